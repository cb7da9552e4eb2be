"""Stage-5 reports: the per-tip interval table and results/summary.csv (like the paper's Table 1).

CSV conventions: column names carry their unit (``h_nm``, ``W_A_mJ_per_m2``,
``F_p_nN``); a value that does not exist (NaN, no crossing, unusable interval) is an
empty cell and the reason is in the matching ``status``/``note`` column.  Confidence
intervals (``*_low``/``*_high``) are the 2.5th/97.5th percentiles of the Monte-Carlo
estimates (``ci_level`` = 0.95); ``u_*`` is half the 16-84 % spread (1 sigma).
"""

from __future__ import annotations

import csv
import math

import numpy as np

from pipeline.adhesion_range.curves import CI_PCTS
from pipeline.adhesion_range.io import load_range
from pipeline.h5io import atomic_output
from pipeline.inversion.calibration import implausible_forces
from pipeline.inversion.laws import CONVENTIONS, LJ_Z0_OVER_H
from pipeline.units import to_unit

CI_LEVEL = 0.95
_I_LO, _I_16, _I_50, _I_84, _I_HI = (CI_PCTS.index(p) for p in (2.5, 16.0, 50.0, 84.0, 97.5))


def fmt(value, digits: int = 4) -> str:
    """Number -> text with ``digits`` significant digits; NaN/None/inf -> empty cell."""
    if value is None:
        return ""
    if isinstance(value, (bool, np.bool_)):
        return "true" if value else "false"
    if isinstance(value, str):
        return value
    try:
        v = float(value)
    except (TypeError, ValueError):
        return str(value)
    if not math.isfinite(v):
        return ""
    if v == int(v) and abs(v) < 1e15 and isinstance(value, (int, np.integer)):
        return str(int(v))
    return f"{v:.{digits}g}"


def _nm(v):
    return to_unit(float(v), "nm") if v is not None and np.isfinite(v) else np.nan


def _mj(v):
    return to_unit(float(v), "mJ/m^2") if v is not None and np.isfinite(v) else np.nan


def _interp_ln(h_grid, y, hv):
    """y(hv) by linear interpolation in ln h (NaN outside the grid or if not finite)."""
    if not (np.isfinite(hv) and h_grid[0] <= hv <= h_grid[-1]):
        return np.nan
    y = np.asarray(y, float)
    x = np.log(h_grid)
    j = int(np.clip(np.searchsorted(x, np.log(hv)) - 1, 0, x.size - 2))
    if not (np.isfinite(y[j]) and np.isfinite(y[j + 1])):
        return np.nan
    t = (np.log(hv) - x[j]) / (x[j + 1] - x[j])
    return float(y[j] * (1 - t) + y[j + 1] * t)


def _write_csv(path, columns, rows):
    with atomic_output(path) as tmp:
        with open(tmp, "w", newline="") as fh:
            w = csv.writer(fh)
            w.writerow(columns)
            for row in rows:
                w.writerow([fmt(row.get(c)) for c in columns])


def tip_report_columns(laws) -> list:
    """Columns of the per-tip interval table (units in the names)."""
    cols = [
        "tip",
        "interval",
        "scans",
        "reference",
        "n",
        "u_n",
        "n_flag",
        "R_nm",
        "S",
        "Q_nm_pow_n_minus_1",
        "F_p_nN",
        "u_F_p_nN",
        "F_p_sd_nN",
        "n_curves",
        "invols_nm_per_V",
        "u_invols_nm_per_V",
        "invols_method",
        "invols_contact_nm_per_V",
        "u_invols_contact_nm_per_V",
        "invols_check",
    ]
    for law in laws:
        cols += [
            f"W_A_{law}_mJ_per_m2",
            f"h_{law}_nm",
            f"h_{law}_low_nm",
            f"h_{law}_high_nm",
            f"h_{law}_status",
            f"h_{law}_crossings_nm",
            f"h_{law}_note",
        ]
        if law == "tri2":
            cols += ["h_tri2_full_range_nm"]
        if law == "lj":
            cols += ["z0_lj_nm"]
        if law != "dugdale":
            cols += [f"model_{law}_at_estimate"]
    cols += [
        "h_estimate_dugdale_nm",
        "Lambda_at_estimate",
        "Lambda_boundary",
        "rigid_valid",
        "model_used_at_estimate",
        "maugis_lambda_at_estimate",
        "ci_level",
    ]
    return cols


