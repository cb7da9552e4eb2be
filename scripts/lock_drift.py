"""What the running environment has that differs from a lock file (``make test-latest``).

    python scripts/lock_drift.py requirements.lock

Prints one line per package whose installed version differs from its pin (``numpy 2.4.6 ->
2.5.0``), and the installed packages the lock does not have, so that a failing run against the
newest releases names its suspects.  Always exits 0: the test run that follows is the verdict.
"""

from __future__ import annotations

import re
import sys
from importlib import metadata

from packaging.markers import Marker
from packaging.utils import canonicalize_name

_PIN = re.compile(r"^([A-Za-z0-9][A-Za-z0-9._-]*)==([^\s;\\]+)\s*(?:;\s*([^\\]+?))?\s*\\?$")
_HASH = re.compile(r"--hash=sha256:([0-9a-f]{64})")


def read_lock(path) -> dict[str, list[dict]]:
    """Pins of a ``pip-compile``/``uv pip compile --generate-hashes`` file: canonical name ->
    list of ``{"version", "marker" (str or None), "hashes" (list of sha256)}`` (a package may
    be pinned twice, under exclusive markers)."""
    pins: dict[str, list[dict]] = {}
    current = None
    with open(path) as fh:
        for line in fh:
            m = _PIN.match(line.strip())
            if m:
                current = {"version": m.group(2), "marker": m.group(3), "hashes": []}
                pins.setdefault(canonicalize_name(m.group(1)), []).append(current)
            elif current is not None:
                current["hashes"] += _HASH.findall(line)
    return pins


def pinned_here(pins: dict[str, list[dict]]) -> dict[str, str]:
    """The pins that apply to the running interpreter and platform: name -> version."""
    out = {}
    for name, entries in pins.items():
        for e in entries:
            if e["marker"] is None or Marker(e["marker"]).evaluate():
                out[name] = e["version"]
    return out


def drift(lock_path) -> list[str]:
    pinned = pinned_here(read_lock(lock_path))
    installed = {canonicalize_name(d.metadata["Name"]): d.version for d in metadata.distributions()}
    lines = [
        f"{name} {pinned[name]} -> {v}" for name, v in sorted(installed.items()) if name in pinned and v != pinned[name]
    ]
    lines += [
        f"{name} {v} (not in the lock)"
        for name, v in sorted(installed.items())
        if name not in pinned and name not in ("pip", "wear-adhesion-pipeline")
    ]
    lines += [f"{name} {v} pinned, not installed" for name, v in sorted(pinned.items()) if name not in installed]
    return lines


if __name__ == "__main__":
    lock = sys.argv[1] if len(sys.argv) > 1 else "requirements.lock"
    found = drift(lock)
    print(f"== versions that differ from {lock}: {len(found)}")
    print("\n".join(found))
