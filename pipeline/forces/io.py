"""The stage-3 forces file of one interval: its writer and its reader (the only place the layout
is spelled).

HDF5 layout (every dataset has ``units``):

/curves/     per curve (n = curves found, maps count each curve): file, accepted,
             rejection_reason, outlier, used, weight, modified_z, delta_V, delta_m, u_delta_m,
             delta_min_m, F_p, u_F_p_stat, baseline_offset, baseline_slope,
             baseline_noise, n_baseline, z_pulloff, spring_constant_file, invols_file, and the
             contact slope measured on every curve whatever the InvOLS source (invols_contact,
             u_invols_contact_fit, invols_contact_reason)
/interval/   F_p_mean, F_p_std, F_p_sem, F_p_median, n_curves_used, n_curves_total,
             n_curves_rejected, n_outliers, F_p_tau, delta_V_mean, delta_m_mean,
             u_F_p_calibration, u_F_p_calibration_rel, u_F_p_total;
             ``calibration`` is a soft link to /calibration
/calibration/ k, u_k, invols, u_invols (this interval's), factor (k*InvOLS), u_factor,
             u_factor_rel, u_k_rel, u_invols_rel, corr_k_invols, k_method, invols_method,
             invols_shared (one InvOLS for the whole tip), invols_tip, u_invols_tip (the
             calibration session's, NaN if none), the contact-slope check (invols_contact,
             u_invols_contact, n_invols_contact, contact_fit_deflection, contact_segment,
             invols_check_z, invols_check), k_source, invols_source and a subgroup per method
             used (hard_sample, reference_curves, reference_lever, thermal)

Root attributes: tip, interval, outlier_rule, mean_rule, reader_config, cantilever_config and
``warnings`` (an InvOLS that disagrees with the contact slope, curves that give no contact
slope, a fallback).
"""

from __future__ import annotations

import contextlib
from dataclasses import dataclass
from typing import TYPE_CHECKING

import h5py
import numpy as np

from pipeline.h5io import atomic_h5, create_group, read_attr_json, read_value, require_group, write_dataset

if TYPE_CHECKING:  # the stage's types; the reader (stage 4) needs none of the stage's science
    from pipeline.forces.calibration import Calibration
    from pipeline.forces.invols import IntervalInvols
    from pipeline.forces.statistics import IntervalStats

OUTLIER_RULES = {
    "esd": "generalized ESD test (Rosner 1983) at significance outlier_alpha "
    "over accepted curves, up to floor(n/3) outliers (none if n < 3)",
    "modified_z": "modified z-score 0.6745 |x - median| / MAD > outlier_z "
    "over accepted curves (none flagged if n < 3 or MAD = 0)",
}
MEAN_RULE = (
    "random-effects weighted mean over accepted non-outlier curves, weights 1/(u_i^2 + tau^2) with tau the "
    "between-curve scatter (DerSimonian-Laird; the plain mean for equal u_i); sem: modified Knapp-Hartung"
)


@dataclass
class CalibrationParts:
    """Relative uncertainties of F_p = k InvOLS delta_V and the factor k InvOLS (N/V)."""

    u_k_rel: float
    u_invols_rel: float
    u_factor_rel: float
    factor: float
    u_factor: float
    corr_k_invols: float


@dataclass
class IntervalForces:
    """What stage 3 found for one interval, as the forces file stores it (SI)."""

    tip: str
    interval: str
    reader: dict
    cantilever: dict
    warnings: list
    files: list  # per curve (a map's i-th curve: "file#i")
    reasons: list  # per curve: why it was rejected ('' if accepted)
    accepted: np.ndarray
    used: np.ndarray
    columns: dict  # per-curve pull-off readings (delta_V, delta_m, ..., see _write_curves)
    F_p: np.ndarray
    u_F_p_stat: np.ndarray
    file_k: list  # k stored in each curve's file (NaN if none)
    file_invols: list
    contact: dict  # per-curve contact-slope InvOLS: invols, u, reason
    stats: IntervalStats
    cal: Calibration
    invols: IntervalInvols
    parts: CalibrationParts


