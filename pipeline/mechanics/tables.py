"""Fast path: tabulated M-D-n (Dugdale) pull-off log P~(n, log Lambda).

The table holds y = log(-min P~) from the direct solve (:mod:`.mdn`) on a tensor grid that is
uniform in log n over [1.8, 21] (48 nodes) and uniform in asinh((x - 1)/4), x = log Lambda, over
[log 1e-7, log 1e7] (240 nodes; densest around the DMT-JKR transition Lambda ~ 1-20).  A
quintic tensor-product interpolating spline (``scipy.interpolate.RectBivariateSpline``, kx=ky=5)
reproduces the direct solve to ~1.5e-8 in y (i.e. relative in P~) over n in [2, 20],
Lambda in [1e-6, 1e6]; the margins keep the spline's end effects outside the supported domain.

Building takes ~0.6-1 s on one core; the table is therefore built lazily once per process
and cached as ``.npz`` under the user cache directory ($PIPELINE_MECHANICS_CACHE, else
$XDG_CACHE_HOME or ~/.cache, sub-directory ``wear-adhesion-pipeline``), keyed by a hash of the
grid definition and solver version.  ``build_table(force=True)`` regenerates it.
"""

from __future__ import annotations

import functools
import hashlib
import os
import tempfile
from pathlib import Path

import numpy as np
from scipy.interpolate import RectBivariateSpline

from .mdn import pulloff_mdn_exact

__all__ = ["TABLE_SPEC", "build_table", "table_path", "log_pulloff_fast", "table_spline", "pulloff_mdn"]

SOLVER_VERSION = "mdn-1"
TABLE_SPEC = dict(n_lo=1.8, n_hi=21.0, n_nodes=48, lam_lo=1e-7, lam_hi=1e7, x_center=1.0, x_width=4.0, x_nodes=240, k=5)


def _key():
    text = repr(sorted(TABLE_SPEC.items())) + SOLVER_VERSION
    return hashlib.sha1(text.encode()).hexdigest()[:12]


def table_path():
    """Location of the cached table file."""
    root = os.environ.get("PIPELINE_MECHANICS_CACHE")
    if root is None:
        base = os.environ.get("XDG_CACHE_HOME") or os.path.join(os.path.expanduser("~"), ".cache")
        root = os.path.join(base, "wear-adhesion-pipeline")
    return Path(root) / f"mdn_pulloff_table_{_key()}.npz"


def grid():
    """Node coordinates (log n, log Lambda) of the table."""
    sp = TABLE_SPEC
    s = np.linspace(np.log(sp["n_lo"]), np.log(sp["n_hi"]), sp["n_nodes"])
    c, w = sp["x_center"], sp["x_width"]
    u = np.linspace(
        np.arcsinh((np.log(sp["lam_lo"]) - c) / w), np.arcsinh((np.log(sp["lam_hi"]) - c) / w), sp["x_nodes"]
    )
    return s, c + w * np.sinh(u)


def _compute():
    s, x = grid()
    return s, x, np.log(pulloff_mdn_exact(np.exp(s)[:, None], np.exp(x)[None, :]))


def build_table(force=False, write=True):
    """Return (log n nodes, log Lambda nodes, log P~ values); load from cache unless ``force``."""
    path = table_path()
    if not force:
        try:
            with np.load(path) as f:
                if str(f["key"]) == _key():
                    return f["s"], f["x"], f["y"]
        except (OSError, KeyError, ValueError):
            pass
    s, x, y = _compute()
    if write:
        try:
            path.parent.mkdir(parents=True, exist_ok=True)
            fd, tmp = tempfile.mkstemp(dir=path.parent, suffix=".npz")
            with os.fdopen(fd, "wb") as fh:
                np.savez(fh, s=s, x=x, y=y, key=np.array(_key()))
            os.replace(tmp, path)
        except OSError:
            pass
    return s, x, y


@functools.lru_cache(maxsize=1)
def table_spline():
    """The interpolating spline (built/loaded once per process)."""
    s, x, y = build_table()
    return RectBivariateSpline(s, x, y, kx=TABLE_SPEC["k"], ky=TABLE_SPEC["k"], s=0)


def log_pulloff_fast(n, log_lam, dx=0):
    """log P~_MDn (or its ``dx``-th derivative in log Lambda) from the table; broadcasting."""
    n, log_lam = np.broadcast_arrays(np.asarray(n, float), np.asarray(log_lam, float))
    out = table_spline().ev(np.log(n).ravel(), log_lam.ravel(), dy=dx)
    return out.reshape(n.shape)


def pulloff_mdn(n, lam, exact=False):
    """M-D-n pull-off -min P~ (> 0; Eqs. 9-11) at validated, broadcast (n, Lambda): the direct
    solve (``exact``) or the table (~1.5e-8 relative)."""
    if exact:
        return pulloff_mdn_exact(n, lam)
    return np.exp(log_pulloff_fast(n, np.log(lam)))
