"""n = 2 against an independent Maugis (1992) implementation, and the DMT / rigid (Lambda -> 0)
and JKR (Lambda -> inf) limits for power-law tips."""

import numpy as np
import pytest
from scipy.optimize import minimize_scalar
from scipy.special import beta

import pipeline.mechanics as M

pytestmark = pytest.mark.filterwarnings("error")


# ----------------------------------------------------------------- Maugis (1992), own variables
def maugis_pbar(t, lam):
    """P-bar = P/(pi W R) on the Maugis branch at m = 1 + e^t; A-bar from the quadratic in A."""
    e = np.exp(t)
    m = 1.0 + e
    s = np.sqrt(e * (2.0 + e))
    asec = np.arctan(s)
    alpha = 0.5 * lam * (s + (m * m - 2.0) * asec)
    beta_ = 4.0 * lam**2 / 3.0 * (s * asec - m + 1.0)
    A = 2.0 / (beta_ + np.sqrt(beta_**2 + 4.0 * alpha))  # root of alpha A^2 + beta A - 1 = 0
    return A**3 - lam * A**2 * (s + m * m * asec)


def maugis_pulloff(lam):
    ts = np.linspace(-20.0, 25.0, 451)
    k = int(np.argmin(maugis_pbar(ts, lam)))
    res = minimize_scalar(
        maugis_pbar,
        bounds=(ts[max(k - 1, 0)], ts[min(k + 1, 450)]),
        args=(lam,),
        method="bounded",
        options={"xatol": 1e-12},
    )
    return -min(res.fun, maugis_pbar(ts[k], lam))


MAUGIS_LAMBDA = np.geomspace(0.01, 100.0, 25)


@pytest.fixture(scope="module")
def maugis_ref():
    return np.array([maugis_pulloff(l) for l in MAUGIS_LAMBDA])


def test_maugis_conversion_factor():
    assert M.maugis_from_transition(1.0) == pytest.approx(2 * (9 / (16 * np.pi)) ** (1 / 3), rel=1e-15)
    assert M.maugis_from_transition(1.0) == pytest.approx(1.1272, abs=1e-4)
    R, E, W, h = 20e-9, 100e9, 0.05, 0.4e-9
    assert M.maugis_parameter(R, E, W, h) == pytest.approx(
        M.maugis_from_transition(M.transition_parameter(2, R, E, W, h)), rel=1e-13
    )


def test_n2_exact_matches_maugis(maugis_ref):
    Lam = MAUGIS_LAMBDA / M.maugis_from_transition(1.0)
    got = M.pulloff_nd(2.0, Lam, exact=True)
    assert np.max(np.abs(got / maugis_ref - 1)) < 1e-8


def test_n2_fast_matches_maugis(maugis_ref):
    Lam = MAUGIS_LAMBDA / M.maugis_from_transition(1.0)
    assert np.max(np.abs(M.pulloff_nd(2.0, Lam) / maugis_ref - 1)) < 1e-6


def test_n2_dmt_and_jkr_limits_dimensional():
    R, E, W = 25e-9, 150e9, 0.08
    # DMT: h large -> Lambda small; JKR: h tiny -> Lambda large (inside the supported domain)
    h_dmt = W / (1e-6 * (R / (W * E**2)) ** (-1 / 3))
    h_jkr = W / (1e6 * (R / (W * E**2)) ** (-1 / 3))
    assert M.transition_parameter(2, R, E, W, h_dmt) == pytest.approx(1e-6, rel=1e-12)
    F_dmt = M.pulloff_force(2, R, E, W, h_dmt, exact=True)
    F_jkr = M.pulloff_force(2, R, E, W, h_jkr, exact=True)
    assert F_dmt == pytest.approx(2 * np.pi * W * R, rel=1e-8)
    assert F_jkr == pytest.approx(1.5 * np.pi * W * R, rel=1e-10)
    assert M.pulloff_force(2, R, E, W, h_dmt, model="rigid") == pytest.approx(2 * np.pi * W * R, rel=1e-14)


# ----------------------------------------------------------------- power-law limits
@pytest.mark.parametrize("n", [2.0, 2.7, 3.0, 5.0, 8.5, 12.0, 20.0])
def test_rigid_limit_is_eq12(n):
    """Lambda -> 0: M-D-n -> rigid Dugdale, Eq. 12: F = (W/h) pi (n h Q)^(2/n)."""
    small = np.array([1e-5, 1e-6])
    ratio = M.pulloff_nd(n, small, exact=True) / M.pulloff_nd(n, small, model="rigid")
    assert np.all(ratio <= 1 + 1e-12)
    assert abs(ratio[1] - 1) < 2e-9
    assert abs(ratio[1] - 1) <= abs(ratio[0] - 1) + 1e-13
    # dimensional Eq. 12
    Q, E, W, h = M.q_from_rs(n, 30e-9, 1.3), 160e9, 0.1, 2e-9
    assert M.pulloff_force(n, Q, E, W, h, model="rigid") == pytest.approx(
        W / h * np.pi * (n * h * Q) ** (2 / n), rel=1e-13
    )


def _jkr_numeric(n):
    """Independent: minimise the power-law JKR curve P~ = B(n/2+1,1/2) a^(n+1)/pi - sqrt(8/pi) a^1.5."""
    f = lambda a: beta(n / 2 + 1, 0.5) / np.pi * a ** (n + 1) - np.sqrt(8 / np.pi) * a**1.5
    return -minimize_scalar(f, bounds=(1e-3, 10.0), method="bounded", options={"xatol": 1e-12}).fun


@pytest.mark.parametrize("n", [2.0, 2.5, 3.0, 4.0, 5.0, 7.0, 10.0, 15.0, 20.0])
def test_jkr_limit(n):
    jkr = float(M.jkr_limit_nd(n))
    assert jkr == pytest.approx(_jkr_numeric(n), rel=1e-10)
    if n == 2.0:
        assert jkr == pytest.approx(1.5, rel=1e-15)
    p = M.pulloff_nd(n, np.array([1e3, 1e4, 1e6]), exact=True)
    assert p[2] == pytest.approx(jkr, rel=1e-10)
    # approach like Lambda^-2 (Dugdale zone of width ~ Lambda^-2 a)
    d3, d4 = p[0] - jkr, p[1] - jkr
    assert d3 > 0 and d4 > 0 and 60 < d3 / d4 < 160


def test_dimensional_jkr_formula():
    n, R, S, E, W = 4.0, 30e-9, 1.0, 160e9, 0.1
    Q = M.q_from_rs(n, R, S)
    lam_target = 1e6
    h = W * (Q * W ** (1 - n) / E**n) ** (1 / (2 * n - 1)) / lam_target
    F = M.pulloff_force(n, Q, E, W, h, exact=True)
    F_jkr = np.pi * M.jkr_limit_nd(n) * (Q**3 * W ** (n + 1) * E ** (n - 2)) ** (1 / (2 * n - 1))
    assert F == pytest.approx(F_jkr, rel=1e-9)
