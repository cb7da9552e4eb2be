"""Fast path: tabulated elastic pull-off of the L-J, Tri1 and Tri2 laws over (n, Lambda).

Tabulated: y_law(n, Lambda) = log(P~_law / P~_MDn), the elastic pull-off of the law (direct
solve, :mod:`.elastic_contact`, grid level 4: within 0.13 % of M-D-n for the Dugdale law) over the
M-D-n (Dugdale) pull-off at the same (n, Lambda); the fast path is
P~_law = P~_MDn(fast table, :mod:`.tables`) * exp(y_law).  y is bounded and smooth: log of the
rigid ratio (paper Fig. 8) for Lambda -> 0, 0 for Lambda -> inf
(JKR: only W_A matters).  Grid: 16 nodes uniform in log n over [2, 20] x 32 nodes uniform in
log Lambda over [1e-3, 30]; bicubic interpolating spline.  Outside the Lambda range y is held at
its end value: below 1e-3 the elastic corrections are < 2e-5 (rigid limit), above 30 every law
is within 0.1 % of M-D-n (measured when the table was built; both in the data file).

Building the table takes ~5-10 min on one core (1536 direct solves), so the table is committed
as ``data/elastic_pulloff_table.npz`` (written by ``python -m
pipeline.mechanics.build_elastic_table``), keyed by a hash of the grid definition and the
solver version.  If that file is missing or its key does not match, the
table is built once and cached under the user cache directory like the M-D-n table
(``tables.table_path``'s directory).
"""

from __future__ import annotations

import functools
import hashlib
import json
import logging
import os
import tempfile
import time
from pathlib import Path

import numpy as np
from scipy.interpolate import RectBivariateSpline

from .mdn import pulloff_mdn_exact

__all__ = [
    "TABLE_LAWS",
    "ELASTIC_TABLE_SPEC",
    "DATA_FILE",
    "build_elastic_table",
    "load_elastic_table",
    "log_ratio_to_mdn",
    "lambda_boundary_law",
    "table_error",
]

log = logging.getLogger(__name__)

TABLE_LAWS = ("lj", "tri1", "tri2")
SOLVER_VERSION = "elastic-4"
ELASTIC_TABLE_SPEC = dict(n_lo=2.0, n_hi=20.0, n_nodes=16, lam_lo=1e-3, lam_hi=30.0, lam_nodes=32, level=4.0, k=3)
DATA_FILE = Path(__file__).with_name("data") / "elastic_pulloff_table.npz"


def _key():
    text = repr(sorted(ELASTIC_TABLE_SPEC.items())) + SOLVER_VERSION
    return hashlib.sha1(text.encode()).hexdigest()[:12]


def grid():
    """Node coordinates (log n, log Lambda)."""
    sp = ELASTIC_TABLE_SPEC
    return (
        np.linspace(np.log(sp["n_lo"]), np.log(sp["n_hi"]), sp["n_nodes"]),
        np.linspace(np.log(sp["lam_lo"]), np.log(sp["lam_hi"]), sp["lam_nodes"]),
    )


def _solve_node(args):
    from .elastic_contact import elastic_pulloff

    law, n, lam = args
    level = ELASTIC_TABLE_SPEC["level"]
    for lev in (level, 1.25 * level, 0.8 * level):  # a neighbouring grid if a path stalls
        try:
            r = elastic_pulloff(n, lam, law, level=lev)
            return np.log(r.pulloff_nd / float(pulloff_mdn_exact(n, lam)))
        except RuntimeError as exc:
            err = exc
    raise RuntimeError(f"elastic table node {law} n = {n:g}, Lambda = {lam:g}: {err}")


def compute_law(law, processes=1):
    """y_law on the grid by direct solves (processes > 1: a multiprocessing pool)."""
    s, x = grid()
    jobs = [(law, float(np.exp(a)), float(np.exp(b))) for a in s for b in x]
    if processes > 1:
        import multiprocessing as mp

        with mp.get_context("spawn").Pool(processes) as pool:
            vals = pool.map(_solve_node, jobs, chunksize=4)
    else:
        vals = [_solve_node(j) for j in jobs]
    return np.asarray(vals, float).reshape(s.size, x.size)