@contextlib.contextmanager
def write_forces_h5(out_h5, res: IntervalForces):
    """Write the forces file; it appears at ``out_h5`` only when the ``with`` block (the stage's
    figure) ends without an error, so a failed stage leaves nothing that looks complete."""
    rule = OUTLIER_RULES[res.reader["outlier_rule"]]
    with atomic_h5(
        out_h5,
        stage="forces",
        tip=res.tip,
        interval=res.interval,
        outlier_rule=rule,
        mean_rule=MEAN_RULE,
        reader_config=dict(res.reader),
        cantilever_config=dict(res.cantilever),
        warnings=res.warnings,
    ) as f:
        _write_curves(f, res)
        _write_calibration(f, res)
        _write_interval(f, res)
        yield f


def _write_curves(f, res: IntervalForces) -> None:
    g = create_group(f, "curves", "NXcollection")
    col, st = res.columns, res.stats
    write_dataset(g, "file", res.files, "1", "curve file (#i: i-th curve of a map)")
    write_dataset(g, "accepted", res.accepted, "1", "curve passed reading and pull-off detection")
    write_dataset(g, "rejection_reason", res.reasons, "1", "why the curve was rejected ('' if accepted)")
    write_dataset(g, "outlier", st.outlier, "1", "flagged by the outlier rule (kept, not averaged)")
    write_dataset(g, "used", res.used, "1", "accepted and not an outlier: enters the interval mean")
    write_dataset(g, "weight", st.weight, "1", "relative weight of the curve in the interval mean (0: not used)")
    write_dataset(g, "modified_z", st.modified_z, "1", "modified z-score of F_p (NaN if rejected)")
    write_dataset(
        g, "delta_V", col["delta_V"], "V", "max adhesive deflection Delta in volts (NaN if not recorded in V)"
    )
    write_dataset(g, "delta_m", col["delta_m"], "m", "Delta in metres (= delta_V * InvOLS)")
    write_dataset(g, "u_delta_m", col["u_delta_m"], "m", "statistical uncertainty of Delta (noise + sampling step)")
    write_dataset(
        g, "delta_min_m", col["delta_min_m"], "m", "raw minimum of the baseline-corrected retract (cross-check)"
    )
    write_dataset(g, "F_p", res.F_p, "N", "pull-off force k * Delta")
    write_dataset(
        g, "u_F_p_stat", res.u_F_p_stat, "N", "statistical uncertainty of F_p of the curve (calibration excluded)"
    )
    bu = "V" if np.isfinite(res.invols.value) else "m"
    write_dataset(g, "baseline_offset", col["off"], bu, "baseline offset at z = 0 (retract free part)")
    write_dataset(g, "baseline_slope", col["slope"], f"{bu}/m", "baseline tilt per m of piezo extension")
    write_dataset(g, "baseline_noise", col["noise"], bu, "rms of the baseline residuals")
    write_dataset(g, "n_baseline", col["nb"], "1", "points in the baseline fit")
    write_dataset(g, "z_pulloff", col["zpo"], "m", "piezo extension at the jump-off")
    write_dataset(g, "spring_constant_file", res.file_k, "N/m", "k stored in the file (NaN if none)")
    write_dataset(g, "invols_file", res.file_invols, "m/V", "InvOLS stored in the file (NaN if none)")
    write_dataset(
        g,
        "invols_contact",
        res.contact["invols"],
        "m/V",
        "InvOLS from this curve's contact slope (NaN: see the reason)",
    )
    write_dataset(g, "u_invols_contact_fit", res.contact["u"], "m/V", "fit standard error of that InvOLS")
    write_dataset(
        g, "invols_contact_reason", res.contact["reason"], "1", "why the curve gives no contact slope ('' if it does)"
    )


