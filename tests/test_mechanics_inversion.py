"""Forward/inverse round trips, broadcasting, auto mode, scaling helpers, shipped/cached table."""

import numpy as np
import pytest

import pipeline.mechanics as M
from pipeline.mechanics.mdn import pulloff_mdn_exact

pytestmark = pytest.mark.filterwarnings("error")

NM = 1e-9
rng = np.random.default_rng(7)


def _cases(k):
    n = np.concatenate([[2.0, 20.0], rng.uniform(2, 20, k - 2)])
    R = rng.uniform(5, 100, k) * NM
    S = rng.uniform(0.5, 3, k)
    E = rng.uniform(20, 500, k) * 1e9
    W = rng.uniform(0.01, 2.0, k)
    h = np.exp(rng.uniform(np.log(0.1 * NM), np.log(10 * NM), k))
    return n, M.q_from_rs(n, R, S), E, W, h


@pytest.mark.parametrize("model", ["mdn", "rigid"])
@pytest.mark.parametrize("exact", [False, True])
def test_round_trip(model, exact):
    n, Q, E, W, h = _cases(40)
    F = M.pulloff_force(n, Q, E, W, h, model=model, exact=exact)
    W2 = M.work_of_adhesion(F, n, Q, E, h, model=model, exact=exact)
    assert np.max(np.abs(W2 / W - 1)) < 1e-9


@pytest.mark.parametrize("law", ["lj", "tri1", "tri2"])
def test_round_trip_rigid_laws(law):
    n, Q, E, W, h = _cases(40)
    F = M.pulloff_force(n, Q, E, W, h, potential=law, model="rigid")
    assert np.max(np.abs(M.work_of_adhesion(F, n, Q, E, h, potential=law, model="rigid") / W - 1)) < 1e-12
    # closed form: W = F h / (ratio pi (n h Q)^(2/n))
    W3 = F * h / (M.rigid_pulloff_ratio(n, law) * np.pi * (n * h * Q) ** (2 / n))
    assert np.allclose(W3, W, rtol=1e-12)


def test_fast_vs_exact_inversion():
    n, Q, E, W, h = _cases(40)
    F = M.pulloff_force(n, Q, E, W, h, exact=True)
    Wf = M.work_of_adhesion(F, n, Q, E, h)
    assert np.max(np.abs(Wf / W - 1)) < 1e-6


@pytest.mark.parametrize("exact", [False, True])
def test_round_trip_auto_outside_ambiguous_band(exact):
    """auto: exact round trip wherever the point is not in the <= 5 % band just above Lambda_b."""
    n, Q, E, W, h = _cases(60)
    lam = M.transition_parameter(n, Q, E, W, h)
    F = M.pulloff_force(n, Q, E, W, h, model="auto", exact=exact)
    W2 = M.work_of_adhesion(F, n, Q, E, h, model="auto", exact=exact)
    fwd_rigid = M.model_used(n, Q, E, h, W=W)
    inv_rigid = M.model_used(n, Q, E, h, F_p=F)
    assert np.array_equal(fwd_rigid, lam < M.lambda_boundary(n))
    same = fwd_rigid == inv_rigid
    assert np.max(np.abs(W2[same] / W[same] - 1)) < 1e-9
    # disagreement only for M-D-n points just above the boundary
    assert np.all(~fwd_rigid[~same])
    assert np.all(lam[~same] < 1.2 * M.lambda_boundary(n[~same]))


def test_auto_picks_the_right_solutions():
    n = np.array([2.0, 4.0, 9.0])
    lam = np.array([1e-3, 1.0, 0.3])
    auto = M.pulloff_nd(n, lam, model="auto")
    rigid = lam < M.lambda_boundary(n)
    assert np.allclose(auto[rigid], M.pulloff_nd(n, lam, model="rigid")[rigid], rtol=1e-15)
    assert np.allclose(auto[~rigid], M.pulloff_nd(n, lam)[~rigid], rtol=1e-15)