def build_elastic_table(path=DATA_FILE, processes=1):
    """Compute every law's table and write it (atomically) to ``path``; returns the arrays."""
    s, x = grid()
    out = {
        "s": s,
        "x": x,
        "key": np.array(_key()),
        "spec": np.array(json.dumps(ELASTIC_TABLE_SPEC)),
        "solver_version": np.array(SOLVER_VERSION),
    }
    t0 = time.perf_counter()
    for law in TABLE_LAWS:
        out[f"y_{law}"] = compute_law(law, processes)
        log.info("elastic table %s done (%.0f s)", law, time.perf_counter() - t0)
    out["build_seconds"] = np.array(time.perf_counter() - t0)
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(dir=path.parent, suffix=".npz")
    with os.fdopen(fd, "wb") as fh:
        np.savez(fh, **out)
    os.replace(tmp, path)
    return out


def _cache_path():
    from .tables import table_path

    return table_path().parent / f"elastic_pulloff_table_{_key()}.npz"


def _read(path):
    try:
        with np.load(path) as f:
            if str(f["key"]) == _key():
                return {k: f[k] for k in f.files}
    except (OSError, KeyError, ValueError):
        pass
    return None


def load_elastic_table():
    """The table arrays: the committed data file, else the user cache, else built now (~10 min)."""
    for path in (DATA_FILE, _cache_path()):
        data = _read(path)
        if data is not None:
            return data
    log.warning("elastic pull-off table not found or out of date: building it (5-10 min, once)")
    return build_elastic_table(_cache_path())


@functools.cache
def _spline(law):
    data = load_elastic_table()
    k = ELASTIC_TABLE_SPEC["k"]
    return RectBivariateSpline(data["s"], data["x"], data[f"y_{law}"], kx=k, ky=k, s=0)


def log_ratio_to_mdn(law, n, log_lam, dx=0):
    """y_law = log(P~_law / P~_MDn) (or its dx-th derivative in log Lambda) at (n, log Lambda);
    held at the end values outside [1e-3, 30] (derivative 0 there).  Broadcasting."""
    if law not in TABLE_LAWS:
        raise ValueError(f"no elastic table for law {law!r}; tabulated: {TABLE_LAWS}")
    n, log_lam = np.broadcast_arrays(np.asarray(n, float), np.asarray(log_lam, float))
    s, x = grid()
    xc = np.clip(log_lam, x[0], x[-1])
    out = _spline(law).ev(np.log(n).ravel(), xc.ravel(), dy=dx).reshape(n.shape)
    if dx:
        out = np.where((log_lam < x[0]) | (log_lam > x[-1]), 0.0, out)
    return out


@functools.cache
def _boundary_nodes(law):
    """log n and log Lambda_b,law(n) on 181 nodes: where the rigid pull-off of the law exceeds
    its elastic pull-off by 5 % (the paper's criterion behind Eq. 13, applied to this law)."""
    from scipy.optimize import brentq

    from .rigid import rigid_pulloff_ratio
    from .tables import log_pulloff_fast

    s, x = grid()
    ls = np.linspace(s[0], s[-1], 181)
    out = np.empty(ls.size)
    for i, l in enumerate(ls):
        n = float(np.exp(l))
        rig0 = np.log(float(rigid_pulloff_ratio(n, law))) + 2.0 / n * np.log(n)

        def excess(xx, n=n, rig0=rig0):  # brentq calls it in this iteration
            el = float(log_pulloff_fast(n, xx)) + float(log_ratio_to_mdn(law, n, xx))
            return rig0 + (n - 2.0) / n * xx - el - np.log(1.05)

        out[i] = brentq(excess, x[0], x[-1], xtol=1e-10)
    return ls, out


def lambda_boundary_law(law, n):
    """Lambda_b of a non-Dugdale law: the rigid limit of the law is within 5 % of its elastic
    pull-off for Lambda < Lambda_b,law(n) (from the table; for Dugdale use Eq. 13)."""
    ls, lb = _boundary_nodes(law)
    return np.exp(np.interp(np.log(np.asarray(n, float)), ls, lb))


def table_error(law, n, lam):
    """Relative difference fast path / direct solve at (n, Lambda) (for tests and benchmarks)."""
    from .elastic_contact import elastic_pulloff

    direct = elastic_pulloff(n, lam, law, level=ELASTIC_TABLE_SPEC["level"]).pulloff_nd
    fast = float(pulloff_mdn_exact(n, lam)) * float(np.exp(log_ratio_to_mdn(law, n, np.log(lam))))
    return fast / direct - 1.0
