"""The sample wear test through profiles/slurm on a real (single-node) SLURM: `make test-cluster`.

Not part of the default suite (`make test`): it needs root and Debian's packages slurmctld slurmd
slurm-client munge slurmdbd mariadb-server (`sudo scripts/slurm_local.sh install --accounting`)
and the cluster extra (`pip install -e ".[cluster]"`), and takes ~15 min on 2 cores. Elsewhere
every test is skipped with the reason.

It starts the cluster with scripts/slurm_local.sh (first without job accounting, then with
slurmdbd + MariaDB) and stops it at the end unless it was running before. Each cluster run must
end by itself (a run whose status polling hangs fails at RUN_TIMEOUT_S) and give the summary and
per-tip reports of a local run byte for byte. One failure of each kind is provoked in one named
stage through tests_cluster/faults/sitecustomize.py (a stage that holds 3 GB, or sleeps):
SLURM's memory limit, its time limit and scancel end the cluster job; the workflow must name the
reason, the rule, the tip and the interval, and a rerun must finish the work without repeating
what was done.
"""

from __future__ import annotations

import importlib.util
import os
import re
import shutil
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
SLURM_LOCAL = ROOT / "scripts" / "slurm_local.sh"
FAULTS = Path(__file__).resolve().parent / "faults"
RUN_TIMEOUT_S = 900
CLUSTER_COMMANDS = ("munged", "slurmctld", "slurmd", "sbatch", "squeue", "slurmdbd", "mariadbd", "sacctmgr")


def _skip_reason() -> str | None:
    if os.name != "posix" or os.geteuid() != 0:
        return "needs root: scripts/slurm_local.sh runs munged, slurmctld and slurmd (which starts the jobs) as root"
    missing = [c for c in CLUSTER_COMMANDS if shutil.which(c) is None]
    if missing:
        return (
            f"needs Debian's packages slurmctld slurmd slurm-client munge slurmdbd mariadb-server "
            f"(missing {', '.join(missing)}): scripts/slurm_local.sh install --accounting"
        )
    if importlib.util.find_spec("snakemake_executor_plugin_slurm") is None:
        return 'needs the SLURM executor plugin: pip install -e ".[cluster]"'
    return None


pytestmark = pytest.mark.skipif(_skip_reason() is not None, reason=str(_skip_reason()))


def slurm_local(*args: str) -> str:
    proc = subprocess.run(["bash", str(SLURM_LOCAL), *args], capture_output=True, text=True, timeout=300)
    assert proc.returncode == 0, f"slurm_local.sh {' '.join(args)}:\n{proc.stdout}{proc.stderr}"
    return proc.stdout


@pytest.fixture(scope="module")
def cluster():
    """Starts the local cluster in a mode on request; stops it at the end unless it ran before."""
    was_running = "slurmctld: running" in slurm_local("status")
    before = slurm_local("status").split("mode: ")[-1].split()[0] if was_running else None
    yield lambda mode: slurm_local("start", *(["--accounting"] if mode == "accounting" else []))
    if before:
        slurm_local("start", *(["--accounting"] if before == "accounting" else []))
    else:
        slurm_local("stop")


def make_workdir(path: Path) -> Path:
    """A run folder like the repository's: its own config (copied) and the sample data."""
    path.mkdir(parents=True)
    shutil.copytree(ROOT / "config", path / "config")
    (path / "data_samples").symlink_to(ROOT / "data_samples")
    return path


def job_env(**extra: str) -> dict[str, str]:
    env = {k: v for k, v in os.environ.items() if not k.startswith(("SLURM_", "SBATCH_", "WEAR_FAULT"))}
    env.update(
        PYTHONPATH=f"{FAULTS}{os.pathsep}{ROOT}",
        OMP_NUM_THREADS="1",
        OPENBLAS_NUM_THREADS="1",
        PYTHONWARNINGS="ignore",
        **extra,
    )
    return env


def snakemake_cmd(workdir: Path, *args: str) -> list[str]:
    return [sys.executable, "-m", "snakemake", "-s", str(ROOT / "Snakefile"), "--directory", str(workdir), *args]


def run_on_cluster(workdir: Path, *targets: str, **env: str) -> subprocess.CompletedProcess:
    cmd = snakemake_cmd(workdir, "--profile", str(ROOT / "profiles" / "slurm"), *targets)
    try:
        return subprocess.run(
            cmd, capture_output=True, text=True, cwd=workdir, env=job_env(**env), timeout=RUN_TIMEOUT_S
        )
    except subprocess.TimeoutExpired as exc:
        pytest.fail(
            f"cluster run did not end within {RUN_TIMEOUT_S} s (status polling hangs?):\n"
            f"{(exc.stderr or b'')[-3000:]!r}"
        )


def results_of(workdir: Path) -> dict[str, bytes]:
    res = workdir / "results"
    return {str(p.relative_to(res)): p.read_bytes() for p in [res / "summary.csv", *sorted(res.glob("*/*_report.csv"))]}


def mtimes(workdir: Path, tip: str) -> dict[str, float]:
    return {str(p): p.stat().st_mtime for p in sorted((workdir / "results" / tip).rglob("*")) if p.is_file()}


