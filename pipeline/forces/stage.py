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
/calibration/ k, u_k, invols, u_invols (this interval's), factor (k*InvOLS), u_factor,
             u_factor_rel, u_k_rel, u_invols_rel, corr_k_invols, k_method, invols_method,
             k_source, invols_source, invols_shared (one InvOLS for the whole tip), invols_tip,
             u_invols_tip (the calibration session's, NaN if none), the contact-slope check
             (invols_contact, u_invols_contact, n_invols_contact, invols_check_z, invols_check)
             and a subgroup per method used (hard_sample, reference_curves, reference_lever, thermal)
/curves/     also invols_contact, u_invols_contact_fit, invols_contact_reason (the per-curve
             contact slope measured on every curve, whatever the InvOLS source)

Statistical (scatter, F_p_sem) and calibration parts are separate: k is common to all
intervals of a tip; InvOLS is the interval's own (``pipeline.forces.invols``: the chip is
remounted after every TEM session) unless ``invols_shared``.  Warnings (an InvOLS that
disagrees with the contact slope, curves that give no contact slope, a fallback) are in the
root attribute ``warnings`` and in the log.
"""
from __future__ import annotations

import logging
from pathlib import Path

import h5py
import numpy as np

from pipeline.forces.calibration import Calibration, calibrate
from pipeline.forces.errors import CalibrationError, ForceCurveError, ForcesStageError
from pipeline.forces.figures import plot_retracts
from pipeline.forces.invols import IntervalInvols, resolve_interval_invols
from pipeline.forces.pulloff import detect_pulloff
from pipeline.forces.reading import read_curves
from pipeline.forces.settings import CANTILEVER_DEFAULTS, READER_DEFAULTS, resolve_paths, with_defaults
from pipeline.forces.statistics import interval_stats
from pipeline.h5io import atomic_h5, create_group, write_dataset

OUTLIER_RULES = {
    "esd": "generalized ESD test (Rosner 1983) at significance outlier_alpha over accepted curves, up to floor(n/3) outliers (none if n < 3)",
    "modified_z": "modified z-score 0.6745 |x - median| / MAD > outlier_z over accepted curves (none flagged if n < 3 or MAD = 0)",
}
MEAN_RULE = ("random-effects weighted mean over accepted non-outlier curves, weights 1/(u_i^2 + tau^2) with tau the "
             "between-curve scatter (DerSimonian-Laird; the plain mean for equal u_i); sem: modified Knapp-Hartung")
log = logging.getLogger(__name__)


def _expand(paths, cfg):
    out = []
    for p in paths:
        p = Path(p)
        out.extend(resolve_paths(cfg, str(p)) if p.is_dir() else [p])
    return out


def run_forces(curve_paths, out_h5, out_png, *, cantilever: dict, reader: dict, tip="", interval="",
               interval_cfg: dict | None = None) -> None:
    """Analyse one interval's force curves; write ``out_h5`` and ``out_png`` atomically.

    ``cantilever``/``reader``: the SI-converted ``cantilever:``/``force_curves:`` sections
    (paths relative to their ``base_dir``); ``interval_cfg`` the interval's entry of the tip
    YAML (its own deflection_sensitivity / calibration_curves, if any).  Unreadable or
    unanalysable curves are rejected with a reason; raises :class:`ForcesStageError` (no
    output) when fewer than ``min_curves`` are accepted, :class:`CalibrationError` when k or
    the interval's InvOLS cannot be resolved.
    """
    reader = with_defaults(reader, READER_DEFAULTS)
    cant = with_defaults(cantilever, CANTILEVER_DEFAULTS)
    for a, b in ((reader, cant), (cant, reader)):
        if "base_dir" in b and "base_dir" not in a:
            a["base_dir"] = b["base_dir"]
    # files that store the instrument's force without its calibration are undone with these
    reader["instrument_spring_constant"] = cant.get("spring_constant")
    reader["instrument_deflection_sensitivity"] = cant.get("deflection_sensitivity")
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
    inv = resolve_interval_invols(cant, interval_cfg, curves, cal, reader=reader, label=label)
    warnings = [f"{label}: {w}" for w in inv.warnings] + ([f"{label}: {inv.check}"] if inv.check else [])
    for w in warnings:
        log.warning(w)

    for r in rows:
        c = r["curve"]
        if c is None:
            continue
        try:
            r["po"] = _pulloff(c, reader, inv.value)
        except ForceCurveError as exc:
            r["reason"] = exc.reason
    accepted = np.array([not r["reason"] for r in rows])
    if not accepted.any():
        raise ForcesStageError(_all_rejected(label, rows))
    if accepted.sum() < int(reader["min_curves"]):
        used_files = ", ".join(r["file"] for r, a in zip(rows, accepted) if a)
        raise ForcesStageError(
            f"{label}: only {int(accepted.sum())} usable force curve(s) ({used_files}) of {len(rows)}; the pull-off "
            f"scatter cannot be estimated from fewer than {int(reader['min_curves'])}: add curves, or set "
            "force_curves.min_curves: 1 to accept it (no statistical uncertainty of F_p), no output written")
    ci = _contact_columns(inv, rows)

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
    st = interval_stats(F_p, accepted, reader["outlier_z"], rule=reader["outlier_rule"], alpha=reader["outlier_alpha"], u=u_F_stat)
    used = accepted & ~st.outlier
    u_k_rel, u_inv_rel, u_cal_rel, factor, u_factor, corr = _calibration_parts(cal, inv)
    _log_decisions(label, rows, cal, inv, st, used, col)

    with atomic_h5(out_h5, stage="forces", tip=tip, interval=interval, outlier_rule=OUTLIER_RULES[reader["outlier_rule"]], mean_rule=MEAN_RULE,
                   reader_config={k: v for k, v in reader.items()}, cantilever_config={k: v for k, v in cant.items()},
                   warnings=warnings) as f:
        g = create_group(f, "curves", "NXcollection")
        write_dataset(g, "file", [r["file"] for r in rows], "1", "curve file (#i: i-th curve of a map)")
        write_dataset(g, "accepted", accepted, "1", "curve passed reading and pull-off detection")
        write_dataset(g, "rejection_reason", [r["reason"] for r in rows], "1", "why the curve was rejected ('' if accepted)")
        write_dataset(g, "outlier", st.outlier, "1", "flagged by the outlier rule (kept, not averaged)")
        write_dataset(g, "used", used, "1", "accepted and not an outlier: enters the interval mean")
        write_dataset(g, "weight", st.weight, "1", "relative weight of the curve in the interval mean (0: not used)")
        write_dataset(g, "modified_z", st.modified_z, "1", "modified z-score of F_p (NaN if rejected)")
        write_dataset(g, "delta_V", col["delta_V"], "V", "max adhesive deflection Delta in volts (NaN if not recorded in V)")
        write_dataset(g, "delta_m", col["delta_m"], "m", "Delta in metres (= delta_V * InvOLS)")
        write_dataset(g, "u_delta_m", col["u_delta_m"], "m", "statistical uncertainty of Delta (noise + sampling step)")
        write_dataset(g, "delta_min_m", col["delta_min_m"], "m", "raw minimum of the baseline-corrected retract (cross-check)")
        write_dataset(g, "F_p", F_p, "N", "pull-off force k * Delta")
        write_dataset(g, "u_F_p_stat", u_F_stat, "N", "statistical uncertainty of F_p of the curve (calibration excluded)")
        bu = "V" if np.isfinite(inv.value) else "m"
        write_dataset(g, "baseline_offset", col["off"], bu, "baseline offset at z = 0 (retract free part)")
        write_dataset(g, "baseline_slope", col["slope"], f"{bu}/m", "baseline tilt per m of piezo extension")
        write_dataset(g, "baseline_noise", col["noise"], bu, "rms of the baseline residuals")
        write_dataset(g, "n_baseline", col["nb"], "1", "points in the baseline fit")
        write_dataset(g, "z_pulloff", col["zpo"], "m", "piezo extension at the jump-off")
        write_dataset(g, "spring_constant_file", [_nan(r, "spring_constant") for r in rows], "N/m", "k stored in the file (NaN if none)")
        write_dataset(g, "invols_file", [_nan(r, "invols") for r in rows], "m/V", "InvOLS stored in the file (NaN if none)")
        write_dataset(g, "invols_contact", ci["invols"], "m/V", "InvOLS from this curve's contact slope (NaN: see the reason)")
        write_dataset(g, "u_invols_contact_fit", ci["u"], "m/V", "fit standard error of that InvOLS")
        write_dataset(g, "invols_contact_reason", ci["reason"], "1", "why the curve gives no contact slope ('' if it does)")

        c = create_group(f, "calibration", "NXcollection")
        for name, val, unit, desc in (
                ("k", cal.k, "N/m", "spring constant used"), ("u_k", cal.u_k, "N/m", "1-sigma uncertainty of k"),
                ("invols", inv.value, "m/V", "deflection sensitivity used for this interval (NaN: deflection recorded in m)"),
                ("u_invols", inv.u, "m/V", "1-sigma uncertainty of InvOLS"),
                ("factor", factor, "N/V", "k * InvOLS: F_p = factor * delta_V"),
                ("u_factor", u_factor, "N/V", "1-sigma uncertainty of k * InvOLS (correlations included)"),
                ("u_factor_rel", u_cal_rel, "1", "relative calibration uncertainty of F_p"),
                ("u_k_rel", u_k_rel, "1", "relative uncertainty of k (common to all intervals of the tip)"),
                ("u_invols_rel", u_inv_rel, "1", "relative uncertainty of this interval's InvOLS (its own unless invols_shared)"),
                ("corr_k_invols", corr, "1", "correlation coefficient of k and InvOLS"),
                ("k_method", cal.k_method, "1", "given | file | reference_lever | thermal"),
                ("invols_method", inv.method, "1", "contact | interval_curves | interval_given | given | hard_sample | file | none"),
                ("invols_shared", inv.shared, "1", "one InvOLS for the whole tip (its error common to all intervals)"),
                ("invols_tip", cal.invols, "m/V", "tip-level InvOLS of the calibration session (NaN if none)"),
                ("u_invols_tip", cal.u_invols, "m/V", "its 1-sigma uncertainty"),
                ("invols_contact", inv.contact.mean if inv.contact else np.nan, "m/V",
                 "InvOLS from the contact slopes of this interval's own curves (mean)"),
                ("u_invols_contact", inv.contact.u if inv.contact else np.nan, "m/V", "its standard error with the systematic floor"),
                ("n_invols_contact", inv.contact.n if inv.contact else 0, "1", "curves that gave a contact slope"),
                ("contact_fit_deflection", inv.contact.fit_range_m if inv.contact else np.full(2, np.nan), "m",
                 "mean deflection above the baseline at the two ends of the contact-slope fit (its load range: "
                 "the inversion corrects a contact InvOLS for the tip's finite contact stiffness over it)"),
                ("contact_segment", str(cant["contact_segment"]), "1", "segment the contact slopes were fitted on"),
                ("invols_check_z", inv.check_z, "1", "(InvOLS in use - contact) / combined uncertainty (NaN: not checked)"),
                ("invols_check", inv.check, "1", "'' or what disagrees (a forgotten remount)"),
                ("k_source", cal.k_source, "1", "where k came from"), ("invols_source", inv.source, "1", "where InvOLS came from")):
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
                ("F_p_tau", st.tau, "N", "between-curve scatter of F_p beyond the curves' own uncertainties (random effects)"),
                ("delta_V_mean", float(np.sum(st.weight[used] * col["delta_V"][used])), "V", "weighted mean Delta of used curves (V)"),
                ("delta_m_mean", float(np.sum(st.weight[used] * col["delta_m"][used])), "m", "weighted mean Delta of used curves (m)"),
                ("u_F_p_calibration", st.mean * u_cal_rel, "N", "calibration part (k common to the tip; InvOLS the interval's own unless shared)"),
                ("u_F_p_calibration_rel", u_cal_rel, "1", "relative calibration uncertainty"),
                ("u_F_p_total", float(np.hypot(np.nan_to_num(st.sem), st.mean * u_cal_rel)), "N", "sqrt(sem^2 + calibration^2)")):
            write_dataset(iv, name, val, unit, desc)
        iv["calibration"] = h5py.SoftLink("/calibration")

        plot_retracts(out_png, [_plot_item(r, cal.k, inv.value, st.outlier[i]) for i, r in enumerate(rows) if r["curve"] is not None],
                      n_total=n, title=_figure_title(tip, interval, st))


def _log_decisions(label, rows, cal, inv, st, used, col) -> None:
    """The stage's decisions in plain lines (the log is the lab notebook)."""
    log.info("%s: k = %.4g N/m +- %.2g %% (%s); InvOLS = %.4g nm/V +- %.2g %% (%s)", label, cal.k, 100 * cal.u_k_rel,
             cal.k_source, inv.value * 1e9, 100 * inv.u / inv.value if inv.value else float("nan"), inv.source)
    if inv.contact is not None and inv.contact.n:
        log.info("%s: contact slopes of %d curve(s): InvOLS %.4g +- %.2g nm/V", label, inv.contact.n, inv.contact.mean * 1e9,
                 inv.contact.u * 1e9)
    for i, r in enumerate(rows):
        name = Path(r["file"]).name
        if r["reason"]:
            log.info("%s: curve %s rejected: %s", label, name, r["reason"])
        elif "po" in r:
            po = r["po"]["_po"]
            log.info("%s: curve %s: Delta = %.4g nm +- %.2g (%s)%s, weight %.3f", label, name, col["delta_m"][i] * 1e9,
                     col["u_delta_m"][i] * 1e9, po.shape, "; outlier, not averaged" if st.outlier[i] else "", st.weight[i])
    log.info("%s: F_p = %.4g nN, standard error %.2g nN, SD %.2g nN over %d curve(s) (%s)", label, st.mean * 1e9,
             np.nan_to_num(st.sem) * 1e9, np.nan_to_num(st.std) * 1e9, st.n_used, MEAN_RULE.split(",")[0])


def _figure_title(tip, interval, st) -> str:
    if st.n_used < 2 or not np.isfinite(st.sem):
        return f"{tip} {interval}: F_p = {st.mean * 1e9:.3g} nN from {st.n_used} curve (no scatter estimate)"
    return f"{tip} {interval}: F_p = {st.mean * 1e9:.3g} +- {st.sem * 1e9:.2g} nN (standard error, n={st.n_used})"


def _nan(row, attr):
    c = row["curve"]
    v = getattr(c, attr, None) if c is not None else None
    return np.nan if v is None else v


def _calibration_parts(cal: Calibration, inv: IntervalInvols):
    """(u_k_rel, u_invols_rel, u_factor_rel, factor, u_factor, corr) of F_p = k InvOLS delta_V.

    A tip-level InvOLS keeps its correlation with k (the reference-lever k uses the same
    hard-sample InvOLS); an interval's own InvOLS is independent of k."""
    u_k_rel = cal.u_k_rel
    if not np.isfinite(inv.value):
        return u_k_rel, np.nan, u_k_rel, np.nan, np.nan, np.nan
    u_inv_rel = inv.u / inv.value
    factor = cal.k * inv.value
    if inv.shared and np.isfinite(cal.factor):
        return u_k_rel, u_inv_rel, cal.u_factor_rel, cal.factor, cal.u_factor, cal.corr_k_invols
    u_rel = float(np.hypot(u_k_rel, u_inv_rel))
    return u_k_rel, u_inv_rel, u_rel, factor, factor * u_rel, 0.0


def _contact_columns(inv: IntervalInvols, rows) -> dict:
    """Per-row contact-slope InvOLS (rows without a curve: NaN, their read error)."""
    n = len(rows)
    out = {"invols": np.full(n, np.nan), "u": np.full(n, np.nan), "reason": [r["reason"] or "" for r in rows]}
    if inv.contact is None:
        return out
    by_file = {}
    for f, v, u, why in zip(inv.contact.files, inv.contact.invols, inv.contact.u_fit, inv.contact.reason):
        by_file.setdefault(f, []).append((v, u, why))
    for i, r in enumerate(rows):
        if r["curve"] is not None and by_file.get(r["file"]):
            out["invols"][i], out["u"][i], out["reason"][i] = by_file[r["file"]].pop(0)
    return out


def _volts_or_m(c, invols: float):
    """(deflection of the retract, to-metres factor, is_volts)."""
    if c.defl_units == "V" or c.invols is not None:
        if not np.isfinite(invols):
            raise CalibrationError(f"{c.path}: curve in volts but no InvOLS available")
        return c.deflection_volts("retract"), invols, True
    return c.defl_retract, 1.0, False


def _pulloff(c, reader, invols: float) -> dict:
    d, to_m, volts = _volts_or_m(c, invols)
    po = detect_pulloff(c.z_retract, d, path=c.path, baseline_gap=reader["baseline_gap"],
                        min_baseline_points=int(reader["min_baseline_points"]), method=reader["pulloff_method"],
                        fit_points=int(reader["pulloff_fit_points"]), min_snr=float(reader["min_pulloff_snr"]))
    return {"delta_V": po.delta if volts else np.nan, "delta_m": po.delta * to_m, "u_delta_m": po.u_delta * to_m,
            "delta_min_m": po.delta_min * to_m, "off": po.baseline.offset, "slope": po.baseline.slope,
            "noise": po.baseline.rms, "nb": po.n_baseline, "zpo": po.z_pulloff, "_po": po}


def _plot_item(r, k, invols, outlier):
    c = r["curve"]
    try:
        d, to_m, _ = _volts_or_m(c, invols)
    except CalibrationError:
        return {"x": np.zeros(0), "force": np.zeros(0), "baseline": None, "x_po": 0, "F_po": 0, "accepted": False, "outlier": False}
    fac = k * to_m
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
