"""Stage entry point: force curves of one interval -> calibrated pull-off forces (HDF5 + PNG).

HDF5 layout (every dataset has ``units``):

/curves/     per curve (n = curves found, maps count each curve): file, accepted,
             rejection_reason, outlier, used, modified_z, delta_V, delta_m, u_delta_m,
             delta_min_m, F_p, u_F_p_stat, baseline_offset, baseline_slope,
             baseline_noise, n_baseline, z_pulloff, spring_constant_file, invols_file
/interval/   F_p_mean, F_p_std, F_p_sem, F_p_median, n_curves_used, n_curves_total,
             n_curves_rejected, n_outliers, delta_V_mean, delta_m_mean,
             u_F_p_calibration, u_F_p_calibration_rel, u_F_p_total;
             ``calibration`` is a soft link to /calibration
/calibration/ k, u_k, invols, u_invols, factor (k*InvOLS), u_factor, u_factor_rel,
             corr_k_invols, k_method, invols_method, k_source, invols_source and a
             subgroup per method used (hard_sample, reference_curves, reference_lever, thermal)

Statistical (scatter, F_p_sem) and calibration (u_F_p_calibration = F_p_mean *
u(k InvOLS)/(k InvOLS), systematic for all intervals of a tip) parts are separate.
"""
from __future__ import annotations

from pathlib import Path

import h5py
import numpy as np

from pipeline.forces.calibration import Calibration, calibrate
from pipeline.forces.errors import CalibrationError, ForceCurveError, ForcesStageError
from pipeline.forces.figures import plot_retracts
from pipeline.forces.pulloff import detect_pulloff
from pipeline.forces.reading import read_curves
from pipeline.forces.settings import CANTILEVER_DEFAULTS, READER_DEFAULTS, resolve_paths, with_defaults
from pipeline.forces.statistics import interval_stats
from pipeline.h5io import atomic_h5, create_group, write_dataset

OUTLIER_RULES = {
    "esd": "generalized ESD test (Rosner 1983) at significance outlier_alpha over accepted curves, up to floor(n/3) outliers (none if n < 3)",
    "modified_z": "modified z-score 0.6745 |x - median| / MAD > outlier_z over accepted curves (none flagged if n < 3 or MAD = 0)",
}
MEAN_RULE = "mean, std (ddof=1) and sem over accepted non-outlier curves"


def _expand(paths, cfg):
    out = []
    for p in paths:
        p = Path(p)
        out.extend(resolve_paths(cfg, str(p)) if p.is_dir() else [p])
    return out


