"""Public pull-off / work-of-adhesion functions (forward and inverse), all models and potentials.

Models: "rigid" (Eq. 12 and the Sec. 4.3 laws, closed forms), "mdn" (Dugdale only, Eqs. 9-11),
"elastic" (any law: M-D-n for Dugdale, the elastic solver of :mod:`.elastic_contact` for L-J,
Tri1, Tri2 through its table :mod:`.elastic_tables`, direct solves with exact=True) and "auto"
(rigid where Lambda < Lambda_b, else the elastic model of the law).  Lambda_b is the paper's 5 %
boundary of the rigid limit: Eq. 13 for Dugdale, and for each other law its own boundary from the
elastic table (Eq. 13 was fitted for Dugdale: applied to Tri1 it would accept rigid errors up to
28 %, to L-J and Tri2 up to 7-8 %).

Forward:  F_p = pi P~(n, Lambda) P*,  P* = (Q^3 W^(n+1) E*^(n-2))^(1/(2n-1))     (Eqs. 6, 8)
Inverse:  G = F_p / (pi E* h^(1+1/n) Q^(1/n)) = P~(n, Lambda) Lambda^((n+1)/n)  is strictly
increasing in Lambda, so Lambda = G^-1(G; n) and W = (Lambda h)^((2n-1)/n) Q^(-1/n) E*.
No per-point root finding: rigid laws invert in closed form, M-D-n by a few vectorised Newton
steps on the tabulated spline (fast) optionally polished by Newton steps on the direct solve
(exact=True).

model="auto" (Dugdale only): rigid (Eq. 12) where Lambda < Lambda_b(n) (Eq. 13), else M-D-n.
Because F_rigid exceeds F_MDn by up to 5 % at the boundary, the auto forward map F(W) jumps
down by <= 5 % when Lambda crosses Lambda_b, and its inverse is not unique in that band.
work_of_adhesion follows the paper's procedure (Sec. 4.2, steps 1-5): invert Eq. 12 first and
keep it when the implied Lambda < Lambda_b, otherwise use M-D-n.  W_A(h) therefore has one jump
of <= 5 % (W_rigid/W_MDn ~ F_MDn/F_rigid) where Lambda crosses Lambda_b, and forward/inverse
round trips of "auto" are exact except for points with Lambda just above Lambda_b whose
pull-off can also be reached by the rigid branch (there the rigid solution is returned).
"""

from __future__ import annotations

import numpy as np

from . import _validate as V
from .boundary import lambda_boundary
from .elastic_tables import lambda_boundary_law, log_ratio_to_mdn
from .mdn import pulloff_mdn_exact
from .rigid import rigid_pulloff_nd_raw, rigid_pulloff_ratio
from .scaling import _log_lambda, log_force_scale, log_g_group, work_from_lambda
from .tables import log_pulloff_fast, pulloff_mdn

__all__ = [
    "pulloff_nd",
    "pulloff_force",
    "work_of_adhesion",
    "model_used",
    "lambda_from_g",
    "pulloff_with_model",
    "work_of_adhesion_with_model",
    "work_of_adhesion_and_regime",
    "rigid_boundary",
]

#: Lambda above which the direct elastic solve is not run (exact=True): every law is within
#: 0.1 % of M-D-n there (JKR limit) and the table's end value is used.
ELASTIC_DIRECT_MAX = 30.0

_XMIN, _XMAX = np.log(V.LAMBDA_MIN), np.log(V.LAMBDA_MAX)


def _elastic_nd(n, lam, pot, exact):
    """P~ of a non-Dugdale law, elastic: M-D-n x exp(y_law) (table) or direct solves."""
    if not exact:
        x = np.log(lam)
        return np.exp(log_pulloff_fast(n, x) + log_ratio_to_mdn(pot, n, x))
    from .elastic_contact import elastic_pulloff

    out = np.empty(np.shape(n))
    for idx in np.ndindex(out.shape):
        nn, ll = float(n[idx]), float(lam[idx])
        if ll > ELASTIC_DIRECT_MAX:
            out[idx] = pulloff_mdn_exact(nn, ll) * np.exp(log_ratio_to_mdn(pot, nn, np.log(ll)))
        else:
            out[idx] = elastic_pulloff(nn, ll, pot).pulloff_nd
    return out


