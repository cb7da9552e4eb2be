"""Elastic adhesive contact for every traction law (pipeline.mechanics.elastic_contact), checked
against independent results: the M-D-n solution (Dugdale), the rigid closed forms (E* -> inf),
an independent L-J implementation (tests/lj_sphere_reference.py), the JKR limit, quadrature of
the kernel and of the laws, and the paper's Fig. 4 and Fig. 7 numbers."""

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from scipy import integrate
from scipy import special as sp

import pipeline.mechanics as M
from pipeline.mechanics.elastic_contact import _disk_integral, elastic_path, elastic_pulloff, kappa_from_lambda
from pipeline.mechanics.mdn import pulloff_mdn_exact
from pipeline.mechanics.traction_laws import get_law, tabulated_law

NM = 1e-9


def _mdn_ratio(n, lam):
    return pulloff_mdn_exact(n, lam) / (n ** (2.0 / n) * lam ** ((n - 2.0) / n))


# ----------------------------------------------------------------------- building blocks
@pytest.mark.parametrize(
    "b,r", [(1.0, 0.0), (1.0, 0.3), (1.0, 0.999), (1.0, 1.0), (1.0, 1.001), (1.0, 2.5), (0.2, 7.0)]
)
def test_disk_kernel_closed_form_vs_ring_quadrature(b, r):
    """int_disk dA/|r - rho| from the E/K closed form equals the ring-by-ring quadrature
    int_0^b 4 s K(4rs/(r+s)^2)/(r+s) ds (log singularity at s = r handled by quad)."""

    def ring(s):
        if r + s == 0 or s == r:
            return 0.0
        return 4.0 * s * sp.ellipkm1(((r - s) / (r + s)) ** 2) / (r + s)

    pts = [r] if 0 < r < b else None
    ref = integrate.quad(ring, 0.0, b, points=pts, limit=400, epsabs=1e-13, epsrel=1e-12)[0]
    assert float(_disk_integral(b, r)) == pytest.approx(ref, rel=1e-9)


@pytest.mark.parametrize("law", ["dugdale", "tri1", "tri2", "lj"])
def test_cell_means_of_the_laws_vs_quadrature(law):
    """Segment integrals of T(y(u)) (ra + L u) L (exact for piecewise-linear laws, Gauss for L-J)
    against adaptive quadrature with the break points given; derivatives against differences."""
    L = get_law(law)
    rng = np.random.default_rng(3)
    k = 25
    ra, length = rng.uniform(0, 2, k), rng.uniform(1e-3, 0.2, k)
    ya = rng.uniform(-0.3, 2.3, k)
    yb = ya + rng.normal(0, 0.4, k)
    if law == "lj":
        ya, yb = np.maximum(ya, -0.2), np.maximum(yb, -0.2)
        yb = ya + np.clip(yb - ya, -0.05, 0.05)  # 6-point Gauss per half-cell: short segments
    I, da, db = L.segment_moments(ra, length, ya, yb)
    brk = np.array([0.0, 0.5, 1.0, 2.0])
    for i in range(k):
        f = lambda u: float(L.traction(ya[i] + (yb[i] - ya[i]) * u)) * (ra[i] + length[i] * u) * length[i]
        d = yb[i] - ya[i]
        pts = sorted(u for u in ((brk - ya[i]) / d if d else []) if 0 < u < 1)
        ref = integrate.quad(f, 0.0, 1.0, points=pts or None, limit=200, epsabs=1e-14)[0]
        assert I[i] == pytest.approx(ref, rel=1e-7 if law == "lj" else 1e-10, abs=1e-12)
    e = 1e-7
    fd_a = (L.segment_moments(ra, length, ya + e, yb)[0] - L.segment_moments(ra, length, ya - e, yb)[0]) / (2 * e)
    fd_b = (L.segment_moments(ra, length, ya, yb + e)[0] - L.segment_moments(ra, length, ya, yb - e)[0]) / (2 * e)
    assert np.allclose(da, fd_a, rtol=1e-5, atol=1e-7)
    assert np.allclose(db, fd_b, rtol=1e-5, atol=1e-7)


def test_laws_have_unit_work_and_the_paper_peaks():
    for law, peak in (("dugdale", 1.0), ("tri1", 2.0), ("tri2", 1.0), ("lj", 0.9997)):
        L = get_law(law)
        s = np.linspace(0.0, 3000.0, 3_000_001) if law == "lj" else np.linspace(0.0, 2.0, 200_001)
        t = L.traction(s)
        assert integrate.trapezoid(np.clip(t, 0, None), s) == pytest.approx(1.0, abs=2e-3 if law == "lj" else 1e-5)
        assert t.max() == pytest.approx(peak, rel=1e-3)


def test_tabulated_law_validation():
    with pytest.raises(ValueError, match="area"):
        tabulated_law([0.0, 1.0], [1.0, 0.5])
    with pytest.raises(ValueError, match="start at 0"):
        tabulated_law([0.5, 1.0], [1.0, 1.0])
    with pytest.raises(ValueError, match="finite"):
        tabulated_law([0.0, np.nan], [1.0, 1.0])


