"""Benchmark of stages 4+5 (inversion + adhesion range) on generated wear tests with known truth.

For each case the pull-off forces come from the exact M-D-n solve
(pulloff_force(model="mdn", exact=True)) with noise on the curves (4 %/curve, 64 curves)
and on the fitted (n, ln R) (0.01, 0.005).  Printed per solver mode and Monte-Carlo sample
count: the error of the global h and W_A (Dugdale), the 95 % CI width of h, and the wall
time of the two stages (all four traction laws, 200-point h grid as in config/config.yaml).
Target: inversion + range < 5 s per tip.

Run:  .venv/bin/python benchmarks/bench_pipeline_inversion.py [--quick]
"""

from __future__ import annotations

import sys
import tempfile
import time
from pathlib import Path

import numpy as np

from pipeline.adhesion_range.stage import run_adhesion_range
from pipeline.inversion.stage import run_inversion
from pipeline.synth.stage_inputs import write_synthetic_inputs

CASES = {
    "paper-like tip A (W=46.7 mJ/m2, h=4.6 nm, E*=165 GPa, R=30 nm, n=2..6)": dict(
        W_A=0.0467, h=4.6e-9, E_star=165e9, R=30e-9, ns=[2, 3, 4, 5, 6], h_grid=(0.2e-9, 10e-9)
    ),
    "elastic (W=1 J/m2, h=0.5 nm, E*=40 GPa, R=10 nm, n=2..6)": dict(
        W_A=1.0, h=0.5e-9, E_star=40e9, R=10e-9, ns=[2, 3, 4, 5, 6], h_grid=(0.1e-9, 5e-9)
    ),
}
LAWS = ["dugdale", "lj", "tri1", "tri2"]


def run_case(tmp: Path, case: dict, mode: str, samples: int, seed: int = 1, H: int = 200):
    ivs = [dict(name="s000", n=case["ns"][0], R=case["R"], reference=True)]
    ivs += [dict(name=f"s{20 * i:03d}", n=n, R=case["R"]) for i, n in enumerate(case["ns"][1:], 1)]
    fits, forces, cfg = write_synthetic_inputs(
        tmp,
        W_A=case["W_A"],
        h=case["h"],
        E_star=case["E_star"],
        intervals=ivs,
        seed=seed,
        sigma_n=0.01,
        sigma_lnR=0.005,
        rel_sd_curve=0.04,
        n_curves=64,
        k=0.2,
        u_k=0.004,
        invols=50e-9,
        u_invols=0.5e-9,
    )
    inv, rng = tmp / "inversion.h5", tmp / "adhesion_range.h5"
    t0 = time.perf_counter()
    run_inversion(
        fits,
        forces,
        inv,
        intervals=cfg,
        E_star=case["E_star"],
        u_E_star=0.05 * case["E_star"],
        h_grid=np.geomspace(*case["h_grid"], H),
        laws=LAWS,
        solver_mode=mode,
        mc_samples=samples,
        seed=seed,
        tip="bench",
    )
    t1 = time.perf_counter()
    res = run_adhesion_range(inv, rng, tip="bench")
    t2 = time.perf_counter()
    g = res["dugdale"]["global"]
    return {
        "h_err": g["h"] / case["h"] - 1.0,
        "W_err": g["W_A"] / case["W_A"] - 1.0,
        "ci_rel": (g["h_pcts"][-1] - g["h_pcts"][0]) / case["h"],
        "covered": bool(g["h_pcts"][0] < case["h"] < g["h_pcts"][-1]),
        "t_inv": t1 - t0,
        "t_rng": t2 - t1,
        "status": g["status"],
    }


def main(argv=None):
    argv = sys.argv[1:] if argv is None else argv
    quick = "--quick" in argv
    sample_counts = (200, 1000) if quick else (200, 1000, 5000)
    # warm-up (imports, spline tables) so that the first row is not penalised
    with tempfile.TemporaryDirectory() as d:
        run_case(Path(d), next(iter(CASES.values())), "auto", 20, H=20)
    for name, case in CASES.items():
        print(f"\n{name}")
        print(
            f"{'mode':6s} {'samples':>7s} {'h err %':>8s} {'W err %':>8s} {'h CI95 width %':>15s} {'truth in CI':>11s} "
            f"{'inversion s':>11s} {'range s':>8s} {'total s':>8s}  status"
        )
        for mode in ("mdn", "rigid", "auto"):
            for S in sample_counts:
                with tempfile.TemporaryDirectory() as d:
                    r = run_case(Path(d), case, mode, S)
                print(
                    f"{mode:6s} {S:7d} {100 * r['h_err']:+8.2f} {100 * r['W_err']:+8.2f} {100 * r['ci_rel']:15.1f} "
                    f"{str(r['covered']):>11s} {r['t_inv']:11.2f} {r['t_rng']:8.2f} "
                    f"{r['t_inv'] + r['t_rng']:8.2f}  {r['status']}"
                )
    print("\n(4 traction laws, 200-point h grid, MC on a 64-point ln-uniform subset; 2 shared CPU cores)")


if __name__ == "__main__":
    main()