def tip_report_rows(rng: dict) -> tuple[list, list]:
    """Columns and rows (dicts) of the per-tip interval table."""
    gd = rng["laws"].get("dugdale", {}).get("global", {})
    h_est_dug = float(gd.get("h", np.nan)) if gd else np.nan
    rows = []
    for nm in rng["order"]:
        d = rng["intervals"][nm]
        row = _interval_cells(rng["tip"], nm, d)
        for law in rng["law_order"]:
            row.update(_law_cells(law, rng["laws"][law], nm, d, rng["h"]))
        row["h_estimate_dugdale_nm"] = _nm(h_est_dug)
        if "Lambda" in d:
            row.update(_regime_cells(d, rng["h"], h_est_dug))
        rows.append(row)
    return tip_report_columns(rng["law_order"]), rows


def _interval_cells(tip: str, nm: str, d: dict) -> dict:
    """The interval's shape, forces and InvOLS."""
    n_used = float(d["n_used"])
    q_nm = float(d["Q"]) / (1e-9) ** (n_used - 1.0) if np.isfinite(n_used) else np.nan
    row = {
        "tip": tip,
        "interval": nm,
        "scans": int(d["scans"]),
        "reference": bool(d["reference"]),
        "n": float(d["n"]),
        "u_n": float(d["u_n"]),
        "n_flag": d["n_flag"],
        "R_nm": _nm(d["R"]),
        "S": float(d["S"]),
        "Q_nm_pow_n_minus_1": float(np.exp(d["ln_Q_used"]) / (1e-9) ** (n_used - 1.0)) if np.isfinite(n_used) else q_nm,
        "F_p_nN": to_unit(float(d["F_p_mean"]), "nN"),
        "u_F_p_nN": to_unit(float(d["F_p_sem"]), "nN"),
        "F_p_sd_nN": to_unit(float(d["F_p_std"]), "nN"),
        "n_curves": int(d["n_curves"]),
        "ci_level": CI_LEVEL,
    }
    for key in ("invols", "u_invols", "invols_contact", "u_invols_contact"):
        if key in d:
            row[f"{key}_nm_per_V"] = to_unit(float(d[key]), "nm/V")
    for key in ("invols_method", "invols_check"):
        row[key] = str(d.get(key, ""))
    return row


def _law_cells(law: str, L: dict, nm: str, d: dict, h) -> dict:
    """One law's cells of an interval: W_A at the law's global h, the interval's own crossing."""
    iv = L["intervals"][nm]
    g = L.get("global", {})
    hv = float(g.get("h", np.nan)) if g else np.nan
    st = iv["status"]
    row = {
        f"W_A_{law}_mJ_per_m2": _mj(_interp_ln(h, iv["W_A"], hv)),
        f"h_{law}_status": st,
        f"h_{law}_note": iv.get("note", ""),
    }
    cr = np.atleast_1d(iv.get("crossings", []))
    row[f"h_{law}_crossings_nm"] = ";".join(f"{_nm(c):.4g}" for c in cr if np.isfinite(c)) if st != "reference" else ""
    if st == "ok":
        row[f"h_{law}_nm"] = _nm(iv["h_cross"])
        row[f"h_{law}_low_nm"] = _nm(iv["h_pcts"][_I_LO])
        row[f"h_{law}_high_nm"] = _nm(iv["h_pcts"][_I_HI])
        open_sides = [s for s, i in (("lower", _I_LO), ("upper", _I_HI)) if not np.isfinite(iv["h_pcts"][i])]
        if open_sides:
            row[f"h_{law}_note"] = (
                f"95 % CI open on the {' and '.join(open_sides)} side (MC crossings beyond "
                f"the h grid; crossing fraction {float(iv['crossing_fraction']):.2f})"
            )
        if law == "tri2":
            row["h_tri2_full_range_nm"] = 2.0 * _nm(iv["h_cross"])
        if law == "lj":
            row["z0_lj_nm"] = _nm(iv["h_cross"]) * LJ_Z0_OVER_H
    if law != "dugdale" and f"model_used_{law}" in d and np.isfinite(hv):
        row[f"model_{law}_at_estimate"] = str(d[f"model_used_{law}"][int(np.argmin(np.abs(np.log(h) - np.log(hv))))])
    return row


def _regime_cells(d: dict, h, h_est_dug: float) -> dict:
    """Lambda, Lambda_b (Eq. 13), rigid validity, the Dugdale model used and the Maugis parameter
    at the Dugdale estimate of h."""
    row = {"Lambda_at_estimate": _interp_ln(h, d["Lambda"], h_est_dug)}
    lb = np.asarray(d["Lambda_boundary"], float)
    row["Lambda_boundary"] = float(np.nanmedian(lb)) if np.any(np.isfinite(lb)) else np.nan
    if np.isfinite(row["Lambda_at_estimate"]):
        row["rigid_valid"] = bool(row["Lambda_at_estimate"] < row["Lambda_boundary"])
        j = int(np.argmin(np.abs(np.log(h) - np.log(h_est_dug))))
        row["model_used_at_estimate"] = str(d["model_used"][j])
    if "maugis_lambda" in d:
        row["maugis_lambda_at_estimate"] = _interp_ln(h, d["maugis_lambda"], h_est_dug)
    return row


