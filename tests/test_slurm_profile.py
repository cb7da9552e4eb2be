"""The SLURM profile without a cluster (the cluster itself: tests_cluster/, `make test-cluster`).

The profile must name every rule of the workflow and only those, its per-rule resources must be
the ones scripts/slurm_resources.py derives from the benchmark table kept beside it, and a failed
SLURM job must be described from its log (reason, rule, tip, interval).
"""

import importlib.util
import re
import subprocess
from pathlib import Path

import pytest
import yaml

from pipeline.workflow_support import describe_slurm_log, failed_cluster_jobs

ROOT = Path(__file__).resolve().parents[1]
PROFILE = ROOT / "profiles" / "slurm"


def load_script():
    spec = importlib.util.spec_from_file_location("slurm_resources", ROOT / "scripts" / "slurm_resources.py")
    mod = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(mod)
    return mod


def workflow_rules() -> set[str]:
    text = "".join(p.read_text() for p in (ROOT / "workflow_rules").glob("*.smk"))
    return set(re.findall(r"^rule (\w+):", text, re.MULTILINE))


@pytest.fixture(scope="module")
def profile():
    return yaml.safe_load((PROFILE / "config.yaml").read_text())


def test_profile_covers_every_rule_and_groups_each_tip(profile):
    rules = workflow_rules()
    assert set(profile["set-resources"]) == rules
    assert set(profile["groups"]) == rules
    per_tip = {r for r, g in profile["groups"].items() if g == "tip"}
    assert per_tip == rules - {"summary", "rigid_laws_figure"}
    assert profile["executor"] == "slurm"
    # squeue works without accounting; the plugin keeps it while MinJobAge >= 3 x the first interval
    assert profile["slurm-status-command"] == "squeue"
    assert 3 * profile["slurm-init-seconds-before-status-checks"] <= 300


def test_profile_resources_are_derived_from_the_benchmark_table(profile):
    mod = load_script()
    stats = mod.read_table(PROFILE / "benchmarks.tsv")
    assert set(stats) == workflow_rules()
    for rule, st in stats.items():
        assert profile["set-resources"][rule] == mod.resources(st), rule


def test_resource_formula_on_hand_computed_numbers(tmp_path):
    mod = load_script()
    # one rule per layout of the benchmark folder: <rule>.tsv, <tip>/<rule>.tsv, <tip>/<rule>/<iv>.tsv
    head = "s\th:m:s\tmax_rss\tmax_vms\tmax_uss\tmax_pss\tio_in\tio_out\tmean_load\tcpu_time\n"
    files = {
        "summary.tsv": "0.5\t0:00:00\t50\t1\t1\t1\t0\t0\t0\t0.4\n",
        "tA/inversion.tsv": "12.0\t0:00:12\t300.0\t1\t1\t1\t0\t0\t0\t11.9\n",
        "tA/profiles/s1.tsv": "2.0\t0:00:02\t150\t1\t1\t1\t0\t0\t0\t1.9\n",
        "tB/profiles/s1.tsv": "100.0\t0:01:40\t1250\t1\t1\t1\t0\t0\t0\t390\n",
    }
    for name, row in files.items():
        (tmp_path / name).parent.mkdir(parents=True, exist_ok=True)
        (tmp_path / name).write_text(head + row)
    stats = mod.read_benchmarks(tmp_path)
    assert stats["profiles"]["jobs"] == 2 and stats["profiles"]["s_max"] == 100.0
    # (30 s + 10 x 12 s) / 60 = 2.5 -> 3 min; 2 x 300 + 500 = 1100 MB; load 11.9/12 -> 1 CPU
    assert mod.resources(stats["inversion"]) == {"runtime": 3, "mem_mb": 1100, "cpus_per_task": 1}
    # (30 + 1000) / 60 = 17.2 -> 18 min; 2 x 1250 + 500 = 3000 MB; load 3.9 -> 4 CPUs
    assert mod.resources(stats["profiles"]) == {"runtime": 18, "mem_mb": 3000, "cpus_per_task": 4}
    assert mod.resources(stats["summary"]) == {"runtime": 1, "mem_mb": 600, "cpus_per_task": 1}


# Tails of SLURM logs of failed group jobs, as written by SLURM 22.05 and the executor plugin
_JOB = """[Tue Nov 24 19:36:14 2026]
rule {rule}:
    input: data_samples/tipB_Si/tem/scan000.tif
    output: results/tipB_Si/{rule}/{iv}.h5
    jobid: 3
    wildcards: tip=tipB_Si, interval={iv}
    resources: tmpdir=<TBD>, mem_mb=900
"""
_ENDINGS = {
    "its time limit was reached (runtime)": "slurmstepd-vm: error: *** JOB 71 ON vm CANCELLED "
    "AT 2026-11-24T19:37:37 DUE TO TIME LIMIT ***\n",
    "it ran out of memory (mem_mb)": "srun: error: vm: task 0: Out Of Memory\nslurmstepd-vm: "
    "error: Detected 1 oom-kill event(s) in StepId=4.0.\n",
    "it was cancelled (scancel or an administrator)": "slurmstepd-vm: error: *** JOB 80 ON vm "
    "CANCELLED AT 2026-11-24T20:01:02 ***\n",
    "its command failed": "Error in rule forces:\n    message: None\n",
}


@pytest.mark.parametrize("reason", list(_ENDINGS))
def test_failed_slurm_job_is_described_by_its_last_job_and_reason(reason):
    log = _JOB.format(rule="profiles", iv="scan000") + _JOB.format(rule="forces", iv="scan060") + _ENDINGS[reason]
    assert describe_slurm_log(log) == (reason, "forces", "tip=tipB_Si, interval=scan060")


def test_failed_cluster_jobs_reads_the_slurm_logs_named_in_the_run_log(tmp_path):
    slurm_log = tmp_path / ".snakemake" / "slurm_logs" / "group_tip_profiles" / "71.log"
    slurm_log.parent.mkdir(parents=True)
    slurm_log.write_text(_JOB.format(rule="profiles", iv="scan010") + _ENDINGS["its time limit was reached (runtime)"])
    gone = tmp_path / ".snakemake" / "slurm_logs" / "rule_summary" / "72.log"  # deleted: job succeeded
    run_log = tmp_path / "run.log"
    run_log.write_text(
        f"Error in group tip:\n    log: {slurm_log} (check log file(s) for error details)\n"
        f"    log: {slurm_log} (again)\nJob 1 submitted (log: {gone}).\n"
    )
    assert failed_cluster_jobs(run_log) == [
        "SLURM job 71 failed: its time limit was reached (runtime), while running rule profiles "
        f"(tip=tipB_Si, interval=scan010). SLURM log: {slurm_log}"
    ]
    assert failed_cluster_jobs(tmp_path / "missing.log") == []


def test_local_cluster_script_is_valid_bash_and_documents_its_commands():
    subprocess.run(["bash", "-n", str(ROOT / "scripts" / "slurm_local.sh")], check=True)
    usage = subprocess.run(["bash", str(ROOT / "scripts" / "slurm_local.sh")], capture_output=True, text=True)
    assert usage.returncode == 2
    for command in ("install", "start [--accounting]", "status", "env", "stop [--purge]"):
        assert command in usage.stdout
