"""Reference-lever and thermal spring constants, calibration precedence and propagation."""

import numpy as np
import pytest

from pipeline.forces.calibration import calibrate
from pipeline.forces.curve import ForceCurve
from pipeline.forces.errors import CalibrationError
from pipeline.forces.invols import resolve_interval_invols
from pipeline.forces.reference_lever import reference_lever_k
from pipeline.forces.settings import CANTILEVER_DEFAULTS, with_defaults
from pipeline.forces.thermal import K_B, fit_sho, psd_from_series, thermal_k
from pipeline.synth.force_curves import make_force_curve, thermal_noise_series, write_curve_csv, write_thermal_csv


def _curve(k=None, invols=None):
    z = np.linspace(0, 1e-7, 20)
    return ForceCurve("f.csv", z, z * 0, z[::-1], z * 0, spring_constant=k, invols=invols)


def test_reference_lever_hand_computed():
    # S in V/nm: S_hard = 1/40, S_ref = 1/100 -> k = 0.5 (2.5 - 1) = 0.75 N/m
    assert reference_lever_k(0.5, 40e-9, 100e-9) == pytest.approx(0.75)
    # off-end: 200 um lever loaded 10 um from its end: k_ref * (200/190)^3
    assert reference_lever_k(0.5, 40e-9, 100e-9, length=200e-6, offset=10e-6) == pytest.approx(0.75 * (200 / 190) ** 3)
    t = np.deg2rad(12)
    assert reference_lever_k(0.5, 40e-9, 100e-9, tilt=t) == pytest.approx(0.75 * np.cos(t))
    assert reference_lever_k(0.5, 40e-9, 100e-9, tilt=t, tilt_correction="cos2") == pytest.approx(0.75 * np.cos(t) ** 2)
    with pytest.raises(ValueError):
        reference_lever_k(0.5, 100e-9, 40e-9)


def test_reference_lever_calibration_with_hard_sample_curves(tmp_path):
    invols = 45e-9
    for i in range(3):
        write_curve_csv(tmp_path / "hard" / f"h{i}.csv", make_force_curve(2e-9, 0.3, invols, seed=i))
    cant = {
        "base_dir": str(tmp_path),
        "hard_sample_curves": "hard",
        "reference_lever": {
            "spring_constant": 0.5,
            "spring_constant_uncertainty": 0.025,
            "deflection_sensitivity": 90e-9,
            "deflection_sensitivity_uncertainty": 0.9e-9,
        },
    }
    cal = calibrate(cant, [_curve(9.9, 9.9)])
    assert cal.invols_method == "hard_sample" and cal.k_method == "reference_lever"
    assert cal.invols == pytest.approx(invols, rel=0.01)
    assert cal.k == pytest.approx(0.5 * (90 / (cal.invols * 1e9) - 1), rel=1e-9)
    # F_p/Delta_V = k*InvOLS = k_ref (InvOLS_ref - InvOLS_hard): the InvOLS_hard error partly cancels
    assert cal.factor == pytest.approx(0.5 * (90e-9 - cal.invols), rel=1e-9)
    r = 90e-9 / cal.invols
    u_rel_k = np.sqrt(0.05**2 + (r / (r - 1)) ** 2 * ((0.01) ** 2 + (cal.u_invols / cal.invols) ** 2))
    assert cal.u_k / cal.k == pytest.approx(u_rel_k, rel=1e-3)
    assert cal.corr_k_invols < 0
    assert "Tortonese" in cal.k_source and "hard_sample" in cal.details


