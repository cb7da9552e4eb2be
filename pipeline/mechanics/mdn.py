"""M-D-n model (Zheng & Yu 2007; paper Sec. 3.1, Eqs. 9-11): branch and direct pull-off solve.

All quantities here are non-dimensional (paper Eqs. 4-8, ERRATA-corrected scalings):
``a`` = a~, ``delta`` = delta~, ``P`` = P~, ``lam`` = Lambda.

The branch is parametrised by ``t = log(m - 1)`` (m = c/a, adhesive-zone to contact radius),
which keeps m - 1 exact down to 1e-300 (JKR end) and lets every large-m quantity be carried in
logarithms (DMT end, m^n would overflow for n = 20).  For a given m, Eq. 11 reads

    alpha(m) a^n + beta(m) a = 1,   alpha = Lambda C1(m) / n,   beta = (4/pi) Lambda^2 C2(m),

with C1 = m^n (1 - I_{m^-2}((n+1)/2, 1/2)) - (n/pi) B(n/2,1/2) arcsec m  (> 0) and
C2 = sqrt(m^2-1) arcsec m + 1 - m  (> 0): a unique root a(m), found by Newton in log a.

C1 is the difference of two O(sqrt(m-1)) terms and is O((m-1)^(3/2)) near m = 1 (the two
leading terms cancel because B(1/2,(n+1)/2) B(n/2,1/2) = 2 pi / n).  It is therefore
evaluated, for m^2 < 2, from the cancellation-free integral

    C1 = 2 sqrt(x) / B(1/2,(n+1)/2) * int_0^1 (1 - x v^2)^(-1/2)
                                   expm1(n/2 [log1p(-x v^2) - log1p(-x)]) dv,  x = 1 - 1/m^2,

(24-point Gauss-Legendre, analytic integrand, machine precision), and for m^2 >= 2 from
C1 = m^n [I_x(1/2,(n+1)/2) - (2/B(1/2,(n+1)/2)) arcsec(m) m^-n]   (1 - I_{1/m^2}(a,b) = I_x(b,a)).
Its derivative is simply dC1/dm = n m^(n-1) I_x(1/2,(n+1)/2).

The pull-off load (load control) is the minimum of P~ along the branch; it is found from the
sign change of the analytic dP~/dt on a coarse grid followed by a vectorised safeguarded
secant (Illinois) iteration on dP~/dt = 0.
"""

from __future__ import annotations

from typing import NamedTuple

import numpy as np
from scipy import special as sp

__all__ = [
    "MDNBranch",
    "mdn_branch",
    "mdn_state",
    "pulloff_mdn_exact",
    "jkr_limit_nd",
    "jkr_contact_nd",
]

_GL_X, _GL_W = np.polynomial.legendre.leggauss(24)
_GL_V = 0.5 * (_GL_X + 1.0)
_GL_W = 0.5 * _GL_W
_LOG_4_PI = np.log(4.0 / np.pi)


def _c1_log(n, logm, x, asec):
    """log C1(m) (see module docstring), elementwise; m given through log m, x = 1 - 1/m^2."""
    n, logm, x, asec = np.broadcast_arrays(n, logm, x, asec)
    out = np.empty(n.shape)
    lb1 = sp.betaln(0.5, 0.5 * (n + 1.0))
    small = x < 0.5
    if np.any(small):
        xs, ns = x[small][:, None], n[small][:, None]
        xv2 = xs * _GL_V**2
        integrand = np.expm1(0.5 * ns * (np.log1p(-xv2) - np.log1p(-xs))) / np.sqrt(1.0 - xv2)
        integral = integrand @ _GL_W
        out[small] = np.log(2.0) + 0.5 * np.log(x[small]) - lb1[small] + np.log(integral)
    big = ~small
    if np.any(big):
        nb = n[big]
        ib = sp.betainc(0.5, 0.5 * (nb + 1.0), x[big])
        corr = 2.0 * np.exp(-lb1[big]) * asec[big] * np.exp(-nb * logm[big])
        out[big] = nb * logm[big] + np.log(ib - corr)
    return out


class _State(NamedTuple):
    a: np.ndarray
    delta: np.ndarray
    P: np.ndarray
    m: np.ndarray
    dPdt: np.ndarray


