"""Boundary of the rigid regime (paper Sec. 4.2, Eq. 13, Fig. 5)."""

from __future__ import annotations

import numpy as np

from . import _validate as V

__all__ = ["lambda_boundary", "lambda_boundary_solved", "rigid_error"]


def lambda_boundary(n):
    """Eq. 13: Lambda_b(n) = -0.002194 n^2 + 0.067185 n + 0.022056 (paper's quadratic fit).

    Rigid (Eq. 12) is within 5 % of M-D-n for Lambda < Lambda_b(n).
    """
    n = V.exponent(n)
    return (-0.002194 * n + 0.067185) * n + 0.022056


def rigid_error(n, lam, exact=True):
    """(F_rigid - F_MDn) / F_MDn for the Dugdale law at (n, Lambda) (>= 0): Eq. 12 against Eqs. 9-11."""
    n, lam = np.broadcast_arrays(V.exponent(n), V.transition(lam))
    from .rigid import rigid_pulloff_nd_raw  # scipy: only where a pull-off is evaluated, not for Eq. 13
    from .tables import pulloff_mdn

    return rigid_pulloff_nd_raw(n, lam) / pulloff_mdn(n, lam, exact) - 1.0


def lambda_boundary_solved(n, tol=0.05):
    """Re-derive the rigid-regime boundary from the solver: the Lambda at which
    |F_MDn - F_rigid| / F_MDn = ``tol`` (5 % in the paper), by Brent's method in log Lambda
    on the direct M-D-n solve.  Compare with :func:`lambda_boundary` (Eq. 13).
    """
    from scipy.optimize import brentq  # a check, not a stage's work: kept out of the stages' start-up

    from .mdn import pulloff_mdn_exact
    from .rigid import rigid_pulloff_nd_raw

    n = V.exponent(n)
    out = np.empty(n.shape)
    lo, hi = np.log(V.LAMBDA_MIN), np.log(V.LAMBDA_MAX)

    def f(x, nn):
        lam = np.exp(x)
        return float(np.log(rigid_pulloff_nd_raw(nn, lam) / pulloff_mdn_exact(nn, lam)) - np.log1p(tol))

    for idx, nn in np.ndenumerate(n):
        out[idx] = np.exp(brentq(f, lo, hi, args=(nn,), xtol=1e-12, rtol=1e-13))
    return out[()]
