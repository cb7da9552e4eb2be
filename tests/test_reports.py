"""Reports (per-tip CSV, results/summary.csv) and the stage 4-5 figures."""

import csv

import numpy as np
import pytest

from pipeline import mechanics as mech
from pipeline.adhesion_range.figures import map_boundary, map_coordinates
from pipeline.adhesion_range.report import SUMMARY_COLUMNS, fmt, write_summary
from pipeline.adhesion_range.stage import run_adhesion_range
from pipeline.inversion.stage import run_inversion
from pipeline.mechanics.figures import plot_rigid_laws
from pipeline.synth.stage_inputs import write_synthetic_inputs

LAWS = ["dugdale", "lj", "tri1", "tri2"]


def _tip(tmp, tip, W, R, E, ns, extra=()):
    ivs = [dict(name="s000", n=ns[0], R=R, reference=True)] + [
        dict(name=f"s{i:03d}", n=n, R=R) for i, n in enumerate(ns[1:], 1)
    ]
    fits, forces, cfg = write_synthetic_inputs(
        tmp / tip,
        W_A=W,
        h=4.6e-9,
        E_star=E,
        intervals=ivs + list(extra),
        seed=3,
        sigma_n=0.01,
        sigma_lnR=0.005,
        rel_sd_curve=0.04,
        n_curves=64,
        u_k=0.004,
    )
    inv = tmp / tip / "inversion.h5"
    run_inversion(
        fits,
        forces,
        inv,
        intervals=cfg,
        E_star=E,
        u_E_star=0.05 * E,
        h_grid=np.geomspace(0.2e-9, 20e-9, 70),
        laws=LAWS,
        solver_mode="auto",
        mc_samples=300,
        seed=7,
        tip=tip,
    )
    rng = tmp / tip / "adhesion_range.h5"
    run_adhesion_range(inv, rng, tmp / tip / f"{tip}_report.csv", tmp / tip, tip=tip)
    return rng


@pytest.fixture(scope="module")
def two_tips(tmp_path_factory):
    tmp = tmp_path_factory.mktemp("reports")
    a = _tip(tmp, "tipA", 0.0467, 30e-9, 165e9, [2, 3, 4, 5, 6], extra=[dict(name="s900", n=2.05, R=30e-9)])
    b = _tip(tmp, "tipB", 0.0798, 10e-9, 80e9, [2, 4, 6])
    out = tmp / "summary.csv"
    write_summary({"tipA": a, "tipB": b}, out)
    return tmp, out


def _rows(path):
    with open(path, newline="") as fh:
        return list(csv.DictReader(fh))


def test_summary_table(two_tips):
    _, out = two_tips
    rows = _rows(out)
    assert list(rows[0]) == SUMMARY_COLUMNS
    assert [(r["tip"], r["law"]) for r in rows] == [(t, law) for t in ("tipA", "tipB") for law in LAWS]
    assert "nan" not in out.read_text().lower()
    for r in rows:
        assert r["status"] == "ok", r
        h, lo, hi = float(r["h_nm"]), float(r["h_low_nm"]), float(r["h_high_nm"])
        assert lo < h < hi and r["ci_level"] == "0.95"
        assert float(r["W_A_low_mJ_per_m2"]) < float(r["W_A_mJ_per_m2"]) < float(r["W_A_high_mJ_per_m2"])
        if r["law"] == "dugdale":
            assert h == pytest.approx(4.6, rel=0.05)
            assert float(r["W_A_mJ_per_m2"]) == pytest.approx(46.7 if r["tip"] == "tipA" else 79.8, rel=0.03)
            assert float(r["W_A_ref_max_rel_change_over_h"]) < 0.02
        if r["law"] == "tri2":
            assert float(r["h_full_range_nm"]) == pytest.approx(2 * h, rel=1e-3)
        if r["law"] == "lj":
            assert float(r["z0_lj_nm"]) == pytest.approx(h / 0.974, rel=1e-3)
            assert r["h_full_range_nm"] == "" and "z0 = h/0.974" in r["notes"]
    a = {r["law"]: r for r in rows if r["tip"] == "tipA"}
    assert a["dugdale"]["n_intervals_used"] == "6" and a["dugdale"]["n_intervals_crossing"] == "4"
    assert "s900: n_too_close_to_2" in a["dugdale"]["notes"]
    # Tri2's full range equals Tri1's h (same law, peak at h vs 2h): the paper's Table 1 columns
    assert float(a["tri2"]["h_full_range_nm"]) == pytest.approx(float(a["tri1"]["h_nm"]), rel=3e-3)


