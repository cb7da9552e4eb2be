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
    run_forces(
        [SIN],
        out,
        tmp_path / "sin.png",
        cantilever={"spring_constant": 2.0, "deflection_sensitivity": 50e-9, "deflection_sensitivity_method": "given"},
        reader=ONE,
        tip="SiN",
        interval="0",
    )
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
        run_forces(
            [JPK_NOCAL],
            tmp_path / "n.h5",
            tmp_path / "n.png",
            cantilever={
                "spring_constant": 0.1,
                "deflection_sensitivity": 50e-9,
                "deflection_sensitivity_method": "given",
            },
            reader=ONE,
        )
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


AFMW = sorted(DATA.glob("fmt-afm-workshop-fd_single_*.csv"))
AFMW_FORCE = DATA / "fmt-afm-workshop-fd_single_2021-10-22_14.16.csv"  # force in nN, no calibration stored


def test_afm_workshop_csv_read_through_afmformats_without_a_traceback(tmp_path):
    """AFM Workshop exports (.csv, but not our CSV layout) go to afmformats; the one storing the
    instrument's force (nN) without its calibration is converted back with the YAML's k and InvOLS
    (the values set in the instrument), or refused naming them -- never a traceback."""
    assert len(AFMW) == 4
    with pytest.raises(ForceCurveError, match="cantilever.spring_constant and cantilever.deflection_sensitivity"):
        read_curves(AFMW_FORCE)
    (c,) = read_curves(AFMW_FORCE, {"instrument_spring_constant": 0.2, "instrument_deflection_sensitivity": 50e-9})
    assert c.defl_units == "V" and c.spring_constant is None
    cant = {"spring_constant": 0.2, "deflection_sensitivity": 50e-9, "deflection_sensitivity_method": "given"}
    run_forces([AFMW_FORCE], tmp_path / "w.h5", tmp_path / "w.png", cantilever=cant, reader=ONE)
    with h5py.File(tmp_path / "w.h5") as f:
        F = f["interval/F_p_mean"][()]
    # the file's own force column: its adhesive dip below the free retract, read the same way in N
    import numpy as np
    import pandas as pd

    df = pd.read_csv(AFMW_FORCE, skiprows=10)
    fr = df["Retract Force(nN)"].to_numpy()
    assert F == pytest.approx((np.median(fr[-100:]) - fr.min()) * 1e-9, rel=0.1)
    for p in AFMW:  # all read, one line of error at most
        try:
            read_curves(p, {"instrument_spring_constant": 0.2, "instrument_deflection_sensitivity": 50e-9})
        except ForceCurveError as exc:
            raise AssertionError(f"{p.name}: {exc}") from None


def _jpk_without_spring_constant(tmp_path):
    """The JPK curve with its force calibration (the spring constant) removed from the headers."""
    import zipfile

    out = tmp_path / "no_k.jpk-force"
    with zipfile.ZipFile(JPK) as zi, zipfile.ZipFile(out, "w", zipfile.ZIP_DEFLATED) as zo:
        for it in zi.infolist():
            data = zi.read(it.filename)
            if it.filename.endswith(".properties"):
                lines = [
                    ln
                    for ln in data.decode("latin-1").split("\n")
                    if "conversion.force.scaling.multiplier" not in ln and "conversion.force.defined" not in ln
                ]
                data = "\n".join(lines).encode("latin-1")
            zo.writestr(it, data)
    return out


def test_jpk_with_invols_but_no_spring_constant(tmp_path):
    """The file's InvOLS is kept and used; only k is asked for."""
    path = _jpk_without_spring_constant(tmp_path)
    (c,) = read_curves(path)
    assert c.spring_constant is None and c.invols == pytest.approx(70.0e-9, rel=1e-4)
    with pytest.raises(CalibrationError, match="spring constant") as exc:
        run_forces([path], tmp_path / "j.h5", tmp_path / "j.png", cantilever={}, reader=ONE)
    assert "InvOLS" not in str(exc.value).split("spring constant")[0]
    run_forces([path], tmp_path / "j.h5", tmp_path / "j.png", cantilever={"spring_constant": 0.043494}, reader=ONE)
    with h5py.File(tmp_path / "j.h5") as f:
        assert f["calibration/invols_method"][()].decode() == "interval_file"
        assert f["interval/F_p_mean"][()] == pytest.approx(0.395e-9, rel=0.05)  # as with the complete file


def test_whitespace_dat_curves_are_read(tmp_path):
    """A .dat file with white-space columns (the README says .dat is read as CSV)."""
    import numpy as np

    from pipeline.forces.pulloff import detect_pulloff
    from pipeline.synth.force_curves import make_force_curve

    c = make_force_curve(5e-9, 0.5, 50e-9, seed=1)
    p = tmp_path / "c.dat"
    with open(p, "w") as fh:
        fh.write("height_nm deflection_V segment\n")
        for h, v, s in zip(c.height * 1e9, c.deflection_V, c.segment):
            fh.write(f"{h:.6f} {v:.7e} {s}\n")
    (cu,) = read_curves(p)
    po = detect_pulloff(cu.z_retract, cu.deflection_volts())
    assert po.delta * 50e-9 * 0.5 == pytest.approx(5e-9, rel=0.02)
    assert np.all(np.diff(cu.z_approach) > 0)
