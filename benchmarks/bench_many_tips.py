"""Many tips: where the time of a large run goes (issue 19).

Generates ``n_tips`` wear tests of ``n_intervals`` intervals each (the sample tip B's physics
with its own seed, radius, wear path and adhesion per tip; ``pipeline.synth.wear_test``), runs
the whole workflow on them with Snakemake on ``--cores`` cores, and prints the wall time, the
sum of the jobs' own times (the rules' ``benchmark:`` files), the number of jobs, and the share
of the job time that is start-up (jobs x the start-up of their command, measured as in
``bench_startup.py``).

Usage: python benchmarks/bench_many_tips.py [--tips 20] [--intervals 6] [--cores 2]
It prints a table; it never fails on time.
"""

from __future__ import annotations

import argparse
import csv
import dataclasses
import sys
import tempfile
import time
from collections import defaultdict
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).parent))
from bench_pipeline_run import run_snakemake  # noqa: E402
from bench_startup import ENTRIES, LOADS_TIP_CONFIG, entry_module, job_code, wall_time  # noqa: E402

ROOT = Path(__file__).resolve().parents[1]
RULE_COMMAND = {
    "profiles": "profiles",
    "fits": "fit",
    "forces": "forces",
    "inversion": "inversion",
    "adhesion_range": "adhesion-range",
}


def make_tips(root: Path, n_tips: int, n_intervals: int) -> Path:
    from pipeline.synth.wear_test import sample_tips, write_sample_bundle

    base = sample_tips()[1]
    rng = np.random.default_rng(2026)
    tips = []
    for i in range(n_tips):
        n_last = rng.uniform(4.5, 6.0)
        tips.append(
            dataclasses.replace(
                base,
                name=f"tip{i:02d}",
                seed=1000 + i,
                R=float(rng.uniform(8e-9, 15e-9)),
                n=[float(x) for x in np.linspace(2.0, n_last, n_intervals)],
                scans=[int(x) for x in np.linspace(0, 100, n_intervals)],
                W_A=float(rng.uniform(0.04, 0.1)),
                h=float(rng.uniform(3e-9, 5.5e-9)),
            )
        )
    write_sample_bundle(out=root / "data", config_dir=root / "tips", tips=tips)
    return root / "tips"


def job_times(results: Path) -> dict:
    """rule -> (jobs, summed seconds) from the benchmark files."""
    out = defaultdict(lambda: [0, 0.0])
    for tsv in (results / "benchmarks").rglob("*.tsv"):
        rel = tsv.relative_to(results / "benchmarks").parts
        rule = rel[1] if len(rel) > 2 else Path(rel[-1]).stem
        with open(tsv) as fh:
            row = next(csv.DictReader(fh, delimiter="\t"))
        out[rule][0] += 1
        out[rule][1] += float(row["s"])
    return dict(out)


def main():
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--tips", type=int, default=20)
    ap.add_argument("--intervals", type=int, default=6)
    ap.add_argument("--cores", type=int, default=2)
    args = ap.parse_args()
    startup = {
        cmd: wall_time(job_code(entry_module(c), cmd in LOADS_TIP_CONFIG))
        for cmd, c in ENTRIES.items()
        if entry_module(c)
    }
    with tempfile.TemporaryDirectory(prefix="bench_many_") as tmp:
        tmp = Path(tmp)
        t0 = time.perf_counter()
        tips_dir = make_tips(tmp, args.tips, args.intervals)
        t_gen = time.perf_counter() - t0
        wall = run_snakemake(tmp / "results", args.cores, {"tips_dir": str(tips_dir)})
        times = job_times(tmp / "results")
    total = sum(s for _, s in times.values())
    jobs = sum(n for n, _ in times.values())
    start = sum(
        min(s, n * startup.get(RULE_COMMAND.get(rule, ""), np.median(list(startup.values()))))
        for rule, (n, s) in times.items()
    )
    print(f"{args.tips} tips x {args.intervals} intervals on {args.cores} cores (generated in {t_gen:.0f} s)")
    print(f"{'rule':<22}{'jobs':>6}{'job time s':>12}{'per job s':>11}")
    for rule, (n, s) in sorted(times.items(), key=lambda kv: -kv[1][1]):
        print(f"{rule:<22}{n:>6}{s:>12.1f}{s / n:>11.2f}")
    print(
        f"wall {wall:.0f} s; job time {total:.0f} s over {jobs} jobs; start-up ~{start:.0f} s "
        f"({100 * start / max(total, 1e-9):.0f} % of the job time)"
    )


if __name__ == "__main__":
    main()