def rigid_boundary(n, potential="dugdale"):
    """Lambda_b(n) below which model="auto" uses the rigid limit of ``potential`` (5 % criterion):
    Eq. 13 for Dugdale, the law's own boundary (elastic table) for L-J, Tri1, Tri2."""
    pot = V.potential(potential)
    n = V.exponent(n)
    return _out(lambda_boundary(n) if pot == "dugdale" else lambda_boundary_law(pot, n))


def _elastic_model_nd(n, lam, pot, exact):
    return pulloff_mdn(n, lam, exact) if pot == "dugdale" else _elastic_nd(n, lam, pot, exact)


def _out(a):
    return a[()] if isinstance(a, np.ndarray) and a.ndim == 0 else a


def pulloff_nd(n, Lambda, potential="dugdale", model="mdn", exact=False):
    """Non-dimensional pull-off -min P~ (> 0) at (n, Lambda); P~ = P/(pi P*) (Eq. 6).

    model: "mdn" (Eqs. 9-11, Dugdale only), "rigid" (Eq. 12 and Sec. 4.3 laws:
    "dugdale", "lj", "tri1", "tri2"), "elastic" (M-D-n for Dugdale, the elastic solver for the
    other laws), "auto" (rigid where Lambda < Eq. 13 boundary, else elastic).
    exact=False uses the tabulated splines (M-D-n ~1e-8 rel.; other laws: see elastic_tables),
    exact=True the direct solves.
    """
    pot = V.potential(potential)
    mdl = V.model(model, pot)
    n, lam = np.broadcast_arrays(V.exponent(n), V.transition(Lambda))
    if mdl == "rigid":
        return _out(rigid_pulloff_nd_raw(n, lam, pot))
    if mdl in ("mdn", "elastic"):
        return _out(_elastic_model_nd(n, lam, pot, exact))
    out = np.empty(n.shape)
    rig = lam < rigid_boundary(n, pot)
    out[rig] = rigid_pulloff_nd_raw(n[rig], lam[rig], pot)
    out[~rig] = _elastic_model_nd(n[~rig], lam[~rig], pot, exact)
    return _out(out)


def pulloff_force(n, Q, E_star, W, h, potential="dugdale", model="mdn", exact=False):
    """Pull-off force F_p [N] for tip z = r^n/(nQ) (Q [m^(n-1)]), E* [Pa], W [J/m^2], h [m]."""
    n = V.exponent(n)
    Q, E_star, W, h = (V.positive(k, v) for k, v in (("Q", Q), ("E_star", E_star), ("W", W), ("h", h)))
    n, Q, E_star, W, h = np.broadcast_arrays(n, Q, E_star, W, h)
    lam = np.exp(_log_lambda(n, Q, E_star, W, h))
    p = np.asarray(pulloff_nd(n, lam, potential, model, exact))
    return _out(p * np.exp(log_force_scale(n, Q, E_star, W)))


def _domain_error(lo, hi):
    return ValueError(
        "the pull-off data imply a transition parameter Lambda outside the supported domain "
        f"[{V.LAMBDA_MIN:g}, {V.LAMBDA_MAX:g}] (got range [{np.exp(lo):.6g}, {np.exp(hi):.6g}]); "
        "check units (SI: N, m, Pa) and the inputs"
    )


def _check_x(x):
    if x.size and (x.min() < _XMIN - 1e-9 or x.max() > _XMAX + 1e-9):
        raise _domain_error(x.min(), x.max())
    return np.clip(x, _XMIN, _XMAX)