@pytest.mark.parametrize("Q", [3.0, 150.0])
def test_thermal_recovers_k(tmp_path, Q):
    k, T, invols = 0.2, 300.0, 50e-9
    t, v = thermal_noise_series(k, 70e3, Q, temperature=T, invols=invols, n=2**19, seed=2, white=2e-28)
    f, P, n_avg = psd_from_series(t, v)
    fit = fit_sho(f, P, n_avg=n_avg)
    assert fit.f0 == pytest.approx(70e3, rel=0.01)
    assert thermal_k(fit.msq * invols**2, T) == pytest.approx(k, rel=0.03)
    assert thermal_k(1.0, 1.0, "v-shaped") == pytest.approx(0.764 * K_B)
    # through the calibration, file in volts, InvOLS given
    write_thermal_csv(tmp_path / "th.csv", t, v)
    cal = calibrate(
        {
            "base_dir": str(tmp_path),
            "deflection_sensitivity": invols,
            "thermal": {"file": "th.csv", "temperature": T, "temperature_uncertainty": 1.0},
        },
        [_curve()],
    )
    assert cal.k_method == "thermal" and cal.k == pytest.approx(k, rel=0.03)
    assert 0 < cal.u_k / cal.k < 0.05
    assert cal.details["thermal"]["Q"][0] == pytest.approx(Q, rel=0.15)


def test_precedence_yaml_over_file_and_errors():
    cal = calibrate({}, [_curve(0.3, 40e-9), _curve(0.3, 40e-9)])
    assert (cal.k, cal.invols, cal.k_method, cal.invols_method) == (0.3, 40e-9, "file", "file")
    cal = calibrate({"spring_constant": 0.25, "deflection_sensitivity": 42e-9}, [_curve(0.3, 40e-9)])
    assert (cal.k, cal.invols, cal.k_method) == (0.25, 42e-9, "given")
    with pytest.raises(CalibrationError, match="different spring constant"):
        calibrate({}, [_curve(0.3, 40e-9), _curve(0.31, 40e-9)])
    # one InvOLS for the whole tip asked for, none to be had: the tip-level calibration says so
    with pytest.raises(CalibrationError, match="InvOLS"):
        calibrate({"spring_constant": 0.2, "deflection_sensitivity_method": "file"}, [_curve()])
    # per interval (auto): the tip level has none, and the interval's flat curves give no contact
    # slope either: the interval fails naming itself and the settings
    cal = calibrate({"spring_constant": 0.2}, [_curve()])
    assert np.isnan(cal.invols)
    with pytest.raises(CalibrationError, match=r"tip 'x' interval 'y': no curve gives an InvOLS.*contact_fallback"):
        resolve_interval_invols(
            with_defaults({"spring_constant": 0.2}, CANTILEVER_DEFAULTS),
            {},
            [_curve()],
            cal,
            reader={},
            label="tip 'x' interval 'y'",
        )
    with pytest.raises(CalibrationError, match="spring constant"):
        calibrate({"deflection_sensitivity": 40e-9}, [_curve()])


def test_one_spiked_hard_sample_curve_is_left_out_not_fatal(tmp_path):
    """Four hard-sample calibration curves, one with a burst of spikes in its contact part (the
    photodiode saturating for a few samples): it is left out with its reason, the tip-level
    InvOLS comes from the other three, and every forces job still runs."""
    import numpy as np

    from pipeline.forces.calibration import calibrate
    from pipeline.synth.force_curves import make_force_curve, write_curve_csv

    invols = 52e-9
    cal_dir = tmp_path / "hard"
    for j in range(4):
        c = make_force_curve(3e-9, 0.3, invols, seed=40 + j, noise=0.05e-9)
        if j == 2:
            app = np.flatnonzero(c.segment == "approach")
            contact = app[-120:-60]
            c.deflection_V[contact[::6]] += 3.0  # ten spikes of 3 V across the contact part
        write_curve_csv(cal_dir / f"h{j}.csv", c)
    cal = calibrate(
        {
            "spring_constant": 0.3,
            "hard_sample_curves": "hard",
            "deflection_sensitivity_method": "hard_sample",
            "base_dir": str(tmp_path),
        },
        [],
        {},
    )
    assert cal.invols == pytest.approx(invols, rel=0.01)
    assert "1 curve(s) left out" in cal.invols_source and "h2.csv" in cal.invols_source
    assert len(cal.details["hard_sample"]["invols"][0]) == 3
