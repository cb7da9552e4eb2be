"""Per-job overhead on SLURM: the sample run through profiles/slurm with one cluster job per rule
and grouped per tip (the profile as it is).

    sudo scripts/slurm_local.sh start --accounting     # or any SLURM cluster with sacct
    python benchmarks/bench_slurm_grouping.py

Per variant: the cluster jobs, their summed SLURM time (sacct Elapsed, i.e. what the allocation
cost), the work in them (the rules' own benchmark wall times), the time per rule job outside its
work ((SLURM time - work) / rule jobs) and the wall time of the whole run (submission, queueing,
status polling included). Without a SLURM whose `sacct` answers it says so and exits 0.
"""

from __future__ import annotations

import csv
import os
import re
import shutil
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import yaml

ROOT = Path(__file__).resolve().parents[1]
PROFILE = ROOT / "profiles" / "slurm" / "config.yaml"
GROUPING_KEYS = ("groups", "group-components", "resources", "set-resource-scopes")


def cluster_with_accounting() -> bool:
    try:
        return subprocess.run(["sacct", "-n", "-X", "-S", "now"], capture_output=True, timeout=30).returncode == 0
    except (OSError, subprocess.TimeoutExpired):
        return False


def profile_variant(folder: Path, grouped: bool) -> Path:
    cfg = yaml.safe_load(PROFILE.read_text())
    if not grouped:
        for key in GROUPING_KEYS:
            cfg.pop(key, None)
    folder.mkdir(parents=True)
    (folder / "config.yaml").write_text(yaml.safe_dump(cfg, sort_keys=False))
    return folder


def run(workdir: Path, profile: Path) -> dict[str, float]:
    workdir.mkdir(parents=True)
    shutil.copytree(ROOT / "config", workdir / "config")
    (workdir / "data_samples").symlink_to(ROOT / "data_samples")
    env = {**os.environ, "PYTHONPATH": str(ROOT), "OMP_NUM_THREADS": "1", "OPENBLAS_NUM_THREADS": "1"}
    t0 = time.monotonic()
    proc = subprocess.run(
        [
            sys.executable,
            "-m",
            "snakemake",
            "-s",
            str(ROOT / "Snakefile"),
            "--directory",
            str(workdir),
            "--profile",
            str(profile),
        ],
        capture_output=True,
        text=True,
        env=env,
    )
    wall = time.monotonic() - t0
    if proc.returncode != 0:
        raise SystemExit(proc.stderr[-3000:])
    run_id = re.search(r"SLURM run ID: (\S+)", proc.stderr).group(1)
    time.sleep(2)  # let slurmdbd record the last job
    sacct = subprocess.run(
        ["sacct", "-X", "-n", "-P", "--name", run_id, "-S", "now-1day", "-o", "ElapsedRaw"],
        capture_output=True,
        text=True,
        check=True,
    ).stdout.split()
    work, rule_jobs = 0.0, 0
    for tsv in (workdir / "results" / "benchmarks").rglob("*.tsv"):
        with open(tsv, newline="") as fh:
            for row in csv.DictReader(fh, delimiter="\t"):
                work += float(row["s"])
                rule_jobs += 1
    return {
        "jobs": len(sacct),
        "slurm_s": sum(map(float, sacct)),
        "work_s": work,
        "rule_jobs": rule_jobs,
        "wall_s": wall,
        "summary": (workdir / "results" / "summary.csv").read_bytes(),
    }


def main() -> int:
    if not cluster_with_accounting():
        print("skipped: needs a SLURM cluster whose sacct answers (sudo scripts/slurm_local.sh start --accounting)")
        return 0
    rows = []
    with tempfile.TemporaryDirectory() as tmp:
        for name, grouped in (("one job per rule", False), ("grouped per tip", True)):
            profile = profile_variant(Path(tmp) / f"profile_{grouped}", grouped)
            rows.append((name, run(Path(tmp) / f"run_{grouped}", profile)))
    print(
        f"{'profile':<18} {'cluster jobs':>12} {'SLURM time s':>12} "
        f"{'work s':>7} {'outside work s/rule job':>24} {'wall s':>7}"
    )
    for name, r in rows:
        overhead = (r["slurm_s"] - r["work_s"]) / r["rule_jobs"]
        print(
            f"{name:<18} {r['jobs']:>12} {r['slurm_s']:>12.0f} "
            f"{r['work_s']:>7.1f} {overhead:>24.1f} {r['wall_s']:>7.0f}"
        )
    print("summary.csv identical in both runs:", rows[0][1]["summary"] == rows[1][1]["summary"])
    return 0


if __name__ == "__main__":
    sys.exit(main())