def write_tip_report(range_h5, out_csv, *, tip: str = ""):
    """Per-tip CSV, one row per interval (see module docstring for conventions)."""
    rng = load_range(range_h5)
    if tip:
        rng["tip"] = tip
    cols, rows = tip_report_rows(rng)
    _write_csv(out_csv, cols, rows)
    return rows


SUMMARY_COLUMNS = [
    "tip",
    "law",
    "solver_mode",
    "W_A_mJ_per_m2",
    "u_W_A_mJ_per_m2",
    "W_A_low_mJ_per_m2",
    "W_A_high_mJ_per_m2",
    "h_nm",
    "u_h_nm",
    "h_low_nm",
    "h_high_nm",
    "h_full_range_nm",
    "h_full_range_low_nm",
    "h_full_range_high_nm",
    "z0_lj_nm",
    "h_crossings_min_nm",
    "h_crossings_max_nm",
    "W_A_ref_mJ_per_m2",
    "u_W_A_ref_mJ_per_m2",
    "W_A_ref_max_rel_change_over_h",
    "n_intervals_used",
    "n_intervals_crossing",
    "chi2",
    "dof",
    "p_value",
    "ci_scale_birge",
    "between_interval_scatter_percent",
    "ci_widening_h",
    "ci_widening_W_A",
    "h_change_per_reference_percent",
    "ci_level",
    "h_convention",
    "model_at_estimate",
    "status",
    "notes",
]


def models_at(rng: dict, law: str, h_value: float) -> str:
    """Which model(s) made the law's W_A(h) of the intervals at h_value: "rigid", "mdn",
    "elastic", or e.g. "rigid (2), elastic (1)" when the intervals differ."""
    if not np.isfinite(h_value):
        return ""
    key = "model_used" if law == "dugdale" else f"model_used_{law}"
    h = np.asarray(rng["h"], float)
    j = int(np.argmin(np.abs(np.log(h) - np.log(h_value))))
    used = [str(d[key][j]) for d in rng["intervals"].values() if key in d]
    names = sorted(set(used))
    return names[0] if len(names) == 1 else ", ".join(f"{m} ({used.count(m)})" for m in names)


def summary_rows(rng: dict) -> list:
    """One summary row per traction law of a tip (``load_range``)."""
    return [_summary_row(rng, law) for law in rng["law_order"]]


def _summary_row(rng: dict, law: str) -> dict:
    L = rng["laws"][law]
    g = L.get("global", {})
    row = {
        "tip": rng["tip"],
        "law": law,
        "solver_mode": rng["solver_mode"],
        "ci_level": CI_LEVEL,
        "h_convention": CONVENTIONS[law],
    }
    status = g.get("status", "no_reference") if g else "no_reference"
    notes = _global_cells(row, g, law, status) if g else []
    ref = L.get("reference")
    if ref is not None and g:
        row["W_A_ref_mJ_per_m2"] = _mj(g.get("W_ref_at_h", np.nan))
        pc = np.asarray(g.get("W_ref_at_h_pcts", [np.nan] * len(CI_PCTS)), float)
        row["u_W_A_ref_mJ_per_m2"] = 0.5 * (_mj(pc[_I_84]) - _mj(pc[_I_16]))
        row["W_A_ref_max_rel_change_over_h"] = float(ref["max_rel_change"])
        if status != "ok":
            notes.append(f"W_A_ref at h = {_nm(g.get('W_ref_h', np.nan)):.3g} nm (grid centre)")
    notes += _crossing_cells(row, L, status)
    notes += _tip_notes(rng, L, law)
    if status == "ok":
        row["model_at_estimate"] = models_at(rng, law, float(g["h"]))
    row["status"] = status
    row["notes"] = " | ".join(n for n in notes if n)
    return row