def mdn_state(n, lam, t, derivative=True):
    """Point of the M-D-n branch at t = log(m-1): returns (a~, delta~, P~, m, dP~/dt).

    Eqs. 9-11 of the paper; broadcasting over n, lam, t.
    """
    n, lam, t = (np.asarray(v, dtype=float) for v in (n, lam, t))
    n, lam, t = np.broadcast_arrays(n, lam, t)
    e = np.exp(t)
    m = 1.0 + e
    logm = np.log1p(e)
    s = np.sqrt(e * (2.0 + e))  # sqrt(m^2 - 1)
    asec = np.arctan(s)  # arcsec m
    x = np.minimum(np.exp(np.log(e) + np.log(2.0 + e) - 2.0 * logm), 1.0)  # 1 - 1/m^2
    loglam = np.log(lam)
    la = loglam + _c1_log(n, logm, x, asec) - np.log(n)
    c2 = s * asec - e
    lb = _LOG_4_PI + 2.0 * loglam + np.log(c2)
    # Newton on g(y) = log(alpha e^{n y} + beta e^{y}) = 0 (convex, increasing), from above.
    y = np.minimum(-lb, -la / n)
    for _ in range(100):
        u1 = la + n * y
        u2 = lb + y
        g = np.logaddexp(u1, u2)
        w1 = np.exp(u1 - g)
        w2 = np.exp(u2 - g)
        step = g / (n * w1 + w2)
        y = y - step
        if np.all(np.abs(step) <= 1e-15 * np.maximum(1.0, np.abs(y))):
            break
    a = np.exp(y)
    b_n = sp.beta(0.5 * n, 0.5)
    b_n1 = sp.beta(0.5 * n + 1.0, 0.5)
    c3 = m * m * asec + s
    P = b_n1 / np.pi * a ** (n + 1.0) - 2.0 / np.pi * lam * a * a * c3
    delta = 0.5 * b_n * a**n - 2.0 * lam * a * s
    if not derivative:
        return _State(a, delta, P, m, np.full_like(P, np.nan))
    ix = sp.betainc(0.5, 0.5 * (n + 1.0), x)
    # alpha_t a^n = Lambda I e m^(n-1) a^n  (dC1/dm = n m^(n-1) I, dm/dt = e)
    log_ix = np.log(np.maximum(ix, 1e-300))
    at_an = np.exp(loglam + log_ix + np.log(e) - logm + n * (logm + y))
    dc2dm = m * asec / s + 1.0 / m - 1.0
    bt_a = np.exp(_LOG_4_PI + 2.0 * loglam + y) * dc2dm * e
    an_alpha = np.exp(la + n * y)
    dy_dt = -(at_an + bt_a) / (n * an_alpha + np.exp(lb + y))
    dc3dt = 2.0 * m * e * asec + 2.0 * m * np.sqrt(e / (2.0 + e))
    dPdt = (b_n1 / np.pi) * (n + 1.0) * a ** (n + 1.0) * dy_dt - 2.0 / np.pi * lam * a * a * (2.0 * c3 * dy_dt + dc3dt)
    return _State(a, delta, P, m, dPdt)


_T_SPAN = 40.0
_N_COARSE = 41


def _coarse_range(lam):
    """t-interval [lo, hi] that contains the pull-off point (JKR end: m - 1 ~ Lambda^-2)."""
    base = -2.0 * np.log(np.maximum(lam, 1.0))
    return base - 8.0, base - 8.0 + _T_SPAN


def _pulloff_flat(n, lam, return_t=False):
    """Direct M-D-n pull-off (positive) for 1-D arrays n, lam of equal length."""
    size = n.size
    lo, hi = _coarse_range(lam)
    grid = lo[:, None] + (hi - lo)[:, None] * np.linspace(0.0, 1.0, _N_COARSE)[None, :]
    st = mdn_state(n[:, None], lam[:, None], grid)
    i = np.argmin(st.P, axis=1)
    rows = np.arange(size)
    best_p = st.P[rows, i]
    best_t = grid[rows, i]
    il = np.maximum(i - 1, 0)
    ir = np.minimum(i + 1, _N_COARSE - 1)
    tl, tr = grid[rows, il], grid[rows, ir]
    fl, fr = st.dPdt[rows, il], st.dPdt[rows, ir]
    # Illinois iteration on dP/dt = 0 where the bracket is a genuine sign change; elsewhere the
    # minimum sits on a plateau (P flat to round-off) and the grid minimum is already exact.
    active = (fl < 0.0) & (fr > 0.0) & (il != i) & (ir != i)
    side = np.zeros(size)
    for _ in range(60):
        idx = np.nonzero(active)[0]
        if idx.size == 0:
            break
        a_l, a_r, f_l, f_r = tl[idx], tr[idx], fl[idx], fr[idx]
        tn = a_r - f_r * (a_r - a_l) / (f_r - f_l)
        tn = np.clip(tn, a_l, a_r)
        sn = mdn_state(n[idx], lam[idx], tn)
        better = sn.P < best_p[idx]
        best_p[idx[better]] = sn.P[better]
        best_t[idx[better]] = tn[better]
        fn = sn.dPdt
        go_right = fn < 0.0  # new point becomes the left end
        # Illinois: halve the retained end's f when the same side is retained twice
        sd = side[idx]
        newl = np.where(go_right, tn, a_l)
        newr = np.where(go_right, a_r, tn)
        nfl = np.where(go_right, fn, np.where(sd == -1, 0.5 * f_l, f_l))
        nfr = np.where(go_right, np.where(sd == 1, 0.5 * f_r, f_r), fn)
        side[idx] = np.where(go_right, 1, -1)
        tl[idx], tr[idx], fl[idx], fr[idx] = newl, newr, nfl, nfr
        done = (np.abs(newr - newl) < 1e-11 * np.maximum(1.0, np.abs(tn))) | (fn == 0.0)
        active[idx[done]] = False
    if return_t:
        return -best_p, best_t
    return -best_p