def _x_rigid(log_g, n, pot):
    """log Lambda from log G for a rigid law: G = ratio n^(2/n) Lambda^((2n-1)/n)."""
    return n / (2.0 * n - 1.0) * (log_g - np.log(rigid_pulloff_ratio(n, pot)) - 2.0 / n * np.log(n))


def _newton_log_lambda(log_g, n, x0, residual_and_slope, iters, tol, pot):
    """Newton in x = log Lambda on [x_min, x_max], element by element: an element stops when its
    own step is below ``tol`` (the others go on), so converged elements cost nothing more.
    ``residual_and_slope(idx, x)`` gives G(x) - log G and dG/dx of the elements ``idx``.  Where the
    solution lies outside the domain the iteration ends on a bound with a residual of that sign
    (> 1e-9): the domain error is raised for those, with the rigid Lambda of ``pot`` in the message."""
    x = np.array(x0, dtype=float)
    r_last = np.zeros_like(x)
    act = np.arange(x.size)
    for _ in range(iters):
        r, d = residual_and_slope(act, x[act])
        step = r / d
        x[act] = np.clip(x[act] - step, _XMIN, _XMAX)
        r_last[act] = r
        act = act[np.abs(step) >= tol]
        if act.size == 0:
            break
    bad = ((x <= _XMIN) & (r_last > 1e-9)) | ((x >= _XMAX) & (r_last < -1e-9))
    if np.any(bad):
        xr = _x_rigid(log_g[bad], n[bad], pot)  # the rigid asymptote gives a rough Lambda for the message
        raise _domain_error(xr.min(), xr.max())
    return x


def _x_mdn(log_g, n, exact):
    """log Lambda from log G for M-D-n (Newton on the spline, started from the rigid asymptote,
    an under-estimate of log Lambda since P~_MDn <= P~_rigid; optional exact polish)."""
    c = (n + 1.0) / n

    def residual_and_slope(i, xi):
        return (
            log_pulloff_fast(n[i], xi) + c[i] * xi - log_g[i],
            log_pulloff_fast(n[i], xi, dx=1) + c[i],
        )

    x0 = np.clip(_x_rigid(log_g, n, "dugdale"), _XMIN, _XMAX)
    x = _newton_log_lambda(log_g, n, x0, residual_and_slope, 30, 1e-13, "dugdale")
    if exact and x.size:
        for _ in range(8):
            r = np.log(pulloff_mdn_exact(n, np.exp(x))) + c * x - log_g
            x = np.clip(x - r / (log_pulloff_fast(n, x, dx=1) + c), _XMIN, _XMAX)
            if np.all(np.abs(r) < 1e-14):
                break
    return x


def _x_elastic(log_g, n, pot, exact):
    """log Lambda from log G for a non-Dugdale law, elastic: Newton on the tables
    (log P~_MDn + y_law + (n+1)/n x, increasing in x), started from the rigid solution; with
    exact=True polished by Newton steps on direct solves."""
    c = (n + 1.0) / n

    def residual_and_slope(i, xi):
        ni, ci = n[i], c[i]
        g = log_pulloff_fast(ni, xi) + log_ratio_to_mdn(pot, ni, xi) + ci * xi
        return g - log_g[i], log_pulloff_fast(ni, xi, dx=1) + log_ratio_to_mdn(pot, ni, xi, dx=1) + ci

    x0 = np.clip(_x_rigid(log_g, n, pot), _XMIN, _XMAX)
    x = _newton_log_lambda(log_g, n, x0, residual_and_slope, 40, 1e-12, pot)
    if exact and x.size:
        for _ in range(4):
            r = np.log(_elastic_nd(n, np.exp(x), pot, True)) + c * x - log_g
            x = np.clip(x - r / (log_pulloff_fast(n, x, dx=1) + log_ratio_to_mdn(pot, n, x, dx=1) + c), _XMIN, _XMAX)
            if np.all(np.abs(r) < 1e-6):  # the direct solve is accurate to ~1e-3: no point in more
                break
    return x