# ------------------------------------------------------------------ Dugdale = M-D-n
@pytest.mark.parametrize(
    "n,lam", [(2, 0.01), (2, 1.0), (2, 10.0), (3, 0.3), (5, 0.1), (5, 3.0), (10, 1.0), (20, 0.03), (20, 10.0)]
)
def test_dugdale_equals_mdn(n, lam):
    """Issue #21: within 0.5 % of the M-D-n solution (measured: <= 0.3 % over n 2-20, Lambda 0.01-30)."""
    r = elastic_pulloff(n, lam, "dugdale")
    assert r.ratio == pytest.approx(_mdn_ratio(n, lam), rel=0.004)
    assert r.pulloff_nd == pytest.approx(pulloff_mdn_exact(n, lam), rel=0.004)


@settings(max_examples=6, deadline=None, derandomize=True)
@given(n=st.floats(2.0, 20.0), log_lam=st.floats(np.log(0.01), np.log(10.0)))
def test_dugdale_equals_mdn_anywhere(n, log_lam):
    lam = float(np.exp(log_lam))
    assert elastic_pulloff(n, lam, "dugdale").ratio == pytest.approx(_mdn_ratio(n, lam), rel=0.005)


@pytest.mark.parametrize("R,S", [(30 * NM, 1.0), (10 * NM, 2.0)])
def test_fig4_cases(R, S):
    """Paper Fig. 4 (E* = 164.8 GPa, W_A = 0.1 J/m^2): the solver matches M-D-n (the paper's FE
    reached 3.5 %), and rigid vs elastic differs by < 3.5 %, by > 2 % only for h < 0.4 nm."""
    E, W = 164.8e9, 0.1
    for n in (2, 3, 4, 5):
        Q = M.q_from_rs(n, R, S)
        for h in (0.3, 0.45, 2.0):
            lam = float(M.transition_parameter(n, Q, E, W, h * NM))
            el = elastic_pulloff(n, lam, "dugdale").pulloff_nd
            assert el == pytest.approx(float(pulloff_mdn_exact(n, lam)), rel=2e-3)
            d = float(M.pulloff_nd(n, lam, model="rigid")) / el - 1.0
            assert 0.0 < d < 0.035
            assert d < 0.02 or h < 0.4


# ---------------------------------------------------------------------- rigid limit
@pytest.mark.parametrize("law", ["dugdale", "lj", "tri1", "tri2"])
def test_rigid_limit_equals_closed_forms(law):
    """E* -> inf (Lambda = 1e-4): the elastic pull-off is the rigid closed form of rigid.py."""
    for n in (2.0, 3.0, 5.0, 10.0, 20.0):
        r = elastic_pulloff(n, 1e-4, law)
        assert r.ratio == pytest.approx(float(M.rigid_pulloff_ratio(n, law)), rel=2.5e-3)


def test_tabulated_law_rigid_limit_vs_quadrature():
    """A user table (not one of the named laws): its rigid limit from the solver equals the
    maximum over the apex gap of int tau(D + z) dA(z) computed by quadrature."""
    s = np.linspace(0.0, 1.6, 9)
    tau = np.exp(-2.0 * s) * s * (1.6 - s)
    tau = tau / integrate.trapezoid(tau, s)
    law = tabulated_law(s, tau, name="test-table")
    n = 3.0
    p = 2.0 / n

    def rigid(D):  # F/F_Dug = int_0^inf tau(D + w^(1/p)) dw, w = z^p  (plan area pi (n Q z)^(2/n))
        kinks = [(sk - D) ** p for sk in s[1:] if sk > D]
        return integrate.quad(
            lambda w: float(np.interp(D + w ** (1 / p), s, tau, right=0.0)),
            0,
            kinks[-1],
            points=kinks[:-1] or None,
            limit=400,
        )[0]

    ref = max(rigid(D) for D in np.linspace(0.0, 1.5, 301))
    assert elastic_pulloff(n, 1e-4, law).ratio == pytest.approx(ref, rel=3e-3)


# ------------------------------------------------------------------- L-J, n = 2
@pytest.mark.parametrize("lam", [0.3, 1.0])
def test_lj_sphere_against_independent_implementation(lam):
    """n = 2, L-J 3-9 (Greenwood 1997 / Feng 2000 problem; Tabor mu = 0.974 Lambda) against a
    second implementation with hat-function pressures, nodal collocation and arc-length
    continuation on a uniform grid (measured agreement 1e-4 to 2.4e-4 for Lambda 0.1-2)."""
    from lj_sphere_reference import pulloff_ratio

    ref = pulloff_ratio(float(kappa_from_lambda(2.0, lam)), nodes=241)
    assert elastic_pulloff(2.0, lam, "lj").ratio == pytest.approx(ref, rel=1e-3)


