"""Cost of the Monte Carlo in stages 4 and 5 against its size: time, time per sample, peak memory.

One generated tip (5 intervals n = 2..6, the 4 traction laws, the 200-point h grid of
config/config.yaml, auto solver mode), each size in a fresh process so that the peak resident
memory is that size's; "CPU s" is the process's CPU time for the two stages (less sensitive
than the wall time to other work on the machine), "us/sample" the wall time per sample.  The
schema maximum of ``monte_carlo.samples`` is the largest size whose stages 4 + 5 stay within a
minute on one of our cores.

Usage: python benchmarks/bench_monte_carlo.py [sizes, default 2000,10000,50000] [--tree DIR ...]

``--tree DIR`` (repeatable) runs the same sizes with the code of another checkout as well (e.g. a
``git worktree`` of an older commit), one row per tree and size, so that a change is measured
against the code before it in the same run.
"""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

CHILD = r"""
import json, resource, sys, tempfile
sys.path[:0] = [sys.argv[2], sys.argv[2] + "/benchmarks"]
from pathlib import Path
from bench_pipeline_inversion import CASES, run_case
S = int(sys.argv[1])
with tempfile.TemporaryDirectory() as d:
    run_case(Path(d), next(iter(CASES.values())), "auto", 20, H=20)  # imports and tables, not timed
    u0 = resource.getrusage(resource.RUSAGE_SELF)
    r = run_case(Path(d), next(iter(CASES.values())), "auto", S)
    u1 = resource.getrusage(resource.RUSAGE_SELF)
    size = sum(p.stat().st_size for p in Path(d).iterdir())
cpu = (u1.ru_utime + u1.ru_stime) - (u0.ru_utime + u0.ru_stime)
print(json.dumps(dict(t_inv=r["t_inv"], t_rng=r["t_rng"], h_err=r["h_err"], ci=r["ci_rel"], files=size, cpu=cpu,
                      rss=u1.ru_maxrss * 1024)))
"""


def main(sizes, trees):
    print(
        f"{'tree':12s} {'samples':>8s} {'inversion s':>11s} {'range s':>8s} {'total s':>8s} {'CPU s':>7s} "
        f"{'us/sample':>9s} {'peak GB':>8s} {'files MB':>8s} {'h err %':>8s} {'CI95 width %':>12s}"
    )
    for S in sizes:
        for tree in trees:
            cmd = [sys.executable, "-c", CHILD, str(S), str(tree)]
            out = subprocess.run(cmd, check=True, capture_output=True, text=True, cwd=tree).stdout
            r = json.loads(out.strip().splitlines()[-1])
            tot = r["t_inv"] + r["t_rng"]
            print(
                f"{Path(tree).name[:12]:12s} {S:8d} {r['t_inv']:11.2f} {r['t_rng']:8.2f} {tot:8.2f} {r['cpu']:7.2f} "
                f"{1e6 * tot / S:9.0f} {r['rss'] / 1e9:8.2f} {r['files'] / 1e6:8.0f} {100 * r['h_err']:+8.2f} "
                f"{100 * r['ci']:12.1f}"
            )


if __name__ == "__main__":
    args = sys.argv[1:]
    trees = [Path(__file__).resolve().parent.parent]
    while "--tree" in args:
        i = args.index("--tree")
        trees.append(Path(args[i + 1]).resolve())
        del args[i : i + 2]
    main([int(x) for x in args[0].split(",")] if args else [2000, 10000, 50000], trees)