def _x_elastic_model(log_g, n, pot, exact):
    return _x_mdn(log_g, n, exact) if pot == "dugdale" else _x_elastic(log_g, n, pot, exact)


def _x_auto(log_g, n, exact, pot="dugdale"):
    x = _x_rigid(log_g, n, pot)
    rig = x < np.log(rigid_boundary(n, pot))
    x = x.copy()
    x[~rig] = _x_elastic_model(log_g[~rig], n[~rig], pot, exact)
    return x, rig


def _log_lambda_from_g(log_g, n, pot, mdl, exact):
    """log Lambda from log G for the chosen model (rigid closed form, elastic table/solve, or auto)."""
    if mdl == "rigid":
        return _x_rigid(log_g, n, pot)
    if mdl in ("mdn", "elastic"):
        return _x_elastic_model(log_g, n, pot, exact)
    return _x_auto(log_g, n, exact, pot)[0]


def lambda_from_g(G, n, potential="dugdale", model="mdn", exact=False):
    """Invert G = P~(n, Lambda) Lambda^((n+1)/n) for Lambda (vectorised, no per-point root finding)."""
    pot = V.potential(potential)
    mdl = V.model(model, pot)
    log_g, n = np.broadcast_arrays(np.log(V.positive("G", G)), V.exponent(n))
    log_g, n = log_g.ravel(), n.ravel().copy()
    shape = np.broadcast_shapes(np.shape(G), np.shape(n))
    x = _log_lambda_from_g(log_g, n, pot, mdl, exact)
    return _out(np.exp(_check_x(x)).reshape(shape))


def work_of_adhesion(F_p, n, Q, E_star, h, potential="dugdale", model="mdn", exact=False):
    """Work of adhesion W_A [J/m^2] from the pull-off force F_p [N] (inverse of pulloff_force).

    All arguments broadcast (e.g. arrays of F_p, n, Q, E* of shape (N, 1) against an h grid of
    shape (M,)); a whole W_A(h) curve or a Monte-Carlo sample is one vectorised call.
    """
    pot = V.potential(potential)
    mdl = V.model(model, pot)
    F_p = V.positive("F_p", F_p)
    n = V.exponent(n)
    Q, E_star, h = (V.positive(k, v) for k, v in (("Q", Q), ("E_star", E_star), ("h", h)))
    return _out(_inverse(F_p, n, Q, E_star, h, pot, mdl, exact)[0])


def work_of_adhesion_and_regime(F_p, n, Q, E_star, h, potential="dugdale", model="mdn", exact=False):
    """(W_A [J/m^2], rigid mask): :func:`work_of_adhesion` and, from the same solve, True where
    the rigid solution was used (``model="auto"``: :func:`model_used`; "rigid": all; else none)."""
    pot = V.potential(potential)
    mdl = V.model(model, pot)
    F_p = V.positive("F_p", F_p)
    n = V.exponent(n)
    Q, E_star, h = (V.positive(k, v) for k, v in (("Q", Q), ("E_star", E_star), ("h", h)))
    W, rigid = _inverse(F_p, n, Q, E_star, h, pot, mdl, exact)
    return _out(W), _out(rigid)


def _inverse(F_p, n, Q, E_star, h, pot, mdl, exact):
    """W_A and the rigid mask, both of the broadcast shape, from validated inputs."""
    F_p, n, Q, E_star, h = np.broadcast_arrays(F_p, n, Q, E_star, h)
    shape = n.shape
    F_p, n, Q, E_star, h = (a.ravel() for a in (F_p, n, Q, E_star, h))
    log_g = log_g_group(F_p, n, Q, E_star, h)
    if mdl == "auto":
        x, rigid = _x_auto(log_g, n, exact, pot)
    else:
        x, rigid = _log_lambda_from_g(log_g, n, pot, mdl, exact), np.full(n.shape, mdl == "rigid")
    x = _check_x(x)
    return work_from_lambda(x, n, Q, E_star, h).reshape(shape), rigid.reshape(shape)


