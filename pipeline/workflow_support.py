"""Small helpers for the Snakemake layer (no science here)."""

from __future__ import annotations

import json
import os
import re
import socket
import sys
import time
from dataclasses import dataclass
from pathlib import Path


def use_this_interpreter_for_jobs() -> str:
    """Put the directory of the running Python (where ``pipeline`` is installed,
    e.g. ``.venv/bin``) first on PATH, so shell jobs' ``python -m pipeline`` find it.
    Returns the new PATH."""
    here = os.path.dirname(sys.executable)
    path = os.environ.get("PATH", "")
    if path.split(os.pathsep)[0] != here:
        os.environ["PATH"] = here + os.pathsep + path
    return os.environ["PATH"]


def config_file_for_jobs(configfiles, workflow_config: dict, keys) -> str:
    """The workflow config file from which jobs read the settings ``keys`` themselves (the
    inversion's h grid, laws, ...): the first of Snakemake's ``configfiles`` whose values of
    ``keys`` (validated, SI) are those of the run, ``workflow_config``; relative to the working
    directory where it lies in it, so that a run folder can be copied.  A ConfigError when none
    is: the settings were given with ``--config`` or spread over several files, and a job would
    compute with other values than the run tracks."""
    from pipeline.config import ConfigError, load_workflow_config

    want = {k: workflow_config[k] for k in keys}
    for path in map(str, configfiles):
        cfg = load_workflow_config(path)
        if {k: cfg[k] for k in keys} == want:
            rel = os.path.relpath(os.path.abspath(path))
            return os.path.abspath(path) if rel.startswith(os.pardir) else rel
    raise ConfigError(
        f"{', '.join(map(str, configfiles)) or 'no config file'}: {', '.join(keys)} must be set in one "
        "config file (not with --config, not spread over several --configfile): the jobs read them from it"
    )


# --- failed cluster jobs ------------------------------------------------------------------------
# Snakemake reports a failed SLURM group job as "Error in group <name>" followed by every job of
# the group, without the SLURM state (9.27 drops the executor's message for groups). The SLURM log
# of the job says both why it ended and which job it was running: the job step runs a group's jobs
# one after another and prints each as it starts ("rule <name>: ... wildcards: ...").
_SLURM_LOG = re.compile(r"log: (\S*slurm_logs\S*\.log)")
_JOB_BLOCK = re.compile(r"^(?:local)?rule (\w+):\n((?:    .*\n)+)", re.MULTILINE)
_REASONS = (  # (text in the SLURM log, what it means), first match wins
    ("DUE TO TIME LIMIT", "its time limit was reached (runtime)"),
    ("Out Of Memory", "it ran out of memory (mem_mb)"),
    ("oom-kill event", "it ran out of memory (mem_mb)"),
    ("exceeded memory limit", "it ran out of memory (mem_mb)"),
    ("DUE TO PREEMPTION", "it was preempted"),
    ("DUE TO NODE FAILURE", "its node failed"),
    ("CANCELLED AT", "it was cancelled (scancel or an administrator)"),
)


def describe_slurm_log(text: str) -> tuple[str, str | None, str | None]:
    """Why a SLURM job ended and the last job it started: ``(reason, rule, wildcards)``.

    ``rule``/``wildcards`` are ``None`` where the log names no job; ``reason`` falls back to
    "its command failed" (a non-zero exit of the stage)."""
    reason = next((why for needle, why in _REASONS if needle in text), "its command failed")
    rule = wildcards = None
    for m in _JOB_BLOCK.finditer(text):
        rule = m.group(1)
        wc = re.search(r"^    wildcards: (.*)$", m.group(2), re.MULTILINE)
        wildcards = wc.group(1) if wc else None
    return reason, rule, wildcards


def failed_cluster_jobs(snakemake_log: str | os.PathLike) -> list[str]:
    """One line per failed SLURM job named in a Snakemake run's log: why it ended and the job
    (rule, tip, interval) it was running, with the path of its SLURM log."""
    try:
        text = Path(snakemake_log).read_text(errors="replace")
    except OSError:
        return []
    lines = []
    for path in dict.fromkeys(m.group(1) for m in _SLURM_LOG.finditer(text)):
        jobid = Path(path).stem
        try:
            slurm_text = Path(path).read_text(errors="replace")
        except OSError:
            continue  # the plugin deletes the logs of jobs that succeeded
        reason, rule, wildcards = describe_slurm_log(slurm_text)
        job = f"rule {rule} ({wildcards})" if wildcards else f"rule {rule}" if rule else "no job yet"
        lines.append(f"SLURM job {jobid} failed: {reason}, while running {job}. SLURM log: {path}")
    return lines


