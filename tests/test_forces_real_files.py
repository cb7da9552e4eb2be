"""Real instrument files (afmformats test data, MIT; see tests/data/afmformats/README.md)."""
from pathlib import Path

import h5py
import pytest

from pipeline.forces.errors import CalibrationError, ForceCurveError, ForcesStageError
from pipeline.forces.reading import read_curves
from pipeline.forces.stage import run_forces

DATA = Path(__file__).parent / "data" / "afmformats"
SIN = DATA / "fmt-igor-fd_SiN_FD_plot.ibw"
JPK = DATA / "fmt-jpk-fd_spot3-0192.jpk-force"
JPK_NOCAL = DATA / "fmt-jpk-cl_calibration_force-save-2015.02.04-11.25.21.294.jpk-force"
ONE = {"min_curves": 1}  # these instrument files hold one curve each


def test_asylum_ibw_split_and_metadata():
    (c,) = read_curves(SIN)
    assert c.spring_constant == 1.1841 and c.invols == pytest.approx(44.99e-9)
    # split from the wave note (Indexes 0,1008,2015), not afmformats' single segment
    assert c.z_approach.size == 1009 and c.z_retract.size == 1008
    assert c.z_approach[-1] > c.z_approach[0] and c.z_retract[-1] < c.z_retract[0]


def test_asylum_ibw_pulloff_end_to_end(tmp_path):
    out = tmp_path / "sin.h5"
    run_forces([SIN], out, tmp_path / "sin.png", cantilever={}, reader=ONE, tip="SiN", interval="0")
    with h5py.File(out) as f:
        assert f["calibration/k"][()] == 1.1841
        assert f["calibration/invols"][()] == pytest.approx(44.99e-9)
        # the file's InvOLS is used (the instrument's calibration at that mounting), and the
        # curve's own contact slope, 98 nm/V on this compliant sample, is reported against it
        assert f["calibration/invols_method"][()].decode() == "interval_file"
        assert f["calibration/invols_contact"][()] == pytest.approx(98.1e-9, rel=0.01)
        assert "counter-surface is not hard" in f["calibration/invols_check"][()].decode()
        assert f["calibration/k_method"][()].decode() == "file"
        # measured: Delta = 0.2398 V = 10.79 nm, F_p = 12.77 nN (retract minimum 10.78 nm)
        assert f["curves/delta_V"][0] == pytest.approx(0.2398, abs=0.002)
        assert f["curves/delta_m"][0] == pytest.approx(10.79e-9, rel=0.01)
        assert f["interval/F_p_mean"][()] == pytest.approx(12.77e-9, rel=0.01)
        assert f["interval/n_curves_used"][()] == 1
    # the YAML overrides the file: F_p scales with k * InvOLS
    run_forces([SIN], out, tmp_path / "sin.png", cantilever={"spring_constant": 2.0, "deflection_sensitivity": 50e-9,
                                                             "deflection_sensitivity_method": "given"},
               reader=ONE, tip="SiN", interval="0")
    with h5py.File(out) as f:
        assert f["interval/F_p_mean"][()] == pytest.approx(12.77e-9 * 2.0 * 50 / (1.1841 * 44.99), rel=0.01)
        assert f["curves/spring_constant_file"][0] == 1.1841


def test_jpk_metadata_and_pulloff(tmp_path):
    (c,) = read_curves(JPK)
    assert c.spring_constant == pytest.approx(0.043494, rel=1e-4)
    assert c.invols == pytest.approx(70.0e-9, rel=1e-4)
    assert c.z_approach.size == c.z_retract.size == 2000
    run_forces([JPK], tmp_path / "j.h5", tmp_path / "j.png", cantilever={}, reader=ONE)
    with h5py.File(tmp_path / "j.h5") as f:
        # measured: Delta = 0.130 V = 9.08 nm, F_p = 0.395 nN (gradual, irregular detachment on a cell:
        # read as the running-mean minimum, the hinge does not describe it)
        assert f["interval/F_p_mean"][()] == pytest.approx(0.395e-9, rel=0.05)


def test_jpk_without_calibration_metadata(tmp_path):
    (c,) = read_curves(JPK_NOCAL)
    assert c.spring_constant is None and c.invols is None and c.defl_units == "V"
    with pytest.raises(CalibrationError, match="no spring constant"):
        run_forces([JPK_NOCAL], tmp_path / "n.h5", tmp_path / "n.png", cantilever={}, reader=ONE)
    # no InvOLS in the file, and its contact part (7 points in the fit range) gives none either
    with pytest.raises(CalibrationError, match=r"no curve gives an InvOLS .*contact part too short"):
        run_forces([JPK_NOCAL], tmp_path / "n.h5", tmp_path / "n.png", cantilever={"spring_constant": 0.1}, reader=ONE)
    assert not (tmp_path / "n.h5").exists()
    # calibrated by hand, the curve still has no adhesive dip: its retract returns to the baseline
    # beyond the noise (the deepest point of the fitted bottom is 0.0115 V, below 5 x the 0.0023 V noise;
    # the raw minimum, 0.02 V, is the noise's own extreme): rejected, naming the setting
    with pytest.raises(ForcesStageError, match=r"no pull-off event.*force_curves.min_pulloff_snr"):
        run_forces([JPK_NOCAL], tmp_path / "n.h5", tmp_path / "n.png",
                   cantilever={"spring_constant": 0.1, "deflection_sensitivity": 50e-9, "deflection_sensitivity_method": "given"},
                   reader=ONE)
    assert not (tmp_path / "n.h5").exists()


def test_broken_instrument_file_named(tmp_path):
    bad = tmp_path / "broken.jpk-force"
    bad.write_bytes(b"PK\x03\x04 not really a zip")
    with pytest.raises(ForceCurveError, match="broken.jpk-force.*afmformats"):
        read_curves(bad)
    other = tmp_path / "image.tif"
    other.write_bytes(b"II*\x00")
    with pytest.raises(ForceCurveError, match="image.tif.*not an afmformats format"):
        read_curves(other)