def model_used(n, Q, E_star, h, W=None, F_p=None, potential="dugdale"):
    """Boolean mask: True where model="auto" uses the rigid solution of ``potential``.

    Give exactly one of W (forward, pulloff_force: Lambda(W, h) < Lambda_b(n)) or F_p
    (inverse, work_of_adhesion: the rigid solution of the law has Lambda < Lambda_b(n));
    Lambda_b from :func:`rigid_boundary` (Eq. 13 for Dugdale).
    """
    if (W is None) == (F_p is None):
        raise ValueError("give exactly one of W (forward) or F_p (inverse)")
    pot = V.potential(potential)
    n = V.exponent(n)
    Q, E_star, h = (V.positive(k, v) for k, v in (("Q", Q), ("E_star", E_star), ("h", h)))
    if W is not None:
        W = V.positive("W", W)
        return _out(np.asarray(_log_lambda(n, Q, E_star, W, h) < np.log(rigid_boundary(n, pot))))
    F_p = V.positive("F_p", F_p)
    x = _x_rigid(log_g_group(F_p, n, Q, E_star, h), n, pot)
    return _out(np.asarray(x < np.log(rigid_boundary(np.broadcast_to(n, x.shape), pot))))


def _mode(mode, pot):
    """A pipeline solver_mode ("auto", "mdn" = always the full elastic model, "rigid") as a model."""
    key = str(mode).lower()
    return "elastic" if key == "mdn" and pot != "dugdale" else key


def _names(rigid_mask, mdl, pot):
    full = "mdn" if pot == "dugdale" else "elastic"
    if mdl == "rigid":
        return np.full(np.shape(rigid_mask), "rigid", dtype=object)
    if mdl in ("mdn", "elastic"):
        return np.full(np.shape(rigid_mask), full, dtype=object)
    return np.where(rigid_mask, "rigid", full).astype(object)


def pulloff_with_model(law, n, Q, E_star, W, h, mode="auto", exact=False):
    """Pull-off F_p [N] and the model that made each value ("rigid", "mdn" or "elastic").

    law: traction law; mode: pipeline solver_mode ("auto": rigid where Lambda < Lambda_b(n)
    (:func:`rigid_boundary`; Eq. 13 for Dugdale), else the law's elastic model; "mdn": always the
    elastic model (M-D-n for Dugdale, the elastic solver otherwise); "rigid"); arrays broadcast.
    """
    pot = V.potential(law)
    mdl = V.model(_mode(mode, pot), pot)
    F = np.asarray(pulloff_force(n, Q, E_star, W, h, potential=pot, model=mdl, exact=exact))
    rig = np.asarray(model_used(n, Q, E_star, h, W=W, potential=pot)) if mdl == "auto" else np.zeros(F.shape, bool)
    return _out(F), _names(np.broadcast_to(rig, F.shape), mdl, pot)


def work_of_adhesion_with_model(law, F_p, n, Q, E_star, h, mode="auto", exact=False):
    """W_A [J/m^2] from F_p [N] and the model that made each value ("rigid", "mdn", "elastic");
    the inverse of :func:`pulloff_with_model` (same modes; auto decides with Lambda of the rigid
    solution, as the paper's procedure, Sec. 4.2)."""
    pot = V.potential(law)
    mdl = V.model(_mode(mode, pot), pot)
    W, rig = work_of_adhesion_and_regime(F_p, n, Q, E_star, h, potential=pot, model=mdl, exact=exact)
    W = np.asarray(W)
    return _out(W), _names(np.broadcast_to(np.asarray(rig) if mdl == "auto" else False, W.shape), mdl, pot)