def _write_calibration(f, res: IntervalForces) -> None:
    cal, inv, p = res.cal, res.invols, res.parts
    contact = inv.contact
    c = create_group(f, "calibration", "NXcollection")
    for name, val, unit, desc in (
        ("k", cal.k, "N/m", "spring constant used"),
        ("u_k", cal.u_k, "N/m", "1-sigma uncertainty of k"),
        ("invols", inv.value, "m/V", "deflection sensitivity used for this interval (NaN: deflection recorded in m)"),
        ("u_invols", inv.u, "m/V", "1-sigma uncertainty of InvOLS"),
        ("factor", p.factor, "N/V", "k * InvOLS: F_p = factor * delta_V"),
        ("u_factor", p.u_factor, "N/V", "1-sigma uncertainty of k * InvOLS (correlations included)"),
        ("u_factor_rel", p.u_factor_rel, "1", "relative calibration uncertainty of F_p"),
        ("u_k_rel", p.u_k_rel, "1", "relative uncertainty of k (common to all intervals of the tip)"),
        (
            "u_invols_rel",
            p.u_invols_rel,
            "1",
            "relative uncertainty of this interval's InvOLS (its own unless invols_shared)",
        ),
        ("corr_k_invols", p.corr_k_invols, "1", "correlation coefficient of k and InvOLS"),
        ("k_method", cal.k_method, "1", "given | file | reference_lever | thermal"),
        (
            "invols_method",
            inv.method,
            "1",
            "contact | interval_curves | interval_given | given | hard_sample | file | none",
        ),
        ("invols_shared", inv.shared, "1", "one InvOLS for the whole tip (its error common to all intervals)"),
        ("invols_tip", cal.invols, "m/V", "tip-level InvOLS of the calibration session (NaN if none)"),
        ("u_invols_tip", cal.u_invols, "m/V", "its 1-sigma uncertainty"),
        (
            "invols_contact",
            contact.mean if contact else np.nan,
            "m/V",
            "InvOLS from the contact slopes of this interval's own curves (mean)",
        ),
        ("u_invols_contact", contact.u if contact else np.nan, "m/V", "its standard error with the systematic floor"),
        ("n_invols_contact", contact.n if contact else 0, "1", "curves that gave a contact slope"),
        (
            "contact_fit_deflection",
            contact.fit_range_m if contact else np.full(2, np.nan),
            "m",
            "mean deflection above the baseline at the two ends of the contact-slope fit (its load range: "
            "the inversion corrects a contact InvOLS for the tip's finite contact stiffness over it)",
        ),
        ("contact_segment", str(res.cantilever["contact_segment"]), "1", "segment the contact slopes were fitted on"),
        ("invols_check_z", inv.check_z, "1", "(InvOLS in use - contact) / combined uncertainty (NaN: not checked)"),
        ("invols_check", inv.check, "1", "'' or what disagrees (a forgotten remount)"),
        ("k_source", cal.k_source, "1", "where k came from"),
        ("invols_source", inv.source, "1", "where InvOLS came from"),
    ):
        write_dataset(c, name, val, unit, desc)
    for gname, items in cal.details.items():
        sub = create_group(c, gname, "NXcollection")
        for name, (val, unit, desc) in items.items():
            write_dataset(sub, name, val, unit, desc)


def _write_interval(f, res: IntervalForces) -> None:
    st, used, col = res.stats, res.used, res.columns
    u_cal_rel = res.parts.u_factor_rel
    iv = create_group(
        f, "interval", "NXcollection", outlier_rule=OUTLIER_RULES[res.reader["outlier_rule"]], mean_rule=MEAN_RULE
    )
    for name, val, unit, desc in (
        ("F_p_mean", st.mean, "N", MEAN_RULE),
        ("F_p_std", st.std, "N", "standard deviation (ddof=1; NaN if 1 curve)"),
        ("F_p_sem", st.sem, "N", "standard error of the mean (statistical part)"),
        ("F_p_median", st.median, "N", "median of used curves"),
        ("n_curves_used", st.n_used, "1", "curves in the mean"),
        ("n_curves_total", len(res.files), "1", "curves found"),
        ("n_curves_rejected", int((~res.accepted).sum()), "1", "rejected curves (see curves/rejection_reason)"),
        ("n_outliers", int(st.outlier.sum()), "1", "accepted curves flagged as outliers"),
        ("F_p_tau", st.tau, "N", "between-curve scatter of F_p beyond the curves' own uncertainties (random effects)"),
        (
            "delta_V_mean",
            float(np.sum(st.weight[used] * col["delta_V"][used])),
            "V",
            "weighted mean Delta of used curves (V)",
        ),
        (
            "delta_m_mean",
            float(np.sum(st.weight[used] * col["delta_m"][used])),
            "m",
            "weighted mean Delta of used curves (m)",
        ),
        (
            "u_F_p_calibration",
            st.mean * u_cal_rel,
            "N",
            "calibration part (k common to the tip; InvOLS the interval's own unless shared)",
        ),
        ("u_F_p_calibration_rel", u_cal_rel, "1", "relative calibration uncertainty"),
        (
            "u_F_p_total",
            float(np.hypot(np.nan_to_num(st.sem), st.mean * u_cal_rel)),
            "N",
            "sqrt(sem^2 + calibration^2)",
        ),
    ):
        write_dataset(iv, name, val, unit, desc)
    iv["calibration"] = h5py.SoftLink("/calibration")