def report_failed_cluster_jobs(logs) -> None:
    """Snakemake ``onerror`` hook: print :func:`failed_cluster_jobs` of the run's log(s)."""
    for log in [logs] if isinstance(logs, (str, os.PathLike)) else list(logs or []):
        for line in failed_cluster_jobs(log):
            print(line, file=sys.stderr)


# --- why a job failed, on the console -----------------------------------------------------------
# Each job runs `python -m pipeline <stage> ... > log 2>&1`; its reason is the CLI's last words
# there ("error (<stage>): <file or tip>: <reason>", possibly with one line per rejected curve)
# or, for an unexpected exception, the traceback's last line.  The `onerror` hook prints it, so
# the reason stands on the console right after Snakemake's "Error in rule ..." and log path.
MAX_REASON_LINES = 8


@dataclass(frozen=True)
class FailedJob:
    rule: str
    wildcards: dict
    logs: tuple

    def name(self) -> str:
        wc = ", ".join(f"{k}={v}" for k, v in self.wildcards.items())
        return f"rule {self.rule} ({wc})" if wc else f"rule {self.rule}"


def failure_reason(log_path, *, since: float | None = None) -> list[str] | None:
    """The lines of a failed job's log that say why it failed (at most ``MAX_REASON_LINES``):
    from the CLI's last ``error (...)`` line to the end, else the last line of a traceback or of
    the log; ``[]`` for an empty log.  ``None`` if the log is missing or older than ``since``
    (written before this run: the job did not start in it; 5 s allow for the clocks of a
    cluster's file system)."""
    try:
        if since is not None and os.path.getmtime(log_path) < since - 5.0:
            return None
        lines = [ln.rstrip() for ln in Path(log_path).read_text(errors="replace").splitlines() if ln.strip()]
    except OSError:
        return None
    starts = [i for i, ln in enumerate(lines) if ln.startswith("error (")]
    block = lines[starts[-1] :] if starts else lines[-1:]
    if len(block) > MAX_REASON_LINES:
        block = block[: MAX_REASON_LINES - 1] + [f"... ({len(block) - MAX_REASON_LINES + 1} more lines in the log)"]
    return block


def failed_jobs_of(workflow) -> list[FailedJob]:
    """The jobs that failed in this Snakemake run (from its scheduler; a failed group job
    stands for each job of the group)."""
    failed = getattr(getattr(workflow, "scheduler", None), "failed", None) or ()
    jobs = []
    for job in failed:
        for j in job.jobs if job.is_group() else [job]:
            jobs.append(FailedJob(j.rule.name, dict(j.wildcards.items()), tuple(str(p) for p in j.log)))
    return sorted(jobs, key=lambda j: (j.rule, sorted(j.wildcards.items())))


def explain_failed_jobs(jobs, *, since: float | None = None) -> list[str]:
    """Console lines: for each failed job, its name, the reason from its log and the log's path
    (nothing for a job of a failed group that did not start in this run)."""
    out = []
    for job in jobs:
        if not job.logs:
            out.append(f"FAILED {job.name()} (it has no log: see Snakemake's message above)")
        for log in job.logs:
            reason = failure_reason(log, since=since)
            if reason is None:
                continue
            out.append(f"FAILED {job.name()}: {reason[0] if reason else 'its log is empty (stopped from outside?)'}")
            out += [f"    {ln}" for ln in reason[1:]]
            out.append(f"    (log: {log})")
    return out