@pytest.fixture(scope="module")
def local_results(tmp_path_factory) -> dict[str, bytes]:
    work = make_workdir(tmp_path_factory.mktemp("cluster") / "local")
    proc = subprocess.run(
        snakemake_cmd(work, "--cores", "2"),
        capture_output=True,
        text=True,
        cwd=work,
        env=job_env(),
        timeout=RUN_TIMEOUT_S,
    )
    assert proc.returncode == 0, proc.stderr[-3000:]
    return results_of(work)


def assert_reported(output: str, reason: str, rule: str, tip: str, interval: str) -> str:
    """The run's error output has the one-line report of the failed SLURM job; returns its log."""
    m = re.search(
        rf"SLURM job (\d+) failed: {re.escape(reason)}, while running rule {rule} "
        rf"\(tip={tip}, interval={interval}\)\. SLURM log: (\S+)",
        output,
    )
    assert m, f"no report of {rule} {tip} {interval} ({reason}) in:\n{output[-4000:]}"
    assert "Error in group tip" in output
    return m.group(2)


def test_without_accounting_out_of_memory_then_rerun(cluster, local_results, tmp_path_factory):
    cluster("plain")
    work = make_workdir(tmp_path_factory.mktemp("cluster") / "plain")
    failed = run_on_cluster(work, WEAR_FAULT="hog:forces:tipB_Si:scan060", WEAR_FAULT_MB="3000")
    assert failed.returncode != 0
    slurm_log = assert_reported(failed.stderr, "it ran out of memory (mem_mb)", "forces", "tipB_Si", "scan060")
    # the job ran in the interpreter (virtual environment) of the Snakemake that submitted it
    assert f"Command: {sys.prefix}" in Path(slurm_log).read_text()
    assert (work / "results" / "tipA_DLC" / "tipA_DLC_report.csv").is_file()  # the other tip finished
    tip_a = mtimes(work, "tipA_DLC")

    rerun = run_on_cluster(work)
    assert rerun.returncode == 0, rerun.stderr[-4000:]
    assert mtimes(work, "tipA_DLC") == tip_a  # picked up where it stopped: tip A not run again
    assert results_of(work) == local_results


def test_without_accounting_time_limit_then_rerun(cluster, tmp_path_factory):
    cluster("plain")
    work = make_workdir(tmp_path_factory.mktemp("cluster") / "timeout")
    target = "results/tipA_DLC/profiles/scan010.h5"
    # one job: its group asks for the 1-minute runtime of `profiles`; the stage sleeps 10 min
    failed = run_on_cluster(work, target, WEAR_FAULT="sleep:profiles:tipA_DLC:scan010")
    assert failed.returncode != 0
    assert_reported(failed.stderr, "its time limit was reached (runtime)", "profiles", "tipA_DLC", "scan010")
    assert not (work / target).exists()  # no output that looks complete

    rerun = run_on_cluster(work, target)
    assert rerun.returncode == 0, rerun.stderr[-4000:]
    assert (work / target).is_file()


def test_with_accounting_cancelled_then_rerun(cluster, local_results, tmp_path_factory):
    cluster("accounting")
    work = make_workdir(tmp_path_factory.mktemp("cluster") / "accounting")
    cmd = snakemake_cmd(work, "--profile", str(ROOT / "profiles" / "slurm"))
    env = job_env(WEAR_FAULT="sleep:profiles:tipA_DLC:scan030", SBATCH_ACCOUNT="wear")
    with open(work / "run.err", "w") as err:
        proc = subprocess.Popen(cmd, stdout=subprocess.DEVNULL, stderr=err, text=True, cwd=work, env=env)
        stage_log = work / "results" / "logs" / "tipA_DLC" / "profiles" / "scan030.log"
        deadline = time.monotonic() + 600
        jobid = None
        while jobid is None and time.monotonic() < deadline and proc.poll() is None:
            m = (
                re.search(r"fault injection .* SLURM_JOB_ID=(\d+)", stage_log.read_text())
                if stage_log.exists()
                else None
            )
            jobid = m.group(1) if m else None
            time.sleep(2)
        if jobid is None:
            proc.send_signal(signal.SIGINT)
            proc.wait(timeout=120)
            pytest.fail("the hung stage never started")
        subprocess.run(["scancel", jobid], check=True)  # killed, as by a user or an administrator
        try:
            rc = proc.wait(timeout=RUN_TIMEOUT_S)
        except subprocess.TimeoutExpired:
            proc.kill()
            pytest.fail("the run did not end after its job was cancelled")
    output = (work / "run.err").read_text()
    assert rc != 0
    assert_reported(output, "it was cancelled (scancel or an administrator)", "profiles", "tipA_DLC", "scan030")
    # with accounting, sacct knows the jobs and the account they ran under
    sacct = subprocess.run(
        ["sacct", "-X", "-n", "-P", "-j", jobid, "-o", "State,Account"], capture_output=True, text=True, check=True
    ).stdout
    assert sacct.split("\n")[0].split("|")[0].startswith("CANCELLED") and sacct.split("\n")[0].endswith("|wear")
    tip_b = mtimes(work, "tipB_Si")

    rerun = run_on_cluster(work, SBATCH_ACCOUNT="wear")
    assert rerun.returncode == 0, rerun.stderr[-4000:]
    assert mtimes(work, "tipB_Si") == tip_b
    assert results_of(work) == local_results
