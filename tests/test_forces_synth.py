"""Synthetic curves: pull-off recovery, contact-slope InvOLS, statistics, stage output."""

import h5py
import numpy as np
import pytest

from pipeline.forces.contact_slope import invols_from_curves
from pipeline.forces.pulloff import detect_pulloff
from pipeline.forces.reading import read_curves
from pipeline.forces.stage import run_forces
from pipeline.forces.statistics import generalized_esd, interval_stats, modified_z_scores
from pipeline.synth.force_curves import make_force_curve, write_curve_csv


def _retract(c):
    m = c.segment == "retract"
    return -c.height[m], c.deflection_V[m]


@pytest.mark.parametrize("noise", [0.05e-9, 0.1e-9, 0.2e-9])
@pytest.mark.parametrize("k,F_p", [(0.2, 10e-9), (0.1, 5e-9), (0.5, 30e-9)])
def test_pulloff_recovered_within_1_percent(noise, k, F_p):
    invols = 60e-9
    for seed in range(5):
        c = make_force_curve(F_p, k, invols, seed=seed, noise=noise, offset_V=0.3, tilt=-4e5, n_points=2000)
        z, d = _retract(c)
        po = detect_pulloff(z, d)
        F = k * po.delta * invols
        assert F == pytest.approx(F_p, rel=0.01)
        assert po.delta == pytest.approx(c.truth["delta_V"], rel=0.01)
        assert po.baseline.slope == pytest.approx(-4e5, abs=5 * po.baseline.u_slope + 2e4)
        assert po.baseline.rms == pytest.approx(noise / invols, rel=0.15)


def test_generator_deterministic_and_physical():
    a = make_force_curve(10e-9, 0.2, 50e-9, seed=7)
    b = make_force_curve(10e-9, 0.2, 50e-9, seed=7)
    assert np.array_equal(a.deflection_V, b.deflection_V)
    # soft lever: jump-off deflection equals F_p/k to better than 1e-4
    assert a.truth["delta_m"] == pytest.approx(10e-9 / 0.2, rel=1e-4)
    assert a.truth["z_snap"] > a.truth["z_pulloff"]  # hysteresis: snap-in closer to the sample
    assert 1000 <= a.height.size <= 4000
    with pytest.raises(ValueError, match="too stiff"):
        make_force_curve(1e-9, 50.0, 50e-9)


def test_csv_roundtrip_and_invols_from_contact_slope(tmp_path):
    invols = 47e-9
    curves = []
    for seed in range(3):
        c = make_force_curve(3e-9, 0.3, invols, seed=seed, noise=0.1e-9, tilt=2e5, offset_V=-0.1)
        curves.extend(read_curves(write_curve_csv(tmp_path / f"h{seed}.csv", c)))
    assert curves[0].z_approach[-1] > curves[0].z_approach[0]
    mean, u, vals, _, rejected = invols_from_curves(curves)
    assert rejected == []
    assert mean == pytest.approx(invols, rel=0.01)
    assert u < 0.01 * invols and vals.size == 3
    # soft sample: slope k_c/(k_c+k) -> apparent InvOLS larger by (k_c+k)/k_c
    c = make_force_curve(3e-9, 0.3, invols, contact_stiffness=3.0, seed=1)
    soft = read_curves(write_curve_csv(tmp_path / "soft.csv", c))
    assert invols_from_curves(soft)[0] == pytest.approx(invols * 3.3 / 3.0, rel=0.01)


def test_modified_z_outliers():
    x = np.array([10.0, 10.1, 9.9, 10.05, 9.95, 10.0, 14.0])
    st = interval_stats(x, np.ones(x.size, bool))
    assert st.outlier.tolist() == [False] * 6 + [True]
    assert st.mean == pytest.approx(np.mean(x[:6]))
    assert st.sem == pytest.approx(np.std(x[:6], ddof=1) / np.sqrt(6))
    assert np.all(modified_z_scores([1.0, 1.0, 1.0]) == 0)
    one = interval_stats([5.0, np.nan], np.array([True, False]))
    assert one.n_used == 1 and np.isnan(one.std)