# --- one bad tip does not cost the others their results -----------------------------------------
def write_partial_summary(summary_csv, range_h5s: dict, failed: dict) -> list[str]:
    """Write the summary of a run in which some tips failed (Snakemake ``--keep-going``).

    ``range_h5s``: tip -> stage-5 file of the tips that finished; ``failed``: tip -> reason.
    The file is dated one second before the oldest of its inputs, so the next run of Snakemake
    takes it as out of date and writes it anew (a partial summary is never kept as final).
    Returns the console lines that say what was written."""
    from pipeline.adhesion_range.report import write_summary

    write_summary(range_h5s, summary_csv, failed=failed)
    inputs = [os.path.getmtime(p) for p in range_h5s.values()]
    before = (min(inputs) if inputs else time.time()) - 1.0
    os.utime(summary_csv, (before, before))
    done = ", ".join(range_h5s) or "none"
    return [
        f"{summary_csv} written for the tips that finished ({done}); "
        f"without a result: {', '.join(failed)} (their rows say why). The next run rewrites it."
    ]


def tips_without_result(jobs, tips, range_h5_of, *, since: float | None = None) -> dict:
    """tip -> reason (one line) for every tip that has a failed job in this run or no stage-5
    file: which job failed, the first lines of its reason and its log."""
    out = {}
    for tip in tips:
        reasons = []
        for job in (j for j in jobs if j.wildcards.get("tip") == tip):
            why = next(filter(None, (failure_reason(log, since=since) for log in job.logs)), None)
            if why:
                detail = " ".join(" ".join(ln.split()) for ln in why[:2]) + (" ..." if len(why) > 2 else "")
            else:
                detail = "no reason in its log (stopped from outside? see the console)"
            reasons.append(f"{job.name()} failed: {detail}" + (f" (log: {job.logs[0]})" if job.logs else ""))
        if reasons:
            out[tip] = "; ".join(reasons)
        elif not os.path.exists(range_h5_of(tip)):
            out[tip] = "no result: a job it needs did not run"
    return out


def report_failed_run(workflow, log, *, results: str, tips) -> None:
    """Snakemake ``onerror`` hook: say on the console why each job failed (and, on a cluster,
    why SLURM ended it); with ``--keep-going`` write the summary of the tips that finished,
    listing the failed ones with the reason."""
    report_failed_cluster_jobs(log)
    own = read_own_run_record()
    since = own.get("started") if own else None
    jobs = failed_jobs_of(workflow)
    for line in explain_failed_jobs(jobs, since=since):
        print(line, file=sys.stderr)
    summary_csv = f"{results}/summary.csv"
    summary_waits = any(summary_csv in map(str, j.output) for j in _pending_jobs(workflow))
    if not summary_waits or any(j.rule == "summary" for j in jobs):
        return
    if not getattr(getattr(workflow, "execution_settings", None), "keep_going", False):
        print(
            f"{summary_csv} not written (a file there is from an earlier run): run with --keep-going (-k; "
            "`make run` does) to get the summary of the tips that finish",
            file=sys.stderr,
        )
        return

    def range_h5_of(tip):
        return f"{results}/{tip}/adhesion_range.h5"

    failed = tips_without_result(jobs, tips, range_h5_of, since=since)
    good = {tip: range_h5_of(tip) for tip in tips if tip not in failed}
    for line in write_partial_summary(summary_csv, good, failed):
        print(line, file=sys.stderr)


def _pending_jobs(workflow):
    dag = getattr(workflow, "dag", None)
    return list(dag.needrun_jobs(exclude_finished=True)) if dag is not None else []


# --- stale locks ---------------------------------------------------------------------------------
# Snakemake locks the working directory (.snakemake/locks) and unlocks it at the end; a run killed
# with SIGKILL (or a power cut) leaves the lock, and the next run stops with a LockException.  The
# lock does not say whose it is, so every run of this Snakefile records, once it holds the lock
# (`onstart`), its host, pid and process start time, and removes the record at its end.  A lock is
# stale when it was taken by a recorded run (lock written between the run's process start and its
# record) that is no longer alive on this host and no Snakemake runs in this folder.
RUNS_DIR = Path(".snakemake") / "wear_runs"


def _record_path(workdir, host: str, pid: int) -> Path:
    return Path(workdir) / RUNS_DIR / f"{host}.{pid}.json"


