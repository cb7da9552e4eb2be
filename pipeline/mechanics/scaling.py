"""Non-dimensionalisation (paper Eqs. 2-8 as corrected in ERRATA) and tip-geometry helpers.

Scales (Q in m^(n-1), W in J/m^2, E* in Pa; computed in logarithms so that Q ~ 1e-170 for
n = 20 or E*^n never under/overflows):

    a*     = (Q^2 W / E*)^(1/(2n-1))                (Eq. 4)
    delta* = (Q W^n / E*^n)^(1/(2n-1))              (Eq. 5)
    P*     = (Q^3 W^(n+1) E*^(n-2))^(1/(2n-1)),  P~ = P / (pi P*)   (Eq. 6)
    Lambda = sigma_0 (Q W^(1-n) / E*^n)^(1/(2n-1)),  sigma_0 = W/h  (Eqs. 3, 8)

Inversion group (W eliminated):  G = F_p / (pi E* h^(1+1/n) Q^(1/n)) = P~(n, Lambda) Lambda^((n+1)/n),
and back-substitution W = (Lambda h)^((2n-1)/n) Q^(-1/n) E*.
"""

from __future__ import annotations

import numpy as np

from . import _validate as V

__all__ = [
    "transition_parameter",
    "maugis_parameter",
    "maugis_from_transition",
    "q_from_rs",
    "r_from_q",
    "log_force_scale",
    "log_length_scale",
    "log_displacement_scale",
    "log_g_group",
    "work_from_lambda",
]


def log_length_scale(n, Q, E_star, W):
    """log a* (Eq. 4, corrected)."""
    return (2.0 * np.log(Q) + np.log(W) - np.log(E_star)) / (2.0 * n - 1.0)


def log_displacement_scale(n, Q, E_star, W):
    """log delta* (Eq. 5, corrected)."""
    return (np.log(Q) + n * (np.log(W) - np.log(E_star))) / (2.0 * n - 1.0)


def log_force_scale(n, Q, E_star, W):
    """log(pi P*) so that P = P~ exp(log_force_scale) (Eq. 6)."""
    return np.log(np.pi) + (3.0 * np.log(Q) + (n + 1.0) * np.log(W) + (n - 2.0) * np.log(E_star)) / (2.0 * n - 1.0)


def _log_lambda(n, Q, E_star, W, h):
    return np.log(W) - np.log(h) + (np.log(Q) + (1.0 - n) * np.log(W) - n * np.log(E_star)) / (2.0 * n - 1.0)


def transition_parameter(n, Q, E_star, W, h):
    """Generalised transition parameter Lambda (Eq. 8, ERRATA-corrected sign of the E* exponent).

    Lambda = (W/h) (Q W^(1-n) / E*^n)^(1/(2n-1)); for n = 2 (Q = R) Lambda = sigma_0 (R/(W E*^2))^(1/3).
    """
    n = V.exponent(n)
    Q, E_star, W, h = (V.positive(k, v) for k, v in (("Q", Q), ("E_star", E_star), ("W", W), ("h", h)))
    return np.exp(_log_lambda(n, Q, E_star, W, h))


def maugis_parameter(R, E_star, W, h):
    """Maugis (1992) parameter lambda = 2 sigma_0 (R / (pi W K^2))^(1/3), K = 4E*/3, sigma_0 = W/h."""
    R, E_star, W, h = (V.positive(k, v) for k, v in (("R", R), ("E_star", E_star), ("W", W), ("h", h)))
    K = 4.0 * E_star / 3.0
    return 2.0 * (W / h) * np.cbrt(R / (np.pi * W * K * K))


def maugis_from_transition(lam):
    """lambda_Maugis = 2 (9/(16 pi))^(1/3) Lambda (about 1.1272 Lambda), valid for n = 2."""
    return 2.0 * np.cbrt(9.0 / (16.0 * np.pi)) * np.asarray(lam, float)


def q_from_rs(n, R, S=1.0):
    """Q = S^(n-2) R^(n-1) [m^(n-1)] (Eq. 2): tip profile z = r^n / (n Q)."""
    n = V.positive("n", n)
    R, S = V.positive("R", R), V.positive("S", S)
    return np.exp((n - 2.0) * np.log(S) + (n - 1.0) * np.log(R))


def r_from_q(n, Q, S=1.0):
    """R = (Q / S^(n-2))^(1/(n-1)) [m], the inverse of :func:`q_from_rs` (needs n > 1)."""
    n = V.positive("n", n)
    if np.any(n <= 1.0):
        raise ValueError("r_from_q needs n > 1")
    Q, S = V.positive("Q", Q), V.positive("S", S)
    return np.exp((np.log(Q) - (n - 2.0) * np.log(S)) / (n - 1.0))


def log_g_group(F_p, n, Q, E_star, h):
    """log G, G = F_p / (pi E* h^(1+1/n) Q^(1/n)) = P~ Lambda^((n+1)/n)."""
    return np.log(F_p) - np.log(np.pi) - np.log(E_star) - (1.0 + 1.0 / n) * np.log(h) - np.log(Q) / n


def work_from_lambda(log_lam, n, Q, E_star, h):
    """W = (Lambda h)^((2n-1)/n) Q^(-1/n) E* from log Lambda (inverse of Eq. 8 at fixed h)."""
    return np.exp((2.0 * n - 1.0) / n * (log_lam + np.log(h)) - np.log(Q) / n + np.log(E_star))