def test_stage_end_to_end(tmp_path):
    k, invols = 0.2, 50e-9
    rng = np.random.default_rng(1)
    F = 12e-9 * (1 + 0.03 * rng.normal(size=8))
    F[3] = 25e-9  # outlier
    paths = [
        write_curve_csv(tmp_path / f"c{i}.csv", make_force_curve(f, k, invols, seed=i, tilt=1e5))
        for i, f in enumerate(F)
    ]
    out, png = tmp_path / "o.h5", tmp_path / "o.png"
    cant = {
        "spring_constant": k,
        "spring_constant_uncertainty": 0.01,
        "deflection_sensitivity": invols,
        "deflection_sensitivity_uncertainty": 1e-9,
        "deflection_sensitivity_method": "given",
        "base_dir": str(tmp_path),
    }
    run_forces(paths, out, png, cantilever=cant, reader={}, tip="T", interval="i0")
    assert png.stat().st_size > 10_000
    with h5py.File(out) as f:
        for g in ("curves", "interval", "calibration"):
            for name, ds in f[g].items():
                if isinstance(ds, h5py.Dataset):
                    assert "units" in ds.attrs, name
        Fp = f["curves/F_p"][()]
        np.testing.assert_allclose(Fp, F, rtol=0.01)
        assert f["curves/outlier"][()].tolist() == [i == 3 for i in range(8)]
        assert f["interval/n_curves_used"][()] == 7 and f["interval/n_curves_total"][()] == 8
        assert f["interval/F_p_mean"][()] == pytest.approx(np.delete(Fp, 3).mean())
        assert f["interval/calibration/k"][()] == k  # soft link to /calibration
        assert f["calibration/u_factor_rel"][()] == pytest.approx(np.hypot(0.05, 0.02), rel=1e-6)
        assert f["interval/u_F_p_calibration"][()] == pytest.approx(
            f["interval/F_p_mean"][()] * np.hypot(0.05, 0.02), rel=1e-6
        )
        np.testing.assert_allclose(f["curves/delta_m"][()], f["curves/delta_V"][()] * invols)
        assert f["curves/delta_V"].attrs["units"] == "V" and f["curves/F_p"].attrs["units"] == "N"


NIST_ESD_DATA = [
    -0.25,
    0.68,
    0.94,
    1.15,
    1.20,
    1.26,
    1.26,
    1.34,
    1.38,
    1.43,
    1.49,
    1.49,
    1.55,
    1.56,
    1.58,
    1.65,
    1.69,
    1.70,
    1.76,
    1.77,
    1.81,
    1.91,
    1.94,
    1.96,
    1.99,
    2.06,
    2.09,
    2.10,
    2.14,
    2.15,
    2.23,
    2.24,
    2.26,
    2.35,
    2.37,
    2.40,
    2.47,
    2.54,
    2.62,
    2.64,
    2.90,
    2.92,
    2.92,
    2.93,
    3.21,
    3.26,
    3.30,
    3.59,
    3.68,
    4.30,
    4.64,
    5.34,
    5.42,
    6.01,
]


def test_generalized_esd_nist_example():
    # NIST/SEMATECH e-Handbook 1.3.5.17.3 (Rosner's test, up to 10 outliers, alpha = 0.05): 3 outliers
    out = generalized_esd(NIST_ESD_DATA, alpha=0.05, max_outliers=10)
    assert sorted(np.asarray(NIST_ESD_DATA)[out]) == [5.34, 5.42, 6.01]


def test_esd_false_alarm_rate_small_intervals():
    # 8 curves with pure Gaussian scatter: ESD flags an interval with probability ~alpha,
    # the MAD rule far more often (the reason ESD is the default).
    rng = np.random.default_rng(3)
    draws = rng.normal(10.0, 0.3, size=(2000, 8))
    esd05 = np.mean([generalized_esd(d, 0.05).any() for d in draws])
    esd01 = np.mean([generalized_esd(d, 0.01).any() for d in draws])
    mad = np.mean([(np.abs(modified_z_scores(d)) > 3.5).any() for d in draws])
    assert 0.03 < esd05 < 0.10 and 0.005 < esd01 < 0.03
    assert mad > 2 * esd05


def test_outlier_rule_choice():
    x = np.array([10.0, 10.1, 9.9, 10.05, 9.95, 10.0, 14.0])
    for rule in ("esd", "modified_z"):
        assert interval_stats(x, np.ones(7, bool), rule=rule).outlier.tolist() == [False] * 6 + [True]
    with pytest.raises(ValueError, match="unknown outlier rule"):
        interval_stats(x, np.ones(7, bool), rule="grubbs")