def record_run_start(workdir=".") -> Path:
    """Snakemake ``onstart`` hook: record this run (host, pid, process start time, now)."""
    import psutil

    proc = psutil.Process()
    rec = {"host": socket.gethostname(), "pid": proc.pid, "create_time": proc.create_time(), "started": time.time()}
    path = _record_path(workdir, rec["host"], rec["pid"])
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_suffix(".part")
    tmp.write_text(json.dumps(rec))
    os.replace(tmp, path)
    return path


def read_own_run_record(workdir=".") -> dict | None:
    try:
        return json.loads(_record_path(workdir, socket.gethostname(), os.getpid()).read_text())
    except (OSError, ValueError):
        return None


def record_run_end(workdir=".") -> None:
    """Snakemake ``onsuccess``/``onerror`` hook: remove this run's record."""
    _record_path(workdir, socket.gethostname(), os.getpid()).unlink(missing_ok=True)


def _alive(rec: dict) -> bool | None:
    """Whether a recorded run still runs (``None``: it ran on another host, cannot tell)."""
    import psutil

    if rec.get("host") != socket.gethostname():
        return None
    try:
        return abs(psutil.Process(int(rec["pid"])).create_time() - float(rec["create_time"])) < 1.0
    except (psutil.NoSuchProcess, psutil.AccessDenied, KeyError, ValueError):
        return False


def _snakemake_processes_in(workdir) -> list[int]:
    """Pids of Snakemake processes on this host whose working directory is ``workdir``."""
    import psutil

    here = os.path.realpath(workdir)
    pids = []
    for proc in psutil.process_iter(["pid", "cmdline"]):
        try:
            cmd = proc.info["cmdline"] or []
            if (
                proc.pid != os.getpid()
                and any(os.path.basename(a) == "snakemake" for a in cmd[:3])
                and os.path.realpath(proc.cwd()) == here
            ):
                pids.append(proc.pid)
        except (psutil.NoSuchProcess, psutil.AccessDenied, psutil.ZombieProcess):
            continue
    return pids


def _when(t: float) -> str:
    return time.strftime("%Y-%m-%d %H:%M:%S", time.localtime(t))


def stale_lock(workdir=".") -> tuple[str, str]:
    """Is ``workdir`` locked by a Snakemake run that has ended?  ``(state, message)`` with state
    ``"none"`` (no lock), ``"stale"`` (safe to unlock), ``"live"`` (a run holds it) or
    ``"unknown"`` (cannot tell: the message says what to type if the user knows it has ended).
    Records of ended runs are removed."""
    workdir = Path(workdir)
    locks = list((workdir / ".snakemake" / "locks").glob("*.lock"))
    records = []
    for path in (workdir / RUNS_DIR).glob("*.json"):
        try:
            records.append((path, json.loads(path.read_text())))
        except (OSError, ValueError):
            continue
    state = [(path, rec, _alive(rec)) for path, rec in records]
    dead = [rec for path, rec, alive in state if alive is False]
    for path, _rec, alive in state:
        if alive is False:
            path.unlink(missing_ok=True)
    if not locks:
        return "none", ""
    unlock = f"if no Snakemake runs in {os.path.abspath(workdir)} on any machine, type: snakemake --unlock"
    live = [rec for _, rec, alive in state if alive]
    if live:
        rec = live[0]
        return (
            "live",
            f"a Snakemake run (pid {rec['pid']}, started {_when(rec['started'])}) holds the lock of this folder",
        )
    elsewhere = [rec for _, rec, alive in state if alive is None]
    if elsewhere:
        rec = elsewhere[0]
        return "unknown", f"the lock belongs to a run started on {rec['host']} at {_when(rec['started'])}; {unlock}"
    pids = _snakemake_processes_in(workdir)
    if pids:
        return "live", f"Snakemake (pid {', '.join(map(str, pids))}) runs in this folder and holds its lock"
    taken_by_dead = all(
        any(rec["create_time"] - 1.0 <= os.path.getmtime(lock) <= rec["started"] + 1.0 for rec in dead)
        for lock in locks
    )
    if not dead or not taken_by_dead:
        return "unknown", f"Snakemake's lock of this folder has no record of the run that took it; {unlock}"
    rec = dead[0]
    return "stale", (
        f"the run that locked this folder (pid {rec['pid']}, started {_when(rec['started'])}) "
        "has ended without unlocking it (killed?)"
    )
