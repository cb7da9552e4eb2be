"""InvOLS per interval (the chip is remounted for every TEM session) and the check that catches a
forgotten remount; bad contact parts; the per-interval Monte Carlo draw."""

from __future__ import annotations

import json
import logging
import re

import h5py
import numpy as np
import pytest

from pipeline.forces.errors import CalibrationError, ForcesStageError
from pipeline.forces.stage import run_forces
from pipeline.synth.force_curves import make_force_curve, write_curve_csv

K = 0.8
INVOLS0 = 55e-9


def _curves(tmp, name, F, invols, n=8, scatter=0.03, seed=0, distort=None, **kw):
    """``n`` curves of true pull-off F (1 + scatter N(0,1)) at InvOLS ``invols`` in tmp/name."""
    rng = np.random.default_rng(seed)
    Fs = F * (1.0 + scatter * rng.standard_normal(n))
    paths = []
    for j, f in enumerate(Fs):
        c = make_force_curve(
            float(f),
            K,
            invols,
            seed=1000 * seed + j,
            offset_V=float(rng.normal(0, 0.05)),
            tilt=float(rng.normal(0, 2e5)),
            **kw,
        )
        if distort is not None:
            distort(c)
        paths.append(write_curve_csv(tmp / name / f"c{j}.csv", c))
    return paths, Fs


def _run(tmp, name, paths, cant=None, interval_cfg=None, reader=None):
    out = tmp / f"{name}.h5"
    cant = {"spring_constant": K, "spring_constant_uncertainty": 0.04, "base_dir": str(tmp), **(cant or {})}
    run_forces(
        paths,
        out,
        tmp / f"{name}.png",
        cantilever=cant,
        reader=reader or {},
        tip="T",
        interval=name,
        interval_cfg=interval_cfg or {},
    )
    return out


def test_drifting_invols_is_measured_for_every_interval(tmp_path):
    """InvOLS drifting 3-10 % between intervals, a YAML that gives k only: each interval's InvOLS
    from its own contact slopes within 0.5 % and its mean F_p within 1 % of its curves' truth.
    With one InvOLS for the tip (the old way) the same intervals are off by the drift."""
    drift = [1.0, 1.06, 0.93, 1.10, 0.97]
    for i, d in enumerate(drift):
        paths, Fs = _curves(tmp_path, f"i{i}", 8e-9 * (1 + 0.5 * i), INVOLS0 * d, seed=i)
        with h5py.File(_run(tmp_path, f"i{i}", paths)) as f:
            c = f["calibration"]
            assert c["invols_method"][()].decode() == "contact" and not c["invols_shared"][()]
            assert c["invols"][()] == pytest.approx(INVOLS0 * d, rel=0.005)
            assert 0.004 < c["u_invols_rel"][()] < 0.01  # SEM of 8 slopes with the 0.5 % floor
            assert f["interval/F_p_mean"][()] == pytest.approx(Fs.mean(), rel=0.01)
            assert c["u_factor_rel"][()] == pytest.approx(np.hypot(0.05, c["u_invols_rel"][()]), rel=1e-9)
        with h5py.File(
            _run(
                tmp_path,
                f"i{i}_tip",
                paths,
                {"deflection_sensitivity": INVOLS0, "deflection_sensitivity_method": "given"},
            )
        ) as f:
            assert f["interval/F_p_mean"][()] / Fs.mean() - 1.0 == pytest.approx(1.0 / d - 1.0, abs=0.01)


def test_forgotten_remount_is_reported_in_words(tmp_path, caplog):
    """One InvOLS for the tip (55 nm/V) while this interval's mounting has 60 nm/V: the contact
    slope is measured anyway and the disagreement (-8.4 %) is in the HDF5, the warnings and the log."""
    paths, _ = _curves(tmp_path, "i3", 10e-9, 60e-9, seed=3)
    with caplog.at_level(logging.WARNING):
        out = _run(
            tmp_path,
            "i3",
            paths,
            {
                "deflection_sensitivity": INVOLS0,
                "deflection_sensitivity_uncertainty": 0.5e-9,
                "deflection_sensitivity_method": "given",
            },
        )
    with h5py.File(out) as f:
        check = f["calibration/invols_check"][()].decode()
        assert re.search(r"by -8\.[34] %", check) and "remounted" in check
        assert f["calibration/invols_contact"][()] == pytest.approx(60e-9, rel=0.005)
        assert f["calibration/invols_check_z"][()] < -3
        assert any("interval 'i3'" in w and re.search(r"-8\.[34] %", w) for w in json.loads(f.attrs["warnings"]))
    assert any("interval 'i3'" in r.getMessage() and re.search(r"-8\.[34] %", r.getMessage()) for r in caplog.records)
    # the right value is not flagged
    out = _run(
        tmp_path,
        "i3ok",
        paths,
        {
            "deflection_sensitivity": 60e-9,
            "deflection_sensitivity_uncertainty": 0.5e-9,
            "deflection_sensitivity_method": "given",
        },
    )
    with h5py.File(out) as f:
        assert f["calibration/invols_check"][()].decode() == ""


def test_interval_values_and_calibration_curves_take_precedence(tmp_path):
    paths, _ = _curves(tmp_path, "i1", 10e-9, 62e-9, seed=1)
    cfg = {"deflection_sensitivity": 62.5e-9, "deflection_sensitivity_uncertainty": 0.6e-9}
    with h5py.File(_run(tmp_path, "i1", paths, interval_cfg=cfg)) as f:
        assert f["calibration/invols_method"][()].decode() == "interval_given"
        assert f["calibration/invols"][()] == 62.5e-9 and f["calibration/u_invols"][()] == 0.6e-9
        assert f["calibration/invols_check"][()].decode() == ""  # 0.8 % off, within its uncertainty
    # a folder of this interval's hard-sample curves
    _curves(tmp_path, "cal1", 2e-9, 62e-9, n=4, seed=9, setpoint_deflection=40e-9)
    with h5py.File(_run(tmp_path, "i1c", paths, interval_cfg={"calibration_curves": "cal1"})) as f:
        assert f["calibration/invols_method"][()].decode() == "interval_curves"
        assert f["calibration/invols"][()] == pytest.approx(62e-9, rel=0.005)


