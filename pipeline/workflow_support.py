"""Small helpers for the Snakemake layer (no science here)."""
from __future__ import annotations

import os
import re
import sys
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
