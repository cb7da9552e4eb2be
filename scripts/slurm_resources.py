#!/usr/bin/env python3
"""Cluster resources per rule from the rules' own Snakemake benchmark files.

    python scripts/slurm_resources.py results/benchmarks            # table + set-resources block
    python scripts/slurm_resources.py results/benchmarks --tsv > profiles/slurm/benchmarks.tsv

Every rule writes a benchmark TSV (wall time ``s``, peak memory ``max_rss`` in MB, ``cpu_time``)
under ``results/benchmarks/``. For each rule the slowest and largest of its jobs are taken and
turned into SLURM requests with a safety margin:

- ``runtime`` (minutes) = ceil((STARTUP_S + RUNTIME_FACTOR * s_max) / 60): a cluster job first
  starts Snakemake twice (the job step and the job itself parse the workflow: STARTUP_S = 30 s,
  several times the 4-8 s a cluster job of this workflow spent outside its stage on the local test
  cluster), and real images
  and curve sets may be several times the sample's size or the node slower (RUNTIME_FACTOR = 10).
  At the sample's size every rule gets the 1-minute minimum: start-up dominates;
- ``mem_mb`` = MEM_FACTOR * max_rss + SNAKEMAKE_MB, rounded up to 100 MB: the job's memory limit
  also holds the two Snakemake processes of a cluster job (SNAKEMAKE_MB = 500, measured 2 x 140
  MB for this workflow), and the stage's own peak is doubled for larger inputs (MEM_FACTOR = 2);
- ``cpus_per_task`` = the rule's mean CPU load rounded up (cpu_time / s; 1 for every stage now,
  they are single-threaded numpy).

A group job (profiles/slurm groups the jobs of a tip) runs its jobs one after another and asks
for the sum of their runtimes and the largest of their memory requests (Snakemake computes it).
"""

from __future__ import annotations

import argparse
import csv
import math
import sys
from pathlib import Path

STARTUP_S = 30.0
RUNTIME_FACTOR = 10.0
MEM_FACTOR = 2.0
SNAKEMAKE_MB = 500.0


def rule_of(tsv: Path, root: Path) -> str:
    """The rule a benchmark file belongs to, from its path below ``root``.

    ``<rule>.tsv`` (summary), ``<tip>/<rule>.tsv`` (per tip), ``<tip>/<rule>/<interval>.tsv``."""
    parts = tsv.relative_to(root).parts
    return parts[1] if len(parts) == 3 else Path(parts[-1]).stem


def read_benchmarks(root: Path) -> dict[str, dict[str, float]]:
    """Per rule: number of jobs, largest wall time ``s_max`` (s), largest ``max_rss_mb`` and
    largest mean CPU load (cpu_time / s)."""
    stats: dict[str, dict[str, float]] = {}
    for tsv in sorted(root.rglob("*.tsv")):
        with open(tsv, newline="") as fh:
            rows = list(csv.DictReader(fh, delimiter="\t"))
        for row in rows:
            s, rss, cpu = float(row["s"]), _number(row["max_rss"]), _number(row["cpu_time"])
            st = stats.setdefault(rule_of(tsv, root), {"jobs": 0, "s_max": 0.0, "max_rss_mb": 0.0, "load_max": 0.0})
            st["jobs"] += 1
            st["s_max"] = max(st["s_max"], s)
            st["max_rss_mb"] = max(st["max_rss_mb"], rss)
            st["load_max"] = max(st["load_max"], cpu / s if s > 0 else 0.0)
    if not stats:
        raise SystemExit(f"{root}: no benchmark files (*.tsv) found; run the workflow once first")
    return stats


def _number(text: str) -> float:
    return float(text) if text not in ("", "NA", "-") else 0.0


def resources(st: dict[str, float]) -> dict[str, int]:
    """SLURM requests of one rule from its benchmark statistics (see the module docstring)."""
    return {
        "runtime": math.ceil((STARTUP_S + RUNTIME_FACTOR * st["s_max"]) / 60.0),
        "mem_mb": int(100 * math.ceil((MEM_FACTOR * st["max_rss_mb"] + SNAKEMAKE_MB) / 100.0)),
        "cpus_per_task": max(1, math.ceil(st["load_max"] - 0.05)),  # a load of 1.02 is one core
    }


def read_table(tsv: Path) -> dict[str, dict[str, float]]:
    """Statistics as written by ``--tsv`` (the profile keeps the ones its numbers came from)."""
    with open(tsv, newline="") as fh:
        return {
            r["rule"]: {k: float(v) for k, v in r.items() if k != "rule"}
            for r in csv.DictReader((line for line in fh if not line.startswith("#")), delimiter="\t")
        }


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("benchmarks", type=Path, help="results/benchmarks of a finished run, or a --tsv table")
    ap.add_argument("--tsv", action="store_true", help="print the per-rule statistics as TSV instead")
    args = ap.parse_args(argv)
    stats = read_table(args.benchmarks) if args.benchmarks.is_file() else read_benchmarks(args.benchmarks)
    if args.tsv:
        print("# per-rule maxima of Snakemake benchmark files (scripts/slurm_resources.py --tsv)")
        print("rule\tjobs\ts_max\tmax_rss_mb\tload_max")
        for rule, st in sorted(stats.items()):
            print(f"{rule}\t{st['jobs']:.0f}\t{st['s_max']:.2f}\t{st['max_rss_mb']:.1f}\t{st['load_max']:.2f}")
        return 0
    print(
        f"{'rule':<20} {'jobs':>4} {'s_max':>7} {'rss_MB':>7} {'load':>5}  ->  runtime_min mem_mb cpus", file=sys.stderr
    )
    for rule, st in sorted(stats.items()):
        r = resources(st)
        print(
            f"{rule:<20} {st['jobs']:>4.0f} {st['s_max']:>7.2f} {st['max_rss_mb']:>7.1f} {st['load_max']:>5.2f}"
            f"  ->  {r['runtime']:>11} {r['mem_mb']:>6} {r['cpus_per_task']:>4}",
            file=sys.stderr,
        )
    print("set-resources:")
    for rule, st in sorted(stats.items()):
        r = resources(st)
        print(f"  {rule}: {{runtime: {r['runtime']}, mem_mb: {r['mem_mb']}, cpus_per_task: {r['cpus_per_task']}}}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
