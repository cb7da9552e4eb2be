"""Plain CSV/TSV force curves.

Default layout (``force_curves.columns``): ``height_nm, deflection_V, segment``;
``height`` is the piezo height (grows away from the sample, as in afmformats;
``height_axis: extension`` for the opposite sign), ``segment`` labels rows
``approach``/``retract`` (also ``extend``, ``app``, ``ret``, ``0``, ``1``; other labels
such as ``pause`` are ignored).  Without a segment column the ramp is split where the
piezo reverses.  Lines starting with ``#`` are comments; the delimiter (comma, tab,
semicolon, or white space as in many .dat files) is taken from the header line.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pandas as pd

from pipeline.forces.curve import ForceCurve, check_segments, split_at_turnaround
from pipeline.forces.errors import ForceCurveError
from pipeline.units import QuantityError, parse_quantity

MAX_DETECTOR_VOLTS = 20.0  # photodetector sum/difference signals stay within +-10-12 V
APPROACH_LABELS = {"approach", "extend", "app", "0"}
RETRACT_LABELS = {"retract", "ret", "1"}


def unit_factor(unit: str, kinds: tuple[str, ...], where: str) -> tuple[float, str]:
    """SI factor of ``unit`` and the first matching kind of ``kinds``."""
    for kind in kinds:
        try:
            return parse_quantity(f"1 {unit}", kind), kind
        except QuantityError:
            continue
    raise QuantityError(f"{where}: unit {unit!r} is not one of {', '.join(kinds)}")


def _header(path: Path) -> str:
    with open(path, encoding="utf-8", errors="strict") as fh:
        for line in fh:
            if line.strip() and not line.lstrip().startswith("#"):
                return line
    raise ForceCurveError(path, "empty file (no header line)")


def read_csv_curve(path, reader: dict) -> ForceCurve:
    """Read one CSV/TSV force curve; raises :class:`ForceCurveError` naming the file."""
    path = Path(path)
    cols = reader["columns"]
    try:
        header = _header(path)
    except UnicodeDecodeError:
        raise ForceCurveError(
            path, "not a text CSV/TSV file (binary content); set force_curves.format or check the file type"
        ) from None
    sep = "\t" if "\t" in header else (";" if ";" in header else ("," if "," in header else r"\s+"))
    try:
        df = pd.read_csv(path, sep=sep, comment="#", skipinitialspace=True)
    except (pd.errors.ParserError, pd.errors.EmptyDataError, UnicodeDecodeError) as exc:
        raise ForceCurveError(path, f"cannot parse as CSV/TSV ({exc})") from None
    df.columns = [str(c).strip() for c in df.columns]
    missing = [cols[k] for k in ("height", "deflection") if cols[k] not in df.columns]
    if missing:
        raise ForceCurveError(path, f"missing column(s) {missing}; found {list(df.columns)} (set force_curves.columns)")
    try:
        h_fac, _ = unit_factor(reader["height_unit"], ("length",), "force_curves.height_unit")
        d_fac, d_kind = unit_factor(reader["deflection_unit"], ("voltage", "length"), "force_curves.deflection_unit")
    except QuantityError as exc:
        raise ForceCurveError(path, str(exc)) from None
    num = df[[cols["height"], cols["deflection"]]].apply(pd.to_numeric, errors="coerce").to_numpy(float)
    sign = -1.0 if reader["height_axis"] == "height" else 1.0
    z, d = sign * h_fac * num[:, 0], d_fac * num[:, 1]
    units = "V" if d_kind == "voltage" else "m"
    if units == "V" and np.nanmax(np.abs(d), initial=0.0) > MAX_DETECTOR_VOLTS:
        raise ForceCurveError(
            path,
            f"the deflection column reaches {np.nanmax(np.abs(d)):.4g} V, beyond any photodetector's "
            f"range (+-{MAX_DETECTOR_VOLTS:g} V): is it in nm? set force_curves.deflection_unit "
            "(e.g. 'nm') to the unit the file uses",
        )
    seg_col = cols.get("segment")
    if seg_col and seg_col in df.columns:
        lab = df[seg_col].astype(str).str.strip().str.lower().str.replace(r"\.0$", "", regex=True).to_numpy()
        app, ret = np.isin(lab, list(APPROACH_LABELS)), np.isin(lab, list(RETRACT_LABELS))
        if not ret.any():
            raise ForceCurveError(path, f"no retract segment (segment labels found: {sorted(set(lab))[:6]})")
        parts = (z[app], d[app], z[ret], d[ret])
    else:
        finite = np.isfinite(z)
        if not finite.all():
            raise ForceCurveError(path, f"{int((~finite).sum())} NaN values in the height column")
        parts = split_at_turnaround(path, z, d)
    curve = ForceCurve(str(path), *parts, defl_units=units, source_format="csv")
    return check_segments(curve)
