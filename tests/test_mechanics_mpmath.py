"""High-precision (mpmath, 40 digits) reference for the M-D-n pull-off, written independently of
pipeline.mechanics: the printed Eqs. 9-11 verbatim (1 - I_{m^-2}((n+1)/2, 1/2) by mpmath.betainc,
no complement / quadrature tricks), a(m) by mpmath.findroot, the minimum of P~ by a scan plus
golden-section search in t = log(m-1)."""

import mpmath as mp
import numpy as np
import pytest

import pipeline.mechanics as M

pytestmark = pytest.mark.filterwarnings("error")

DPS = 40


def mp_point(n, lam, t):
    n, lam = mp.mpf(n), mp.mpf(lam)
    e = mp.exp(t)
    m = 1 + e
    asec = mp.asec(m)
    root = mp.sqrt(m * m - 1)
    inc = mp.betainc((n + 1) / 2, mp.mpf(1) / 2, 0, 1 / m**2, regularized=True)
    c1 = m**n * (1 - inc) - n / mp.pi * mp.beta(n / 2, mp.mpf(1) / 2) * asec
    c2 = root * asec + 1 - m
    alpha = lam * c1 / n
    beta = 4 / mp.pi * lam**2 * c2
    y0 = min(-mp.log(beta), -mp.log(alpha) / n)
    y = mp.findroot(lambda y: mp.log(alpha * mp.exp(n * y) + beta * mp.exp(y)), y0, tol=mp.mpf(10) ** (-2 * DPS + 10))
    a = mp.exp(y)
    return mp.beta(n / 2 + 1, mp.mpf(1) / 2) / mp.pi * a ** (n + 1) - 2 / mp.pi * lam * a**2 * (m**2 * asec + root)


def mp_pulloff(n, lam, scan=36, iters=80):
    """-min P~ along the branch (positive), 40-digit arithmetic."""
    with mp.workdps(DPS):
        base = -2 * mp.log(max(mp.mpf(lam), 1))
        ts = [base - 12 + k * mp.mpf(48) / (scan - 1) for k in range(scan)]
        ps = [mp_point(n, lam, t) for t in ts]
        k = min(range(scan), key=lambda i: ps[i])
        lo, hi = ts[max(k - 1, 0)], ts[min(k + 1, scan - 1)]
        g = (mp.sqrt(5) - 1) / 2
        x1, x2 = hi - g * (hi - lo), lo + g * (hi - lo)
        f1, f2 = mp_point(n, lam, x1), mp_point(n, lam, x2)
        best = min(ps[k], f1, f2)
        for _ in range(iters):
            if f1 < f2:
                hi, x2, f2 = x2, x1, f1
                x1 = hi - g * (hi - lo)
                f1 = mp_point(n, lam, x1)
            else:
                lo, x1, f1 = x1, x2, f2
                x2 = lo + g * (hi - lo)
                f2 = mp_point(n, lam, x2)
            best = min(best, f1, f2)
        return -best


CASES = [
    (2.0, 1e-3),
    (2.0, 0.7),
    (2.5, 3.0),
    (3.0, 0.05),
    (4.0, 1.0),
    (5.0, 0.2),
    (5.0, 20.0),
    (7.3, 1e-4),
    (10.0, 2.0),
    (13.7, 150.0),
    (20.0, 0.5),
    (20.0, 1e4),
    (3.0, 1e6),
    (17.0, 1e-6),
]


@pytest.fixture(scope="module")
def reference():
    return {c: float(mp_pulloff(*c)) for c in CASES}


def test_exact_solver_matches_mpmath(reference):
    n = np.array([c[0] for c in CASES])
    lam = np.array([c[1] for c in CASES])
    ref = np.array([reference[c] for c in CASES])
    got = M.pulloff_nd(n, lam, exact=True)
    assert np.max(np.abs(got / ref - 1)) < 1e-10


def test_fast_path_matches_mpmath(reference):
    n = np.array([c[0] for c in CASES])
    lam = np.array([c[1] for c in CASES])
    ref = np.array([reference[c] for c in CASES])
    got = M.pulloff_nd(n, lam, exact=False)
    assert np.max(np.abs(got / ref - 1)) < 1e-6


def test_branch_point_matches_mpmath():
    """A single branch point (a~, P~ at given m) of the vectorised solver vs mpmath."""
    from pipeline.mechanics.mdn import mdn_state

    for n, lam, t in [(2.0, 1.0, -1.0), (5.5, 0.3, 2.0), (20.0, 30.0, -6.0), (3.0, 1e5, -24.0)]:
        st = mdn_state(n, lam, t)
        with mp.workdps(DPS):
            ref = float(mp_point(n, lam, mp.mpf(t)))
        assert abs(float(st.P) / ref - 1) < 1e-12
