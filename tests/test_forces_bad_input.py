"""Bad input: clear errors naming the file, per-curve rejections, all-rejected failure."""

import h5py
import numpy as np
import pandas as pd
import pytest

from pipeline.forces.errors import ForceCurveError, ForcesStageError
from pipeline.forces.reading import read_curves
from pipeline.forces.stage import run_forces
from pipeline.synth.force_curves import make_force_curve, write_curve_csv

CANT = {"spring_constant": 0.2, "deflection_sensitivity": 50e-9}


def _df(seed=0, F_p=10e-9):
    c = make_force_curve(F_p, 0.2, 50e-9, seed=seed)
    return pd.DataFrame({"height_nm": c.height * 1e9, "deflection_V": c.deflection_V, "segment": c.segment})


def _write(df, path):
    df.to_csv(path, index=False)
    return path


def test_no_retract_segment(tmp_path):
    df = _df()
    p = _write(df[df.segment == "approach"], tmp_path / "appr.csv")
    with pytest.raises(ForceCurveError, match="appr.csv.*no retract segment"):
        read_curves(p)
    p2 = _write(df[df.segment == "approach"].drop(columns="segment"), tmp_path / "noseg.csv")
    with pytest.raises(ForceCurveError, match="noseg.csv.*no retract segment"):
        read_curves(p2)


def test_split_without_segment_column(tmp_path):
    p = _write(_df().drop(columns="segment"), tmp_path / "s.csv")
    (c,) = read_curves(p)
    assert c.z_approach.size == 1000 and c.z_retract.size == 1001


def test_nan_and_missing_columns_and_other_format(tmp_path):
    df = _df()
    df.loc[1500, "deflection_V"] = np.nan
    with pytest.raises(ForceCurveError, match="nan.csv.*NaN.*retract"):
        read_curves(_write(df, tmp_path / "nan.csv"))
    with pytest.raises(ForceCurveError, match="cols.csv.*missing column.*deflection_V"):
        read_curves(_write(_df().rename(columns={"deflection_V": "defl"}), tmp_path / "cols.csv"))
    png = tmp_path / "img.csv"
    png.write_bytes(b"\x89PNG\r\n\x1a\n\x00\x00\x00\rIHDR\xff\xfe")
    with pytest.raises(ForceCurveError, match="img.csv.*not a text CSV"):
        read_curves(png)
    with pytest.raises(ForceCurveError, match="absent.csv.*not found"):
        read_curves(tmp_path / "absent.csv")


def test_no_pulloff_event_rejected_and_recorded(tmp_path):
    good = [write_curve_csv(tmp_path / f"g{i}.csv", make_force_curve(10e-9, 0.2, 50e-9, seed=i)) for i in range(3)]
    flat = _df()
    m = flat.segment == "retract"
    flat.loc[m, "deflection_V"] = np.random.default_rng(0).normal(0, 0.002, m.sum())  # no adhesion at all
    nan = _df()
    nan.loc[1800, "deflection_V"] = np.nan
    bad = [_write(flat, tmp_path / "flat.csv"), _write(nan, tmp_path / "nan.csv")]
    (tmp_path / "junk.csv").write_text("foo;bar\n1;2\n")
    out = tmp_path / "o.h5"
    run_forces(good + bad + [tmp_path / "junk.csv"], out, tmp_path / "o.png", cantilever=CANT, reader={})
    with h5py.File(out) as f:
        acc = f["curves/accepted"][()]
        why = [s.decode() for s in f["curves/rejection_reason"][()]]
        assert acc.tolist() == [True] * 3 + [False] * 3
        assert "no pull-off event" in why[3] and "NaN" in why[4] and "missing column" in why[5]
        assert np.isnan(f["curves/F_p"][3:]).all()  # never a silent zero
        assert f["interval/n_curves_used"][()] == 3 and f["interval/n_curves_rejected"][()] == 3


def test_all_rejected_fails_without_output(tmp_path):
    df = _df()
    paths = [_write(df[df.segment == "approach"], tmp_path / "a.csv")]
    (tmp_path / "b.csv").write_text("x,y\n1,2\n")
    paths.append(tmp_path / "b.csv")
    out = tmp_path / "o.h5"
    with pytest.raises(ForcesStageError) as ei:
        run_forces(paths, out, tmp_path / "o.png", cantilever=CANT, reader={}, tip="T", interval="i3")
    msg = str(ei.value)
    assert (
        "all 2 force curves were rejected" in msg
        and "a.csv: no retract segment" in msg
        and "b.csv: missing column" in msg
    )
    assert not out.exists() and not (tmp_path / "o.png").exists()
    assert not list(tmp_path.glob(".*part"))


def test_custom_columns_and_units(tmp_path):
    c = make_force_curve(10e-9, 0.2, 50e-9, seed=3)
    df = pd.DataFrame({"Z (um)": -(c.height - 1e-6) * 1e6, "Defl (nm)": c.deflection_V * 50.0, "dir": c.segment})
    p = tmp_path / "c.tsv"
    df.to_csv(p, sep="\t", index=False)
    reader = {
        "columns": {"height": "Z (um)", "deflection": "Defl (nm)", "segment": "dir"},
        "height_unit": "um",
        "deflection_unit": "nm",
        "height_axis": "extension",
        "min_curves": 1,
    }
    (cv,) = read_curves(p, reader)
    assert cv.defl_units == "m"
    out = tmp_path / "o.h5"
    run_forces([p], out, tmp_path / "o.png", cantilever={"spring_constant": 0.2}, reader=reader)
    with h5py.File(out) as f:
        assert f["interval/F_p_mean"][()] == pytest.approx(10e-9, rel=0.01)
        assert np.isnan(f["curves/delta_V"][0])


def test_deflection_in_nm_read_as_volts_is_refused(tmp_path):
    """A CSV whose deflection column is in nm while the YAML says V (F_p came out 60 x too large
    before): values beyond any photodetector's range are refused naming the setting; and an
    interval whose mean F_p is far off the others' is said to be so in words."""
    import numpy as np

    from pipeline.forces.reading import read_curves
    from pipeline.inversion.calibration import implausible_forces
    from pipeline.synth.force_curves import make_force_curve, write_curve_csv

    c = make_force_curve(5e-9, 0.2, 50e-9, seed=2)
    c.deflection_V = c.deflection_V * 50.0  # nm written where volts are expected
    p = write_curve_csv(tmp_path / "nm.csv", c)
    with pytest.raises(
        ForceCurveError, match=r"reaches .* V, beyond any photodetector's range.*force_curves.deflection_unit"
    ):
        read_curves(p)
    (cu,) = read_curves(p, {"deflection_unit": "nm"})
    assert cu.defl_units == "m" and np.abs(cu.defl_retract).max() < 1e-6
    notes = implausible_forces({"a": 5e-9, "b": 6e-9, "c": 298.7e-9, "d": 7e-9})
    assert len(notes) == 1 and notes[0].startswith("interval c:") and "deflection unit" in notes[0]