# ------------------------------------------------------------------------------ reading
def load_forces(path) -> dict:
    """Read the stage-3 pull-off forces of one interval (SI).

    Returns F_p_mean, F_p_std, F_p_sem, n_curves (N), F_p_curves, accepted (per curve, may be
    empty), the calibration k, u_k (N/m), invols, u_invols (m/V), u_cal_rel (the relative
    uncertainty of k * InvOLS with their correlation, NaN if the file has none), where the
    InvOLS came from and its contact-slope check, and the file's warnings.
    """
    with h5py.File(path, "r") as f:
        out = _read_interval(f)
        cal = _read_calibration(f)
        warnings = list(read_attr_json(f, "warnings")) if "warnings" in f.attrs else []
    u_cal_rel, u_factor_rel = out.pop("u_cal_rel"), cal.pop("u_factor_rel")
    if u_cal_rel is None:  # the interval's relative calibration uncertainty, else the calibration group's
        u_cal_rel = u_factor_rel
    return {**out, **cal, "u_cal_rel": float(u_cal_rel) if u_cal_rel is not None else np.nan, "warnings": warnings}


def _read_interval(f) -> dict:
    g = require_group(f, "interval")
    fp_mean = float(read_value(g, "F_p_mean", required=True))
    n_curves = int(read_value(g, "n_curves_used", read_value(g, "n_curves", 0)))
    fp_std = read_value(g, "F_p_std")
    fp_sem = read_value(g, "F_p_sem")
    gc = f["curves"] if "curves" in f else g  # per-curve data (stage 3: group "curves")
    fp_curves = np.atleast_1d(np.asarray(read_value(gc, "F_p", np.array([])), dtype=float))
    accepted = read_value(gc, "used", read_value(gc, "accepted", None))
    if accepted is None:
        outlier = read_value(gc, "outlier", None)
        accepted = (~np.asarray(outlier, dtype=bool)) if outlier is not None else np.ones(fp_curves.shape, bool)
    accepted = np.atleast_1d(np.asarray(accepted, dtype=bool))
    if fp_std is None and fp_curves.size > 1:
        fp_std = float(np.std(fp_curves[accepted], ddof=1))
    fp_std = float(fp_std) if fp_std is not None else np.nan
    if fp_sem is None:
        fp_sem = fp_std / np.sqrt(n_curves) if n_curves > 0 else np.nan
    return {
        "F_p_mean": fp_mean,
        "F_p_std": fp_std,
        "F_p_sem": float(fp_sem),
        "n_curves": n_curves,
        "F_p_curves": fp_curves,
        "accepted": accepted,
        "u_cal_rel": read_value(g, "u_F_p_calibration_rel", None),
    }


def _read_calibration(f) -> dict:
    """The calibration group; the values of a file without one are those of a file written before
    InvOLS was per interval (one value for the whole tip)."""
    cal = f["calibration"] if "calibration" in f else None

    def get(name, default):
        return default if cal is None else read_value(cal, name, default)

    return {
        "k": float(get("k", np.nan)),
        "u_k": float(get("u_k", 0.0)),
        "invols": float(get("invols", np.nan)),
        "u_invols": float(get("u_invols", 0.0)),
        "u_factor_rel": get("u_factor_rel", None),
        "invols_shared": bool(get("invols_shared", True)),
        "invols_method": str(get("invols_method", "")),
        "contact_fit_deflection": np.asarray(get("contact_fit_deflection", np.full(2, np.nan)), float),
        "contact_segment": str(get("contact_segment", "approach")),
        "invols_check": str(get("invols_check", "")),
        "invols_contact": float(get("invols_contact", np.nan)),
        "u_invols_contact": float(get("u_invols_contact", np.nan)),
    }
