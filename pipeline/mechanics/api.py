"""Public pull-off / work-of-adhesion functions (forward and inverse), all models and potentials.

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
from .mdn import pulloff_mdn_exact
from .rigid import rigid_pulloff_nd_raw, rigid_pulloff_ratio
from .scaling import _log_lambda, log_force_scale, log_g_group, work_from_lambda
from .tables import log_pulloff_fast

__all__ = ["pulloff_nd", "pulloff_force", "work_of_adhesion", "model_used", "lambda_from_g"]

_XMIN, _XMAX = np.log(V.LAMBDA_MIN), np.log(V.LAMBDA_MAX)


def _mdn_nd(n, lam, exact):
    if exact:
        return pulloff_mdn_exact(n, lam)
    return np.exp(log_pulloff_fast(n, np.log(lam)))


def _out(a):
    return a[()] if isinstance(a, np.ndarray) and a.ndim == 0 else a


def pulloff_nd(n, Lambda, potential="dugdale", model="mdn", exact=False):
    """Non-dimensional pull-off -min P~ (> 0) at (n, Lambda); P~ = P/(pi P*) (Eq. 6).

    model: "mdn" (Eqs. 9-11, Dugdale only), "rigid" (Eq. 12 and Sec. 4.3 laws:
    "dugdale", "lj", "tri1", "tri2"), "auto" (rigid where Lambda < Eq. 13 boundary, else mdn).
    exact=False uses the tabulated spline (~1e-8 rel.), exact=True the direct solve.
    """
    pot = V.potential(potential)
    mdl = V.model(model, pot)
    n, lam = np.broadcast_arrays(V.exponent(n), V.transition(Lambda))
    if mdl == "rigid":
        return _out(rigid_pulloff_nd_raw(n, lam, pot))
    if mdl == "mdn":
        return _out(_mdn_nd(n, lam, exact))
    out = np.empty(n.shape)
    rig = lam < lambda_boundary(n)
    out[rig] = rigid_pulloff_nd_raw(n[rig], lam[rig])
    out[~rig] = _mdn_nd(n[~rig], lam[~rig], exact)
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


def _x_mdn(log_g, n, exact):
    """log Lambda from log G for M-D-n (Newton on the spline; optional exact polish)."""
    c = (n + 1.0) / n
    g_lo = log_pulloff_fast(n, _XMIN) + c * _XMIN
    g_hi = log_pulloff_fast(n, _XMAX) + c * _XMAX
    bad = (log_g < g_lo - 1e-9) | (log_g > g_hi + 1e-9)
    if np.any(bad):
        # rigid/JKR asymptotes give a rough Lambda for the message
        xr = _x_rigid(log_g[bad], n[bad], "dugdale")
        raise _domain_error(xr.min(), xr.max())
    # start from the rigid asymptote (an under-estimate of log Lambda since P~_MDn <= P~_rigid)
    x = np.clip(_x_rigid(log_g, n, "dugdale"), _XMIN, _XMAX)
    for _ in range(30):
        r = log_pulloff_fast(n, x) + c * x - log_g
        d = log_pulloff_fast(n, x, dx=1) + c
        step = r / d
        x = np.clip(x - step, _XMIN, _XMAX)
        if np.all(np.abs(step) < 1e-13):
            break
    if exact and x.size:
        for _ in range(8):
            r = np.log(pulloff_mdn_exact(n, np.exp(x))) + c * x - log_g
            x = np.clip(x - r / (log_pulloff_fast(n, x, dx=1) + c), _XMIN, _XMAX)
            if np.all(np.abs(r) < 1e-14):
                break
    return x


def _x_auto(log_g, n, exact):
    x = _x_rigid(log_g, n, "dugdale")
    rig = x < np.log(lambda_boundary(n))
    x = x.copy()
    x[~rig] = _x_mdn(log_g[~rig], n[~rig], exact)
    return x, rig


def _log_lambda_from_g(log_g, n, pot, mdl, exact):
    """log Lambda from log G for the chosen model (rigid closed form, M-D-n table/solve, or auto)."""
    if mdl == "rigid":
        return _x_rigid(log_g, n, pot)
    if mdl == "mdn":
        return _x_mdn(log_g, n, exact)
    return _x_auto(log_g, n, exact)[0]


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
    F_p, n, Q, E_star, h = np.broadcast_arrays(F_p, n, Q, E_star, h)
    shape = n.shape
    F_p, n, Q, E_star, h = (a.ravel() for a in (F_p, n, Q, E_star, h))
    log_g = log_g_group(F_p, n, Q, E_star, h)
    x = _check_x(_log_lambda_from_g(log_g, n, pot, mdl, exact))
    return _out(work_from_lambda(x, n, Q, E_star, h).reshape(shape))


def model_used(n, Q, E_star, h, W=None, F_p=None):
    """Boolean mask: True where model="auto" uses the rigid solution (Dugdale).

    Give exactly one of W (forward, pulloff_force: Lambda(W, h) < Lambda_b(n)) or F_p
    (inverse, work_of_adhesion: the Eq. 12 solution has Lambda < Lambda_b(n)).
    """
    if (W is None) == (F_p is None):
        raise ValueError("give exactly one of W (forward) or F_p (inverse)")
    n = V.exponent(n)
    Q, E_star, h = (V.positive(k, v) for k, v in (("Q", Q), ("E_star", E_star), ("h", h)))
    if W is not None:
        W = V.positive("W", W)
        return _out(np.asarray(_log_lambda(n, Q, E_star, W, h) < np.log(lambda_boundary(n))))
    F_p = V.positive("F_p", F_p)
    x = _x_rigid(log_g_group(F_p, n, Q, E_star, h), n, "dugdale")
    return _out(np.asarray(x < np.log(lambda_boundary(np.broadcast_to(n, x.shape)))))