def run_forces(curve_paths, out_h5, out_png, *, cantilever: dict, reader: dict, tip="", interval="") -> None:
    """Analyse one interval's force curves; write ``out_h5`` and ``out_png`` atomically.

    ``cantilever``/``reader``: the SI-converted ``cantilever:``/``force_curves:`` sections
    (paths relative to their ``base_dir``).  Unreadable or unanalysable curves are
    rejected with a reason; raises :class:`ForcesStageError` (no output) when none is
    accepted, :class:`CalibrationError` when k/InvOLS cannot be resolved.
    """
    reader = with_defaults(reader, READER_DEFAULTS)
    cant = with_defaults(cantilever, CANTILEVER_DEFAULTS)
    for a, b in ((reader, cant), (cant, reader)):
        if "base_dir" in b and "base_dir" not in a:
            a["base_dir"] = b["base_dir"]
    label = f"tip {tip!r} interval {interval!r}"
    files = _expand(curve_paths, reader)
    if not files:
        raise ForcesStageError(f"{label}: no force-curve files given")

    rows = []  # one per curve: dict(file, curve|None, reason)
    for p in files:
        try:
            rows.extend({"file": c.path, "curve": c, "reason": ""} for c in read_curves(p, reader))
        except ForceCurveError as exc:
            rows.append({"file": str(p), "curve": None, "reason": exc.reason})
    curves = [r["curve"] for r in rows if r["curve"] is not None]
    if not curves:
        raise ForcesStageError(_all_rejected(label, rows))
    cal = calibrate(cant, curves, reader)

    for r in rows:
        c = r["curve"]
        if c is None:
            continue
        try:
            r["po"] = _pulloff(c, reader, cal)
        except ForceCurveError as exc:
            r["reason"] = exc.reason
    accepted = np.array([not r["reason"] for r in rows])
    if not accepted.any():
        raise ForcesStageError(_all_rejected(label, rows))

    n = len(rows)
    col = {k: np.full(n, np.nan) for k in ("delta_V", "delta_m", "u_delta_m", "delta_min_m", "off", "slope", "noise", "nb", "zpo")}
    for i, r in enumerate(rows):
        if "po" in r and not r["reason"]:
            for k, v in r["po"].items():
                if k.startswith("_"):
                    continue
                col[k][i] = v
    F_p = cal.k * col["delta_m"]
    u_F_stat = cal.k * col["u_delta_m"]
    st = interval_stats(F_p, accepted, reader["outlier_z"], rule=reader["outlier_rule"], alpha=reader["outlier_alpha"])
    used = accepted & ~st.outlier
    u_cal_rel = cal.u_factor_rel if np.isfinite(cal.invols) else cal.u_k_rel

    with atomic_h5(out_h5, stage="forces", tip=tip, interval=interval, outlier_rule=OUTLIER_RULES[reader["outlier_rule"]], mean_rule=MEAN_RULE,
                   reader_config={k: v for k, v in reader.items()}, cantilever_config={k: v for k, v in cant.items()}) as f:
        g = create_group(f, "curves", "NXcollection")
        write_dataset(g, "file", [r["file"] for r in rows], "1", "curve file (#i: i-th curve of a map)")
        write_dataset(g, "accepted", accepted, "1", "curve passed reading and pull-off detection")
        write_dataset(g, "rejection_reason", [r["reason"] for r in rows], "1", "why the curve was rejected ('' if accepted)")
        write_dataset(g, "outlier", st.outlier, "1", "flagged by the modified z-score rule (kept, not averaged)")
        write_dataset(g, "used", used, "1", "accepted and not an outlier: enters the interval mean")
        write_dataset(g, "modified_z", st.modified_z, "1", "modified z-score of F_p (NaN if rejected)")
        write_dataset(g, "delta_V", col["delta_V"], "V", "max adhesive deflection Delta in volts (NaN if not recorded in V)")
        write_dataset(g, "delta_m", col["delta_m"], "m", "Delta in metres (= delta_V * InvOLS)")
        write_dataset(g, "u_delta_m", col["u_delta_m"], "m", "statistical uncertainty of Delta (noise + sampling step)")
        write_dataset(g, "delta_min_m", col["delta_min_m"], "m", "raw minimum of the baseline-corrected retract (cross-check)")
        write_dataset(g, "F_p", F_p, "N", "pull-off force k * Delta")
        write_dataset(g, "u_F_p_stat", u_F_stat, "N", "statistical uncertainty of F_p of the curve (calibration excluded)")
        bu = "V" if np.isfinite(cal.invols) else "m"
        write_dataset(g, "baseline_offset", col["off"], bu, "baseline offset at z = 0 (retract free part)")
        write_dataset(g, "baseline_slope", col["slope"], f"{bu}/m", "baseline tilt per m of piezo extension")
        write_dataset(g, "baseline_noise", col["noise"], bu, "rms of the baseline residuals")
        write_dataset(g, "n_baseline", col["nb"], "1", "points in the baseline fit")
        write_dataset(g, "z_pulloff", col["zpo"], "m", "piezo extension at the jump-off")
        write_dataset(g, "spring_constant_file", [_nan(r, "spring_constant") for r in rows], "N/m", "k stored in the file (NaN if none)")
        write_dataset(g, "invols_file", [_nan(r, "invols") for r in rows], "m/V", "InvOLS stored in the file (NaN if none)")

        c = create_group(f, "calibration", "NXcollection")
        for name, val, unit, desc in (
                ("k", cal.k, "N/m", "spring constant used"), ("u_k", cal.u_k, "N/m", "1-sigma uncertainty of k"),
                ("invols", cal.invols, "m/V", "deflection sensitivity used (NaN: deflection recorded in m)"),
                ("u_invols", cal.u_invols, "m/V", "1-sigma uncertainty of InvOLS"),
                ("factor", cal.factor, "N/V", "k * InvOLS: F_p = factor * delta_V"),
                ("u_factor", cal.u_factor, "N/V", "1-sigma uncertainty of k * InvOLS (correlations included)"),
                ("u_factor_rel", u_cal_rel, "1", "relative calibration uncertainty of F_p (systematic)"),
                ("corr_k_invols", cal.corr_k_invols, "1", "correlation coefficient of k and InvOLS"),
                ("k_method", cal.k_method, "1", "given | file | reference_lever | thermal"),
                ("invols_method", cal.invols_method, "1", "given | hard_sample | file"),
                ("k_source", cal.k_source, "1", "where k came from"), ("invols_source", cal.invols_source, "1", "where InvOLS came from")):
            write_dataset(c, name, val, unit, desc)
        for gname, items in cal.details.items():
            sub = create_group(c, gname, "NXcollection")
            for name, (val, unit, desc) in items.items():
                write_dataset(sub, name, val, unit, desc)

        iv = create_group(f, "interval", "NXcollection", outlier_rule=OUTLIER_RULES[reader["outlier_rule"]], mean_rule=MEAN_RULE)
        for name, val, unit, desc in (
                ("F_p_mean", st.mean, "N", MEAN_RULE), ("F_p_std", st.std, "N", "standard deviation (ddof=1; NaN if 1 curve)"),
                ("F_p_sem", st.sem, "N", "standard error of the mean (statistical part)"),
                ("F_p_median", st.median, "N", "median of used curves"),
                ("n_curves_used", st.n_used, "1", "curves in the mean"), ("n_curves_total", n, "1", "curves found"),
                ("n_curves_rejected", int((~accepted).sum()), "1", "rejected curves (see curves/rejection_reason)"),
                ("n_outliers", int(st.outlier.sum()), "1", "accepted curves flagged as outliers"),
                ("delta_V_mean", float(np.mean(col["delta_V"][used])), "V", "mean Delta of used curves (V)"),
                ("delta_m_mean", float(np.mean(col["delta_m"][used])), "m", "mean Delta of used curves (m)"),
                ("u_F_p_calibration", st.mean * u_cal_rel, "N", "systematic calibration part (k, InvOLS), common to all intervals of the tip"),
                ("u_F_p_calibration_rel", u_cal_rel, "1", "relative calibration uncertainty"),
                ("u_F_p_total", float(np.hypot(np.nan_to_num(st.sem), st.mean * u_cal_rel)), "N", "sqrt(sem^2 + calibration^2)")):
            write_dataset(iv, name, val, unit, desc)
        iv["calibration"] = h5py.SoftLink("/calibration")

        plot_retracts(out_png, [_plot_item(r, cal, st.outlier[i]) for i, r in enumerate(rows) if r["curve"] is not None],
                      n_total=n, title=f"{tip} {interval}: F_p = {st.mean * 1e9:.3g} +- {np.nan_to_num(st.sem) * 1e9:.2g} nN (n={st.n_used})")