def test_broadcasting_monte_carlo_shape():
    k = 50
    n = rng.uniform(2, 8, (k, 1))
    Q = M.q_from_rs(n, 30 * NM, 1.0)
    E = rng.uniform(70, 170, (k, 1)) * 1e9
    F = rng.uniform(5, 50, (k, 1)) * 1e-9
    h = np.geomspace(0.3, 6, 30) * NM
    Wa = M.work_of_adhesion(F, n, Q, E, h)
    assert Wa.shape == (k, 30)
    assert np.all(np.isfinite(Wa)) and np.all(Wa > 0)
    Wa_loop = np.array([M.work_of_adhesion(F[i, 0], n[i, 0], Q[i, 0], E[i, 0], h) for i in range(k)])
    assert np.allclose(Wa, Wa_loop, rtol=1e-13)
    assert np.ndim(M.work_of_adhesion(1e-8, 3.0, M.q_from_rs(3.0, 20 * NM), 1e11, 1 * NM)) == 0
    assert isinstance(M.pulloff_nd(3.0, 0.5), float)


def test_lambda_from_g_identity():
    n = np.array([2.0, 3.3, 11.0, 20.0])
    lam = np.array([1e-5, 0.4, 30.0, 2e5])
    for model in ("mdn", "rigid"):
        G = M.pulloff_nd(n, lam, model=model, exact=True) * lam ** ((n + 1) / n)
        assert np.allclose(M.lambda_from_g(G, n, model=model, exact=True), lam, rtol=1e-10)


def test_g_group_identity():
    """G = F_p / (pi E* h^(1+1/n) Q^(1/n)) equals P~ Lambda^((n+1)/n) (dimensional bookkeeping)."""
    n, Q, E, W, h = _cases(20)
    lam = M.transition_parameter(n, Q, E, W, h)
    F = M.pulloff_force(n, Q, E, W, h)
    G = F / (np.pi * E * h ** (1 + 1 / n) * Q ** (1 / n))
    assert np.allclose(G, M.pulloff_nd(n, lam) * lam ** ((n + 1) / n), rtol=1e-12)


def test_scaling_helpers():
    n, R, S = 4.5, 25 * NM, 1.7
    Q = M.q_from_rs(n, R, S)
    assert Q == pytest.approx(S ** (n - 2) * R ** (n - 1), rel=1e-13)
    assert M.r_from_q(n, Q, S) == pytest.approx(R, rel=1e-13)
    assert M.q_from_rs(2, R, 5.0) == pytest.approx(R, rel=1e-14)
    # Lambda for n = 2 reduces to Maugis' sigma_0 (R / (W E*^2))^(1/3)
    E, W, h = 90e9, 0.2, 0.5 * NM
    assert M.transition_parameter(2, R, E, W, h) == pytest.approx(W / h * (R / (W * E**2)) ** (1 / 3), rel=1e-13)
    # extreme but valid geometry: Q ~ 1e-170 (n = 20, R = 1 nm) stays finite
    Q20 = M.q_from_rs(20.0, 1 * NM)
    assert 0 < Q20 < 1e-160
    assert np.isfinite(M.pulloff_force(20.0, Q20, 1e11, 0.1, 1 * NM))


def test_branch_outputs():
    b = M.mdn_branch(4.0, 0.8, num=300)
    assert len(b.a) == 300 and np.all(np.diff(b.a) < 0)
    assert -b.P[b.i_pulloff] == pytest.approx(b.pulloff, rel=1e-12)
    assert b.pulloff == pytest.approx(float(pulloff_mdn_exact(4.0, 0.8)), rel=1e-14)
    assert np.all(b.P >= -b.pulloff - 1e-15)
    # Eq. 9 / Eq. 10 consistency and the Hertz limit at large a (m -> 1)
    from scipy.special import beta

    s = np.sqrt(b.m**2 - 1)
    assert np.allclose(b.delta, 0.5 * beta(2, 0.5) * b.a**4 - 1.6 * b.a * s, rtol=1e-12, atol=1e-14)
    Q, E, W, h = M.q_from_rs(4.0, 30 * NM), 150e9, 0.1, 1 * NM
    si = M.mdn_branch_si(4.0, Q, E, W, h, num=100)
    assert si.pulloff == pytest.approx(M.pulloff_force(4.0, Q, E, W, h, exact=True), rel=1e-12)
    assert -si.P.min() == pytest.approx(si.pulloff, rel=1e-12)


def test_table_matches_fresh_solve():
    from pipeline.mechanics.tables import build_table

    s, x, y = build_table()
    idx_n = rng.integers(0, len(s), 12)
    idx_x = rng.integers(0, len(x), 12)
    fresh = np.log(pulloff_mdn_exact(np.exp(s[idx_n]), np.exp(x[idx_x])))
    assert np.allclose(fresh, y[idx_n, idx_x], rtol=0, atol=1e-13)
