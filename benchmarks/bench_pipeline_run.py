"""Whole-pipeline benchmark on data_samples/: run time per stage and h / W_A error.

1. Runs the full `snakemake` workflow on the bundled sample wear test in a scratch
   results folder and prints the wall time and, from the rules' `benchmark:` files,
   the time of every stage (summed over jobs).
2. Re-runs only the inversion and adhesion-range stages for each solver mode
   (auto, mdn, rigid) and Monte Carlo sample count, and prints the global h and W_A
   of every tip against the ground truth in data_samples/<tip>/truth.yaml:
   the run-time vs error table of the pipeline.

Run:  python benchmarks/bench_pipeline_run.py [--cores 2] [--samples 200,2000,10000]
It prints tables; it never fails on time.
"""

from __future__ import annotations

import argparse
import csv
import shutil
import subprocess
import sys
import tempfile
import time
from collections import defaultdict
from pathlib import Path

import yaml

ROOT = Path(__file__).resolve().parents[1]
SNAKEMAKE = [sys.executable, "-m", "snakemake"]


def run_snakemake(results: Path, cores: int, overrides: dict) -> float:
    with open(ROOT / "config" / "config.yaml") as fh:
        cfg = yaml.safe_load(fh)
    cfg.update(overrides, results_dir=str(results))
    results.mkdir(parents=True, exist_ok=True)
    cfg_path = results.parent / f"{results.name}.config.yaml"
    cfg_path.write_text(yaml.safe_dump(cfg))
    cmd = SNAKEMAKE + ["--cores", str(cores), "--quiet", "all", "--configfile", str(cfg_path)]
    t0 = time.perf_counter()
    proc = subprocess.run(cmd, cwd=ROOT, capture_output=True, text=True)
    dt = time.perf_counter() - t0
    if proc.returncode != 0:
        print(proc.stdout[-3000:], proc.stderr[-3000:], sep="\n")
        raise SystemExit(f"snakemake failed (exit {proc.returncode})")
    return dt


def stage_times(results: Path) -> dict[str, float]:
    totals = defaultdict(float)
    for tsv in (results / "benchmarks").rglob("*.tsv"):
        rel = tsv.relative_to(results / "benchmarks").parts
        stage = rel[1] if len(rel) > 2 else Path(rel[-1]).stem
        with open(tsv) as fh:
            row = next(csv.DictReader(fh, delimiter="\t"))
        totals[stage] += float(row["s"])
    return dict(totals)


def truth_by_tip() -> dict[str, dict]:
    out = {}
    for truth in sorted((ROOT / "data_samples").glob("*/truth.yaml")):
        with open(truth) as fh:
            out[truth.parent.name] = yaml.safe_load(fh)
    return out


def summary_rows(results: Path) -> list[dict]:
    with open(results / "summary.csv") as fh:
        return list(csv.DictReader(fh))


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--cores", type=int, default=2)
    ap.add_argument("--samples", default="200,2000,10000")
    args = ap.parse_args()
    truths = truth_by_tip()
    with tempfile.TemporaryDirectory(prefix="bench_run_") as tmp:
        base = Path(tmp) / "full"
        wall = run_snakemake(base, args.cores, {})
        times = stage_times(base)
        print(f"\nWhole run on data_samples/ ({args.cores} cores): {wall:.1f} s wall (target < 60 s)")
        print(f"{'stage':<22}{'sum of job times [s]':>22}")
        for stage, s in sorted(times.items(), key=lambda kv: -kv[1]):
            print(f"{stage:<22}{s:>22.2f}")

        print("\nInversion + adhesion range only, against the ground truth (Dugdale law):")
        print(
            f"{'mode':<7}{'MC':>7}{'time [s]':>10}  "
            + "  ".join(f"{t + ' h err %':>18}{'W err %':>9}{'in CI':>6}" for t in truths)
        )
        for mode in ("auto", "mdn", "rigid"):
            for samples in [int(s) for s in args.samples.split(",")]:
                res = Path(tmp) / f"{mode}_{samples}"
                shutil.copytree(
                    base,
                    res,
                    ignore=shutil.ignore_patterns("inversion.h5", "adhesion_range.h5", "summary.csv", "*_report.csv"),
                )
                dt = run_snakemake(
                    res, args.cores, {"solver_mode": mode, "monte_carlo": {"samples": samples, "seed": 1}}
                )
                rows = {(r["tip"], r["law"]): r for r in summary_rows(res)}
                cells = []
                for tip, truth in truths.items():
                    r = rows.get((tip, "dugdale"))
                    if r is None or not r.get("h_nm"):
                        cells.append(f"{'n/a':>18}{'':>9}{'':>6}")
                        continue
                    h, lo, hi = float(r["h_nm"]), float(r["h_low_nm"]), float(r["h_high_nm"])
                    h_true = truth["h_m"] * 1e9
                    w_err = 100 * (float(r["W_A_mJ_per_m2"]) / (truth["W_A_J_per_m2"] * 1e3) - 1)
                    cells.append(
                        f"{100 * (h / h_true - 1):>18.2f}{w_err:>9.2f}{('yes' if lo <= h_true <= hi else 'NO'):>6}"
                    )
                print(f"{mode:<7}{samples:>7}{dt:>10.2f}  " + "  ".join(cells))


if __name__ == "__main__":
    main()