def _nan(row, attr):
    c = row["curve"]
    v = getattr(c, attr, None) if c is not None else None
    return np.nan if v is None else v


def _volts_or_m(c, cal: Calibration):
    """(deflection of the retract, to-metres factor, is_volts)."""
    if c.defl_units == "V" or c.invols is not None:
        if not np.isfinite(cal.invols):
            raise CalibrationError(f"{c.path}: curve in volts but no InvOLS available")
        return c.deflection_volts("retract"), cal.invols, True
    return c.defl_retract, 1.0, False


def _pulloff(c, reader, cal: Calibration) -> dict:
    d, to_m, volts = _volts_or_m(c, cal)
    po = detect_pulloff(c.z_retract, d, path=c.path, baseline_gap=reader["baseline_gap"],
                        min_baseline_points=int(reader["min_baseline_points"]), method=reader["pulloff_method"],
                        fit_points=int(reader["pulloff_fit_points"]), min_snr=float(reader["min_pulloff_snr"]))
    return {"delta_V": po.delta if volts else np.nan, "delta_m": po.delta * to_m, "u_delta_m": po.u_delta * to_m,
            "delta_min_m": po.delta_min * to_m, "off": po.baseline.offset, "slope": po.baseline.slope,
            "noise": po.baseline.rms, "nb": po.n_baseline, "zpo": po.z_pulloff, "_po": po}


def _plot_item(r, cal, outlier):
    c = r["curve"]
    try:
        d, to_m, _ = _volts_or_m(c, cal)
    except CalibrationError:
        return {"x": np.zeros(0), "force": np.zeros(0), "baseline": None, "x_po": 0, "F_po": 0, "accepted": False, "outlier": False}
    fac = cal.k * to_m
    po = r.get("_po") or (r.get("po") or {}).get("_po")
    if po is None or r["reason"]:
        x = c.z_retract.max() - c.z_retract
        return {"x": x, "force": fac * (d - np.median(d[-max(10, d.size // 5):])), "baseline": None, "x_po": 0, "F_po": 0,
                "accepted": False, "outlier": False}
    x = po.z_pulloff - c.z_retract
    ref = po.baseline(po.z_pulloff)
    return {"x": x, "force": fac * (d - ref), "baseline": fac * (po.baseline(c.z_retract) - ref), "x_po": 0.0, "F_po": -fac * po.delta,
            "accepted": True, "outlier": bool(outlier)}


def _all_rejected(label, rows) -> str:
    lines = "\n".join(f"  {r['file']}: {r['reason']}" for r in rows)
    return f"{label}: all {len(rows)} force curves were rejected, no output written:\n{lines}"


__all__ = ["run_forces", "CalibrationError", "ForcesStageError", "CANTILEVER_DEFAULTS"]
