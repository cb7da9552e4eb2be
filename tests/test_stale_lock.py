"""A run killed with SIGKILL leaves Snakemake's lock behind; `python -m pipeline unlock-stale`
(what `make run` does first) removes it, and never the lock of a run that is still alive."""

import json
import os
import signal
import socket
import subprocess
import sys
import time

import pytest

from pipeline.workflow_support import RUNS_DIR, stale_lock

# The project Snakefile's hooks, on a rule that takes long enough to be killed.
SNAKEFILE = """
from pipeline.workflow_support import record_run_end, record_run_start

onstart:
    record_run_start()

onsuccess:
    record_run_end()

onerror:
    record_run_end()

rule all:
    output: "done.txt"
    shell: "sleep 120; touch {output}"
"""


def run(*args, cwd):
    return subprocess.run([sys.executable, *args], cwd=cwd, capture_output=True, text=True)


def unlock_stale(cwd):
    return run("-m", "pipeline", "unlock-stale", cwd=cwd)


def locks(work):
    return sorted((work / ".snakemake" / "locks").glob("*.lock"))


def wait_for(condition, timeout=60.0):
    t0 = time.monotonic()
    while not condition():
        assert time.monotonic() - t0 < timeout, "timed out"
        time.sleep(0.2)


def test_lock_of_a_killed_run_is_removed_and_a_live_ones_kept(tmp_path):
    (tmp_path / "Snakefile").write_text(SNAKEFILE)
    live = subprocess.Popen(
        [sys.executable, "-m", "snakemake", "--cores", "1"],
        cwd=tmp_path,
        start_new_session=True,
        stdout=subprocess.DEVNULL,
        stderr=subprocess.DEVNULL,
    )
    try:
        wait_for(lambda: list((tmp_path / RUNS_DIR).glob("*.json")) and locks(tmp_path))
        proc = unlock_stale(tmp_path)  # the run is alive: its lock stays
        assert proc.returncode == 0 and f"pid {live.pid}" in proc.stderr and "holds the lock" in proc.stderr
        assert locks(tmp_path)
    finally:
        os.killpg(live.pid, signal.SIGKILL)  # snakemake, its job's shell and sleep
        live.wait()
    assert locks(tmp_path)
    blocked = run("-m", "snakemake", "--cores", "1", cwd=tmp_path)
    assert blocked.returncode != 0 and "LockException" in blocked.stderr

    proc = unlock_stale(tmp_path)
    assert proc.returncode == 0, proc.stderr
    assert f"pid {live.pid}" in proc.stderr and "ended without unlocking it" in proc.stderr
    assert not locks(tmp_path) and not list((tmp_path / RUNS_DIR).glob("*.json"))
    proc = unlock_stale(tmp_path)  # nothing left to say
    assert proc.returncode == 0 and proc.stderr == ""


def fake_lock(work, *, record=None, lock_time=None):
    lockdir = work / ".snakemake" / "locks"
    lockdir.mkdir(parents=True, exist_ok=True)
    (lockdir / "0.output.lock").write_text(f"{work}/done.txt\n")
    if lock_time is not None:
        os.utime(lockdir / "0.output.lock", (lock_time, lock_time))
    if record is not None:
        (work / RUNS_DIR).mkdir(parents=True, exist_ok=True)
        (work / RUNS_DIR / f"{record['host']}.{record['pid']}.json").write_text(json.dumps(record))


def dead_pid():
    proc = subprocess.Popen([sys.executable, "-c", "pass"])
    proc.wait()
    return proc.pid, time.time() - 5.0


@pytest.mark.parametrize(
    "case, state, words",
    [
        ("no record", "unknown", "no record of the run that took it; if no Snakemake runs in"),
        ("other host", "unknown", "started on far-away-node"),
        ("lock newer than the dead run", "unknown", "no record of the run that took it"),
        ("dead run took it", "stale", "has ended without unlocking it"),
    ],
)
def test_only_a_lock_taken_by_a_run_known_dead_is_stale(tmp_path, case, state, words):
    pid, created = dead_pid()
    rec = {"host": socket.gethostname(), "pid": pid, "create_time": created, "started": created + 1.0}
    if case == "no record":
        fake_lock(tmp_path)
    elif case == "other host":
        fake_lock(tmp_path, record={**rec, "host": "far-away-node"}, lock_time=created + 0.5)
    elif case == "lock newer than the dead run":  # another run locked the folder after the dead one
        fake_lock(tmp_path, record=rec, lock_time=created + 60.0)
    else:
        fake_lock(tmp_path, record=rec, lock_time=created + 0.5)
    got, message = stale_lock(tmp_path)
    assert got == state and words in message
    if state == "unknown":
        assert message.endswith("type: snakemake --unlock") or "holds" in message


def test_no_lock_no_message(tmp_path):
    assert stale_lock(tmp_path) == ("none", "")
