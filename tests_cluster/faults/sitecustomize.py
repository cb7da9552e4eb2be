"""Test-only fault injection for the cluster tests (tests_cluster/): imported by every Python
process started with this folder on PYTHONPATH, it acts only in the one pipeline stage named by
WEAR_FAULT = "<action>:<stage>:<tip>:<interval>", e.g. "sleep:profiles:tipA_DLC:scan030":

- sleep: the stage sleeps for WEAR_FAULT_SECONDS (default 600) before it starts (a hung stage:
  SLURM's time limit or scancel ends it);
- hog: the stage fills WEAR_FAULT_MB (default 3000) MB of memory and holds it (SLURM's memory
  limit ends it).

Nothing in the pipeline knows about it; the stage then runs as usual if it is still alive.
"""

import os
import sys


def _matches(spec: str) -> bool:
    """Is this process `python -m pipeline <stage> --tip-config .../<tip>.yaml --interval <interval>`?"""
    _, stage, tip, interval = spec.split(":")
    argv = sys.orig_argv
    if "-m" not in argv or argv[argv.index("-m") + 1 : argv.index("-m") + 3] != ["pipeline", stage]:
        return False
    if not any(a.endswith(f"/{tip}.yaml") for a in argv):
        return False
    return "--interval" in argv and argv[argv.index("--interval") + 1] == interval


_spec = os.environ.get("WEAR_FAULT", "")
if _spec and _matches(_spec):
    import time

    action = _spec.split(":")[0]
    print(
        f"fault injection ({_spec}) in pid {os.getpid()} SLURM_JOB_ID={os.environ.get('SLURM_JOB_ID')}",
        file=sys.stderr,
        flush=True,
    )
    if action == "sleep":
        time.sleep(float(os.environ.get("WEAR_FAULT_SECONDS", "600")))
    elif action == "hog":
        block = bytearray(int(os.environ.get("WEAR_FAULT_MB", "3000")) * 2**20)
        block[::4096] = b"\x01" * len(block[::4096])  # touch every page: resident, not just reserved
        time.sleep(float(os.environ.get("WEAR_FAULT_SECONDS", "600")))