def _hertzian(c):
    """Make the contact part of the approach non-linear (a soft sample: slope doubling)."""
    app = c.segment == "approach"
    v = c.deflection_V[app]
    base = np.median(v[: v.size // 4])
    up = v - base
    top = up.max()
    c.deflection_V[app] = np.where(up > 0, base + up * (0.5 + 0.5 * up / top), v)


def _short_contact(c):
    """Approach stopped right after contact: no usable contact part."""
    app = np.flatnonzero(c.segment == "approach")
    v = c.deflection_V[app]
    base = np.median(v[: v.size // 4])
    hi = np.flatnonzero(v - base > 0.05 * (v.max() - base))
    if hi.size:
        c.deflection_V[app[hi]] = base + 0.05 * (v.max() - base)


@pytest.mark.parametrize("distort,reason", [(_hertzian, "not linear"), (_short_contact, "no repulsive contact")])
def test_curves_that_cannot_give_invols_fail_naming_interval_and_setting(tmp_path, distort, reason):
    paths, _ = _curves(tmp_path, "i2", 10e-9, 58e-9, n=4, seed=2, distort=distort)
    with pytest.raises(
        CalibrationError, match=rf"tip 'T' interval 'i2': no curve gives an InvOLS .*{reason}.*contact_fallback"
    ):
        _run(tmp_path, "i2", paths)
    assert not (tmp_path / "i2.h5").exists()
    # the configured fallback: the tip-level value, with a warning that says so
    out = _run(tmp_path, "i2", paths, {"deflection_sensitivity": 58e-9, "contact_fallback": "tip"})
    with h5py.File(out) as f:
        assert f["calibration/invols"][()] == 58e-9 and f["calibration/invols_shared"][()]
        assert "contact_fallback: tip" in f.attrs["warnings"]


def test_contact_slope_that_changes_sign_gives_no_invols(tmp_path):
    def flip(c):  # deflection falls in contact (a detector saturating / laser off the diode)
        app = c.segment == "approach"
        v = c.deflection_V[app]
        base = np.median(v[: v.size // 4])
        c.deflection_V[app] = np.where(v - base > 0, base - (v - base), v)

    paths, _ = _curves(tmp_path, "i4", 10e-9, 58e-9, n=3, seed=4, distort=flip)
    with pytest.raises(CalibrationError, match="interval 'i4'.*(no repulsive contact|not positive)"):
        _run(tmp_path, "i4", paths)


def test_single_curve_interval_needs_the_setting(tmp_path):
    paths, Fs = _curves(tmp_path, "i5", 10e-9, 58e-9, n=1, seed=5)
    with pytest.raises(
        ForcesStageError,
        match=r"interval 'i5': only 1 usable force curve\(s\) \(.*c0.csv\).*force_curves.min_curves: 1",
    ):
        _run(tmp_path, "i5", paths)
    assert not (tmp_path / "i5.h5").exists()
    with h5py.File(_run(tmp_path, "i5", paths, reader={"min_curves": 1})) as f:
        assert f["interval/F_p_mean"][()] == pytest.approx(Fs[0], rel=0.01)
        assert f["calibration/invols"][()] == pytest.approx(58e-9, rel=0.01)


def test_monte_carlo_draws_invols_per_interval_and_k_once(tmp_path):
    """Two intervals with their own InvOLS (u 5 %) and k (u 5 %): the calibration factors of the
    two intervals correlate through k only (rho = 0.05^2 / (0.05^2 + 0.05^2) = 0.5); a tip-level
    InvOLS is one draw for both (rho = 1)."""
    from pipeline.inversion.io import load_inversion
    from pipeline.inversion.stage import run_inversion
    from pipeline.synth.stage_inputs import write_synthetic_inputs

    ivs = [{"name": "a", "n": 2.0, "R": 20e-9, "reference": True}, {"name": "b", "n": 4.0, "R": 20e-9}]
    for shared, rho in ((False, 0.5), (True, 1.0)):
        fits, forces, cfg = write_synthetic_inputs(
            tmp_path / str(shared),
            W_A=0.05,
            h=3e-9,
            E_star=100e9,
            intervals=ivs,
            k=1.0,
            u_k=0.05,
            invols=50e-9,
            u_invols=2.5e-9,
            seed=3,
        )
        if not shared:
            for p in forces.values():
                with h5py.File(p, "a") as f:
                    f["calibration"].create_dataset("invols_shared", data=False)
        out = tmp_path / f"inv{shared}.h5"
        run_inversion(
            fits,
            forces,
            out,
            intervals=cfg,
            E_star=100e9,
            u_E_star=0.0,
            h_grid=np.geomspace(1e-9, 8e-9, 20),
            laws=("dugdale",),
            mc_samples=4000,
            seed=1,
            tip="t",
        )
        inv = load_inversion(out)
        fa, fb = (inv["intervals"][n]["draws"]["cal_factor"] for n in ("a", "b"))
        assert np.std(fa) == pytest.approx(0.05 * (np.sqrt(2) if not shared else np.sqrt(2)), rel=0.1)
        assert np.corrcoef(fa, fb)[0, 1] == pytest.approx(rho, abs=0.05)