def pulloff_mdn_exact(n, lam, chunk=4096):
    """Non-dimensional M-D-n pull-off -min P~ (positive) by direct solution of Eqs. 9-11.

    Vectorised over broadcast n, lam; no domain checks (see ``pipeline.mechanics.pulloff_nd``).
    """
    n, lam = np.broadcast_arrays(np.asarray(n, float), np.asarray(lam, float))
    out = np.empty(n.shape)
    fn, fl, fo = n.ravel(), lam.ravel(), out.reshape(-1)
    for s in range(0, fn.size, chunk):
        fo[s : s + chunk] = _pulloff_flat(fn[s : s + chunk], fl[s : s + chunk])
    return out


class MDNBranch(NamedTuple):
    """One M-D-n load curve (non-dimensional; Eqs. 4-6, 9-11), ordered by increasing m."""

    t: np.ndarray  # log(m - 1)
    m: np.ndarray  # c / a
    a: np.ndarray  # a~
    delta: np.ndarray  # delta~
    P: np.ndarray  # P~ (tensile negative)
    i_pulloff: int  # index of min P~ on the returned grid
    pulloff: float  # -min P~ from the direct solve (positive)


def mdn_branch(n, lam, num=400, a_factor=2.5, t_tail=12.0):
    """Full M-D-n branch for scalar (n, Lambda).

    Covers contact radii from ``a_factor`` times the pull-off contact radius (compressive,
    Hertz-dominated end) down to the small-contact end ``t_tail`` units of log(m-1) past the
    pull-off point.  The grid is uniform in t = log(m-1) and contains the pull-off point.
    """
    n, lam = float(n), float(lam)
    po, t_star = _pulloff_flat(np.array([n]), np.array([lam]), return_t=True)
    t_star = float(t_star[0])
    a_star = mdn_state(n, lam, t_star, derivative=False).a
    probe = t_star - np.linspace(0.0, 80.0, 321)
    a_probe = mdn_state(n, lam, probe, derivative=False).a
    over = np.nonzero(a_probe >= a_factor * a_star)[0]
    t_lo = probe[over[0]] if over.size else probe[-1]
    n_left = max(2, int(round(num * (t_star - t_lo) / (t_star - t_lo + t_tail))))
    t = np.concatenate([np.linspace(t_lo, t_star, n_left), np.linspace(t_star, t_star + t_tail, num - n_left + 1)[1:]])
    st = mdn_state(n, lam, t, derivative=False)
    return MDNBranch(t, st.m, st.a, st.delta, st.P, n_left - 1, float(po[0]))


def jkr_contact_nd(n, a):
    """Power-law JKR load curve P~(a~) = B(n/2+1,1/2) a~^(n+1)/pi - sqrt(8/pi) a~^(3/2)."""
    n = np.asarray(n, float)
    return sp.beta(0.5 * n + 1.0, 0.5) / np.pi * a ** (n + 1.0) - np.sqrt(8.0 / np.pi) * a**1.5


def jkr_limit_nd(n):
    """Lambda -> infinity limit of the M-D-n pull-off (power-law JKR), non-dimensional, positive.

    Derivation.  For Lambda -> inf the Dugdale zone shrinks to a crack tip (m - 1 ~ Lambda^-2,
    Eq. 11 reduces to (4/pi) Lambda^2 a~ (m-1) = 1) and the adhesive term of Eq. 10 tends to
    (2/pi) Lambda a~^2 * 2 sqrt(2(m-1)) = sqrt(8/pi) a~^(3/2).  Dimensionally this is the
    Griffith (G = W) flat-punch stress-intensity load sqrt(8 pi W E* a^3) superposed on the
    power-law Hertz load P_H = B(n/2+1,1/2) E* a^(n+1)/Q, i.e.

        P~(a~) = A a~^(n+1) - C a~^(3/2),  A = B(n/2+1,1/2)/pi,  C = sqrt(8/pi).

    Load-controlled pull-off at dP~/da~ = 0:  a~_c^(n-1/2) = 3C / (2(n+1)A), so

        P~_JKR(n) = C (2n-1)/(2(n+1)) * (3C / (2(n+1)A))^(3/(2n-1)).

    n = 2 gives exactly 3/2, i.e. F = 1.5 pi W R (JKR).  Dimensional:
    F = pi P~_JKR(n) (Q^3 W^(n+1) E*^(n-2))^(1/(2n-1)).
    """
    n = np.asarray(n, float)
    A = sp.beta(0.5 * n + 1.0, 0.5) / np.pi
    C = np.sqrt(8.0 / np.pi)
    return C * (2.0 * n - 1.0) / (2.0 * (n + 1.0)) * (3.0 * C / (2.0 * (n + 1.0) * A)) ** (3.0 / (2.0 * n - 1.0))
