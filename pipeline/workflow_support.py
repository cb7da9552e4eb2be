"""Small helpers for the Snakemake layer (no science here)."""
from __future__ import annotations

import os
import sys


def use_this_interpreter_for_jobs() -> str:
    """Put the directory of the running Python (where ``pipeline`` is installed,
    e.g. ``.venv/bin``) first on PATH, so shell jobs' ``python -m pipeline`` find it.
    Returns the new PATH."""
    here = os.path.dirname(sys.executable)
    path = os.environ.get("PATH", "")
    if path.split(os.pathsep)[0] != here:
        os.environ["PATH"] = here + os.pathsep + path
    return os.environ["PATH"]
