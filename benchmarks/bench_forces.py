"""Pull-off accuracy and speed on synthetic curves: F_p error vs deflection noise.

Run: .venv/bin/python benchmarks/bench_forces.py [n_curves_per_row]
"""

from __future__ import annotations

import sys
import time

import numpy as np

from pipeline.forces.pulloff import detect_pulloff
from pipeline.synth.force_curves import make_force_curve


def main(n=50):
    k, invols = 0.2, 50e-9
    print(
        f"{'F_p nN':>7} {'noise nm':>8} {'points':>6} {'method':>6} "
        f"{'mean err %':>10} {'rms err %':>9} {'max |err| %':>11} {'ms/curve':>8}"
    )
    for F_p in (2e-9, 10e-9):
        for noise in (0.05e-9, 0.1e-9, 0.2e-9, 0.5e-9):
            for npts in (1000, 4000):
                for method in ("fit", "min"):
                    err, dt = [], 0.0
                    for seed in range(n):
                        c = make_force_curve(
                            F_p, k, invols, seed=seed, noise=noise, tilt=2e5, offset_V=0.1, n_points=npts
                        )
                        m = c.segment == "retract"
                        t0 = time.perf_counter()
                        po = detect_pulloff(-c.height[m], c.deflection_V[m], method=method)
                        dt += time.perf_counter() - t0
                        err.append(k * po.delta * invols / F_p - 1)
                    e = np.array(err) * 100
                    print(
                        f"{F_p * 1e9:7.1f} {noise * 1e9:8.2f} {npts:6d} {method:>6} {e.mean():10.3f} "
                        f"{np.sqrt(np.mean(e**2)):9.3f} {np.abs(e).max():11.3f} {dt / n * 1e3:8.2f}"
                    )


if __name__ == "__main__":
    main(int(sys.argv[1]) if len(sys.argv) > 1 else 50)
