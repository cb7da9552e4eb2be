"""The reason of a failed job, as the onerror hook prints it (the end-to-end run is in
test_workflow.py): the CLI's error block, a traceback's last line, nothing from a log older
than the run."""

import os
import time

from pipeline.workflow_support import (
    MAX_REASON_LINES,
    FailedJob,
    explain_failed_jobs,
    failure_reason,
    tips_without_result,
)


def write_log(tmp_path, name, text, age=0.0):
    path = tmp_path / name
    path.write_text(text)
    if age:
        t = time.time() - age
        os.utime(path, (t, t))
    return str(path)


def test_reason_is_the_cli_error_block_or_the_last_traceback_line(tmp_path):
    cli = write_log(
        tmp_path,
        "a.log",
        "INFO pipeline.forces: k = 0.9 N/m\nerror (forces): tip 'B' interval 's1': all 2 "
        "force curves were rejected, no output written:\n  c1.csv: flat\n  c2.csv: flat\n",
    )
    assert failure_reason(cli) == [
        "error (forces): tip 'B' interval 's1': all 2 force curves were rejected, no output written:",
        "  c1.csv: flat",
        "  c2.csv: flat",
    ]
    tb = write_log(tmp_path, "b.log", "Traceback (most recent call last):\n  File \"x.py\", line 1\nKeyError: 'tem'\n")
    assert failure_reason(tb) == ["KeyError: 'tem'"]
    long = write_log(tmp_path, "c.log", "error (forces): many\n" + "".join(f"  c{i}.csv: flat\n" for i in range(30)))
    lines = failure_reason(long)
    assert len(lines) == MAX_REASON_LINES and lines[-1] == f"... ({31 - MAX_REASON_LINES + 1} more lines in the log)"
    assert failure_reason(write_log(tmp_path, "d.log", "")) == []
    assert failure_reason(tmp_path / "missing.log") is None


def test_a_log_from_before_the_run_is_not_taken_for_its_reason(tmp_path):
    old = write_log(tmp_path, "old.log", "error (fit): from yesterday\n", age=3600)
    new = write_log(tmp_path, "new.log", "error (fit): today\n")
    jobs = [
        FailedJob("fit", {"tip": "A", "interval": "s0"}, (old,)),
        FailedJob("fit", {"tip": "A", "interval": "s1"}, (new,)),
    ]
    lines = explain_failed_jobs(jobs, since=time.time() - 60)
    assert lines == ["FAILED rule fit (tip=A, interval=s1): error (fit): today", f"    (log: {new})"]
    reasons = tips_without_result(
        jobs, ["A", "B"], lambda tip: str(tmp_path / tip / "adhesion_range.h5"), since=time.time() - 60
    )
    assert reasons["A"].startswith("rule fit (tip=A, interval=s0) failed: no reason in its log")
    assert "rule fit (tip=A, interval=s1) failed: error (fit): today" in reasons["A"]
    assert reasons["B"] == "no result: a job it needs did not run"