def _global_cells(row: dict, g: dict, law: str, status: str) -> list:
    """The global h and W_A with their intervals and the consistency of the intervals (into
    ``row``); returns the notes."""
    notes = []
    hp = np.asarray(g["h_pcts"], float)
    wp = np.asarray(g["W_pcts"], float)
    if status == "ok":
        row["h_nm"] = _nm(g["h"])
        row["u_h_nm"] = 0.5 * (_nm(hp[_I_84]) - _nm(hp[_I_16]))
        row["h_low_nm"], row["h_high_nm"] = _nm(hp[_I_LO]), _nm(hp[_I_HI])
        if not np.isfinite(hp[_I_LO]) or not np.isfinite(hp[_I_HI]):
            notes.append("h CI open (reaches the h grid edge)")
        row["W_A_mJ_per_m2"] = _mj(g["W_A"])
        row["u_W_A_mJ_per_m2"] = 0.5 * (_mj(wp[_I_84]) - _mj(wp[_I_16]))
        row["W_A_low_mJ_per_m2"], row["W_A_high_mJ_per_m2"] = _mj(wp[_I_LO]), _mj(wp[_I_HI])
        factor = {"dugdale": 1.0, "tri1": 1.0, "tri2": 2.0}.get(law)
        if factor is not None:
            row["h_full_range_nm"] = factor * row["h_nm"]
            row["h_full_range_low_nm"] = factor * row["h_low_nm"]
            row["h_full_range_high_nm"] = factor * row["h_high_nm"]
        if law == "lj":
            row["z0_lj_nm"] = row["h_nm"] * LJ_Z0_OVER_H
        row["chi2"] = float(g["chi2_min"])
        row["dof"] = int(g["dof"])
        row["p_value"] = float(g.get("p_value", np.nan))
        row["ci_scale_birge"] = float(g.get("birge_ratio", np.nan))
        row["between_interval_scatter_percent"] = 100.0 * float(g.get("tau", np.nan))
        row["ci_widening_h"] = float(g.get("ci_widening_h", 1.0))
        row["ci_widening_W_A"] = float(g.get("ci_widening_W", 1.0))
    row["n_intervals_used"] = len(g.get("intervals_used", []))
    if g.get("note"):
        notes.append(str(g["note"]).strip())
    return notes


def _crossing_cells(row: dict, L: dict, status: str) -> list:
    """The intervals' own crossings and how much h rests on the reference (into ``row``); returns
    the notes."""
    notes = []
    # how much h rests on the reference: d ln h / d ln W_ref = 1 / |d ln(W/W_ref) / d ln h| at each crossing
    slopes = [float(iv["slope"]) for iv in L["intervals"].values() if iv["status"] == "ok" and float(iv["slope"]) > 0]
    if slopes and status == "ok":
        row["h_change_per_reference_percent"] = float(np.median(1.0 / np.asarray(slopes)))
        notes.append(
            f"h rests on the reference interval: a 1 % error of its W_A (its pull-off or R) moves h by "
            f"{row['h_change_per_reference_percent']:.2g} %, which the agreement of the intervals reveals only in part"
        )
    crossings = [float(iv["h_cross"]) for iv in L["intervals"].values() if iv["status"] == "ok"]
    row["n_intervals_crossing"] = len(crossings)
    if crossings:
        row["h_crossings_min_nm"] = _nm(min(crossings))
        row["h_crossings_max_nm"] = _nm(max(crossings))
    return notes


def _tip_notes(rng: dict, L: dict, law: str) -> list:
    """Calibration warnings of the tip, intervals that did not take part, and the law's h convention."""
    notes = []
    flagged = [nm for nm in rng["order"] if str(rng["intervals"][nm].get("invols_check", ""))]
    if flagged:
        notes.append(
            f"InvOLS in use disagrees with the contact slope in {', '.join(flagged)} (invols_check in "
            f"{rng['tip']}_report.csv): a remount without a new InvOLS, or a soft counter-surface"
        )
    notes += implausible_forces({nm: float(rng["intervals"][nm].get("F_p_mean", np.nan)) for nm in rng["order"]})
    bad = [f"{nm}: {iv['status']}" for nm, iv in L["intervals"].items() if iv["status"] not in ("ok", "reference")]
    if bad:
        notes.append("intervals " + "; ".join(bad))
    if law == "lj":
        notes.append("L-J range in the z0 = h/0.974 convention")
    if law == "tri2":
        notes.append("h = Dugdale-equivalent (peak-stress) h; full range 2h in h_full_range_nm (paper Table 1 uses 2h)")
    return notes


def write_summary(tip_range_h5s: dict, out_csv, *, failed: dict | None = None):
    """results/summary.csv: one row per tip and traction law (like the paper's Table 1).

    ``tip_range_h5s`` maps tip name -> stage-5 HDF5 (a list of paths is accepted too; the tip
    name is then read from the files).  ``failed`` maps the name of a tip without a result to
    the reason (which job failed and why): it gets one row, status ``failed``, the reason in
    ``notes`` and every number empty.
    """
    items = tip_range_h5s.items() if isinstance(tip_range_h5s, dict) else [(None, p) for p in tip_range_h5s]
    rows = []
    for tip, path in items:
        rng = load_range(path)
        if tip:
            rng["tip"] = str(tip)
        rows += summary_rows(rng)
    rows += [{"tip": tip, "status": "failed", "notes": reason} for tip, reason in (failed or {}).items()]
    _write_csv(out_csv, SUMMARY_COLUMNS, rows)
    return rows
