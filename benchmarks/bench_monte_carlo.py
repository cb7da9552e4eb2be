"""Cost of the Monte Carlo in stages 4 and 5 against its size: time, time per sample, peak memory.

One generated tip (5 intervals n = 2..6, the 4 traction laws, the 200-point h grid of
config/config.yaml, auto solver mode), each size in a fresh process so that the peak resident
memory is that size's.  The schema maximum of ``monte_carlo.samples`` is the largest size whose
stages 4 + 5 stay within about a minute on one of our cores with a few GB of memory.

Usage: python benchmarks/bench_monte_carlo.py [sizes, default 2000,10000,50000]
"""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

CHILD = r"""
import json, resource, sys, tempfile
sys.path.insert(0, {bench!r})
from pathlib import Path
from bench_pipeline_inversion import CASES, run_case
S = int(sys.argv[1])
with tempfile.TemporaryDirectory() as d:
    r = run_case(Path(d), next(iter(CASES.values())), "auto", S)
    size = sum(p.stat().st_size for p in Path(d).iterdir())
print(json.dumps(dict(t_inv=r["t_inv"], t_rng=r["t_rng"], h_err=r["h_err"], ci=r["ci_rel"], files=size,
                      rss=resource.getrusage(resource.RUSAGE_SELF).ru_maxrss * 1024)))
"""


def main(sizes):
    code = CHILD.format(bench=str(Path(__file__).parent))
    print(
        f"{'samples':>8s} {'inversion s':>11s} {'range s':>8s} {'total s':>8s} {'us/sample':>9s} {'peak GB':>8s} "
        f"{'files MB':>8s} {'h err %':>8s} {'CI95 width %':>12s}"
    )
    for S in sizes:
        out = subprocess.run([sys.executable, "-c", code, str(S)], check=True, capture_output=True, text=True).stdout
        r = json.loads(out.strip().splitlines()[-1])
        tot = r["t_inv"] + r["t_rng"]
        print(
            f"{S:8d} {r['t_inv']:11.2f} {r['t_rng']:8.2f} {tot:8.2f} {1e6 * tot / S:9.0f} {r['rss'] / 1e9:8.2f} "
            f"{r['files'] / 1e6:8.0f} {100 * r['h_err']:+8.2f} {100 * r['ci']:12.1f}"
        )


if __name__ == "__main__":
    main([int(x) for x in sys.argv[1].split(",")] if len(sys.argv) > 1 else [2000, 10000, 50000])