def test_tip_report(two_tips):
    tmp, _ = two_tips
    path = tmp / "tipA" / "tipA_report.csv"
    rows = {r["interval"]: r for r in _rows(path)}
    assert list(rows) == ["s000", "s001", "s002", "s003", "s004", "s900"]
    assert "nan" not in path.read_text().lower()
    for col in (
        "scans",
        "n",
        "u_n",
        "R_nm",
        "S",
        "F_p_nN",
        "u_F_p_nN",
        "n_curves",
        "W_A_dugdale_mJ_per_m2",
        "h_dugdale_nm",
        "h_dugdale_low_nm",
        "h_dugdale_high_nm",
        "h_dugdale_status",
        "Lambda_at_estimate",
        "rigid_valid",
        "h_tri2_full_range_nm",
        "z0_lj_nm",
    ):
        assert col in rows["s000"], col
    assert rows["s000"]["h_dugdale_status"] == "reference" and rows["s000"]["h_dugdale_nm"] == ""
    assert rows["s900"]["h_dugdale_status"] == "n_too_close_to_2" and rows["s900"]["h_dugdale_nm"] == ""
    r = rows["s002"]
    assert r["h_dugdale_status"] == "ok"
    assert float(r["h_dugdale_low_nm"]) < float(r["h_dugdale_nm"]) < float(r["h_dugdale_high_nm"])
    assert float(r["h_tri2_full_range_nm"]) == pytest.approx(2 * float(r["h_tri2_nm"]), rel=1e-3)
    assert r["rigid_valid"] == "true" and r["model_used_at_estimate"] == "rigid"
    assert float(r["R_nm"]) == pytest.approx(30, rel=0.05)
    assert float(r["F_p_nN"]) > 0 and int(r["n_curves"]) == 64
    # Maugis parameter given for the paraboloidal reference, and small (DMT, paper Sec. 4.1: mu < 0.1)
    assert 0 < float(rows["s000"]["maugis_lambda_at_estimate"]) < 0.1


def test_figures_written(two_tips):
    tmp, _ = two_tips
    for name in ("W_A_vs_h.png", "adhesion_map.png"):
        p = tmp / "tipA" / name
        assert p.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n" and p.stat().st_size > 20_000
    out = tmp / "rigid_laws.png"
    plot_rigid_laws(out)
    assert out.read_bytes()[:4] == b"\x89PNG"


@pytest.mark.parametrize("n,S", [(2.0, 1.0), (3.0, 1.0), (4.5, 2.0), (6.0, 0.7)])
def test_adhesion_map_algebra(n, S):
    """Map coordinates: Lambda = (sigma_0/E*)^(n/(2n-1)) (R_eff/h)^((n-1)/(2n-1)), R_eff = R S^((n-2)/(n-1)),
    checked against Eq. 8 (corrected) from the mechanics; the boundary line has Lambda = Lambda_b(n)."""
    R, E, W = 20e-9, 100e9, 0.3
    h = np.geomspace(0.3e-9, 5e-9, 7)
    Q = S ** (n - 2) * R ** (n - 1)
    x, y = map_coordinates(W, h, n, Q, E)
    lam_map = x ** (n / (2 * n - 1)) * y ** ((n - 1) / (2 * n - 1))
    np.testing.assert_allclose(lam_map, mech.transition_parameter(n, Q, E, W, h), rtol=1e-10)
    np.testing.assert_allclose(y, R * S ** ((n - 2) / (n - 1)) / h, rtol=1e-12)
    xb = np.geomspace(1e-5, 1e-2, 5)
    lb = -0.002194 * n**2 + 0.067185 * n + 0.022056
    yb = map_boundary(n, xb)
    np.testing.assert_allclose(xb ** (n / (2 * n - 1)) * yb ** ((n - 1) / (2 * n - 1)), lb, rtol=1e-10)


def test_fmt_never_prints_nan():
    assert fmt(float("nan")) == "" and fmt(None) == "" and fmt(float("inf")) == ""
    assert fmt(np.float64(4.61234567)) == "4.612" and fmt(3) == "3" and fmt(True) == "true"