def test_lj_sphere_bradley_and_jkr_limits():
    """Pull-off / (pi R W_A) = P~ (n = 2): 2 (Bradley/DMT) for mu -> 0, 1.5 (JKR) for mu -> inf,
    decreasing in between (Greenwood 1997, Fig. 6)."""
    lams = [1e-3, 0.1, 1.0, 3.0, 30.0]
    p = [elastic_pulloff(2.0, lam, "lj").pulloff_nd for lam in lams]
    assert p[0] == pytest.approx(2.0, rel=1e-3)
    assert p[-1] == pytest.approx(1.5, rel=3e-3)
    assert np.all(np.diff(p) < 0)


# ---------------------------------------------------------------------- paper Fig. 7
def test_fig7_law_differences_at_n5():
    """n = 5, R = 30 nm, S = 1: Tri1 about +17 % and Tri2 about -23 % against M-D-n (paper Sec. 4.3),
    and elastic vs rigid within 8.5 % (the largest: Tri1 at h = 0.3 nm; paper: < 8 %, > 5 % only
    for Tri1 at 0.3 nm)."""
    E, W, n = 164.8e9, 0.1, 5.0
    Q = M.q_from_rs(n, 30 * NM, 1.0)
    for h in (1.0, 2.0):
        lam = float(M.transition_parameter(n, Q, E, W, h * NM))
        ref = float(pulloff_mdn_exact(n, lam))
        assert 1.15 < elastic_pulloff(n, lam, "tri1").pulloff_nd / ref < 1.18
        assert 0.765 < elastic_pulloff(n, lam, "tri2").pulloff_nd / ref < 0.785
    lam = float(M.transition_parameter(n, Q, E, W, 0.3 * NM))
    dev = {
        law: 1.0 - elastic_pulloff(n, lam, law).pulloff_nd / float(M.pulloff_nd(n, lam, potential=law, model="rigid"))
        for law in ("dugdale", "lj", "tri1", "tri2")
    }
    assert 0.05 < dev["tri1"] < 0.085
    assert max(dev["dugdale"], dev["lj"], dev["tri2"]) < 0.035


# ---------------------------------------------------------------------- path, errors
def test_path_folds_in_displacement_but_not_in_the_control():
    """JKR side (Lambda = 3): the approach D turns along the path (a displacement-controlled
    retraction would jump), the contact radius does not; the pull-off is the path maximum."""
    p = elastic_path(2.0, 3.0, "dugdale")
    dD = np.diff(p["D"])
    assert np.any(dD > 0) and np.any(dD < 0)
    a = p["a"][p["a"] > 0]
    assert np.all(np.diff(a) < 0)
    assert p["f"].max() == pytest.approx(_mdn_ratio(2.0, 3.0), rel=5e-3)


def test_error_estimate_bounds_the_error():
    for n, lam in ((2.0, 10.0), (5.0, 1.0)):
        r = elastic_pulloff(n, lam, "dugdale", estimate_error=True)
        assert abs(r.ratio / _mdn_ratio(n, lam) - 1.0) <= r.error_estimate + 5e-4


def test_domain_checked():
    with pytest.raises(ValueError, match="n in"):
        elastic_pulloff(1.5, 0.1)
    with pytest.raises(ValueError, match="Lambda"):
        elastic_pulloff(3.0, 100.0)


# --------------------------------------------------------------------------- slow
@pytest.mark.slow
def test_dugdale_equals_mdn_full_grid():
    worst = 0.0
    for n in (2.0, 2.5, 3.0, 4.0, 5.0, 7.0, 10.0, 14.0, 20.0):
        for lam in (0.01, 0.03, 0.1, 0.3, 1.0, 3.0, 10.0, 30.0):
            worst = max(worst, abs(elastic_pulloff(n, lam, "dugdale").ratio / _mdn_ratio(n, lam) - 1.0))
    assert worst < 0.005


@pytest.mark.slow
@pytest.mark.parametrize("law", ["lj", "tri1", "tri2"])
def test_other_laws_converge_with_the_grid(law):
    """Level 2 (default) against level 4 over n 2-20, Lambda 0.01-30 (no reference exists; the
    Dugdale comparison calibrates what this difference means: level 2 error <= 0.3 %)."""
    for n in (2.0, 3.0, 5.0, 10.0, 20.0):
        for lam in (0.01, 0.1, 1.0, 3.0, 10.0, 30.0):
            a = elastic_pulloff(n, lam, law, level=2.0).ratio
            b = elastic_pulloff(n, lam, law, level=4.0).ratio
            assert a == pytest.approx(b, rel=0.005), (n, lam)


@pytest.mark.slow
@pytest.mark.parametrize("lam", [0.1, 2.0])
def test_lj_sphere_against_independent_implementation_fine(lam):
    from lj_sphere_reference import pulloff_ratio

    ref = pulloff_ratio(float(kappa_from_lambda(2.0, lam)), nodes=481)
    assert elastic_pulloff(2.0, lam, "lj", level=4.0).ratio == pytest.approx(ref, rel=5e-4)
