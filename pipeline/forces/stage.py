"""Stage 3 entry point: force curves of one interval -> calibrated pull-off forces (HDF5 + PNG).

Statistical (scatter, F_p_sem) and calibration parts are separate: k is common to all
intervals of a tip; InvOLS is the interval's own (``pipeline.forces.invols``: the chip is
remounted after every TEM session) unless ``invols_shared``.  Warnings (an InvOLS that
disagrees with the contact slope, curves that give no contact slope, a fallback) go into the
file (``pipeline.forces.io``, its layout) and the log.
"""

from __future__ import annotations

import logging
from pathlib import Path

import numpy as np

from pipeline.forces.calibration import Calibration, calibrate
from pipeline.forces.errors import CalibrationError, ForceCurveError, ForcesStageError
from pipeline.forces.invols import IntervalInvols, resolve_interval_invols
from pipeline.forces.io import MEAN_RULE, CalibrationParts, IntervalForces, write_forces_h5
from pipeline.forces.pulloff import detect_pulloff
from pipeline.forces.reading import read_curves
from pipeline.forces.settings import CANTILEVER_DEFAULTS, READER_DEFAULTS, resolve_paths, with_defaults
from pipeline.forces.statistics import interval_stats

log = logging.getLogger(__name__)
# per-curve readings of the pull-off (keys of ``_pulloff``; NaN for rejected curves)
PULLOFF_COLUMNS = ("delta_V", "delta_m", "u_delta_m", "delta_min_m", "off", "slope", "noise", "nb", "zpo")


def _expand(paths, cfg):
    out = []
    for p in paths:
        p = Path(p)
        out.extend(resolve_paths(cfg, str(p)) if p.is_dir() else [p])
    return out


def run_forces(
    curve_paths,
    out_h5,
    out_png,
    *,
    cantilever: dict,
    reader: dict,
    tip="",
    interval="",
    interval_cfg: dict | None = None,
) -> None:
    """Analyse one interval's force curves; write ``out_h5`` and ``out_png`` atomically.

    ``cantilever``/``reader``: the SI-converted ``cantilever:``/``force_curves:`` sections
    (paths relative to their ``base_dir``); ``interval_cfg`` the interval's entry of the tip
    YAML (its own deflection_sensitivity / calibration_curves, if any).  Unreadable or
    unanalysable curves are rejected with a reason; raises :class:`ForcesStageError` (no
    output) when fewer than ``min_curves`` are accepted, :class:`CalibrationError` when k or
    the interval's InvOLS cannot be resolved.
    """
    reader, cant = _settings(reader, cantilever)
    label = f"tip {tip!r} interval {interval!r}"
    rows = _read_rows(_expand(curve_paths, reader), reader, label)
    curves = [r["curve"] for r in rows if r["curve"] is not None]
    cal = calibrate(cant, curves, reader)
    inv = resolve_interval_invols(cant, interval_cfg, curves, cal, reader=reader, label=label)
    warnings = [f"{label}: {w}" for w in inv.warnings] + ([f"{label}: {inv.check}"] if inv.check else [])
    for w in warnings:
        log.warning(w)
    accepted = _read_pulloffs(rows, reader, inv.value, label)
    col = _pulloff_columns(rows)
    F_p, u_F_stat = cal.k * col["delta_m"], cal.k * col["u_delta_m"]
    st = interval_stats(
        F_p, accepted, reader["outlier_z"], rule=reader["outlier_rule"], alpha=reader["outlier_alpha"], u=u_F_stat
    )
    used = accepted & ~st.outlier
    _log_decisions(label, rows, cal, inv, st, col)
    res = IntervalForces(
        tip=tip,
        interval=interval,
        reader=reader,
        cantilever=cant,
        warnings=warnings,
        files=[r["file"] for r in rows],
        reasons=[r["reason"] for r in rows],
        accepted=accepted,
        used=used,
        columns=col,
        F_p=F_p,
        u_F_p_stat=u_F_stat,
        file_k=[_nan(r, "spring_constant") for r in rows],
        file_invols=[_nan(r, "invols") for r in rows],
        contact=_contact_columns(inv, rows),
        stats=st,
        cal=cal,
        invols=inv,
        parts=calibration_parts(cal, inv),
    )
    with write_forces_h5(out_h5, res):  # the file appears only once the figure is written too
        from pipeline.forces.figures import plot_retracts  # matplotlib only where a figure is drawn

        plot_retracts(
            out_png,
            [_plot_item(r, cal.k, inv.value, st.outlier[i]) for i, r in enumerate(rows) if r["curve"] is not None],
            n_total=len(rows),
            title=_figure_title(tip, interval, st),
        )


def _settings(reader: dict, cantilever: dict) -> tuple[dict, dict]:
    """The reader and cantilever sections with their defaults and a shared base_dir; the reader
    gets the configured k and InvOLS, which undo the calibration of files that store forces."""
    reader = with_defaults(reader, READER_DEFAULTS)
    cant = with_defaults(cantilever, CANTILEVER_DEFAULTS)
    for a, b in ((reader, cant), (cant, reader)):
        if "base_dir" in b and "base_dir" not in a:
            a["base_dir"] = b["base_dir"]
    reader["instrument_spring_constant"] = cant.get("spring_constant")
    reader["instrument_deflection_sensitivity"] = cant.get("deflection_sensitivity")
    return reader, cant


def _read_rows(files, reader: dict, label: str) -> list:
    """One row per curve: dict(file, curve (None if unreadable), reason)."""
    if not files:
        raise ForcesStageError(f"{label}: no force-curve files given")
    rows = []
    for p in files:
        try:
            rows.extend({"file": c.path, "curve": c, "reason": ""} for c in read_curves(p, reader))
        except ForceCurveError as exc:
            rows.append({"file": str(p), "curve": None, "reason": exc.reason})
    if not any(r["curve"] is not None for r in rows):
        raise ForcesStageError(_all_rejected(label, rows))
    return rows


def _read_pulloffs(rows, reader: dict, invols: float, label: str) -> np.ndarray:
    """Read every curve's pull-off into its row (``po``, or the reason it has none); the mask of
    accepted curves.  Raises ForcesStageError when fewer than ``min_curves`` are accepted."""
    for r in rows:
        if r["curve"] is None:
            continue
        try:
            r["po"] = _pulloff(r["curve"], reader, invols)
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
            "force_curves.min_curves: 1 to accept it (no statistical uncertainty of F_p), no output written"
        )
    return accepted


def _pulloff_columns(rows) -> dict:
    """The pull-off readings as per-curve arrays (NaN for rejected curves)."""
    col = {k: np.full(len(rows), np.nan) for k in PULLOFF_COLUMNS}
    for i, r in enumerate(rows):
        if "po" in r and not r["reason"]:
            for k in PULLOFF_COLUMNS:
                col[k][i] = r["po"][k]
    return col


def _log_decisions(label, rows, cal, inv, st, col) -> None:
    """The stage's decisions in plain lines (the log is the lab notebook)."""
    log.info(
        "%s: k = %.4g N/m +- %.2g %% (%s); InvOLS = %.4g nm/V +- %.2g %% (%s)",
        label,
        cal.k,
        100 * cal.u_k_rel,
        cal.k_source,
        inv.value * 1e9,
        100 * inv.u / inv.value if inv.value else float("nan"),
        inv.source,
    )
    if inv.contact is not None and inv.contact.n:
        log.info(
            "%s: contact slopes of %d curve(s): InvOLS %.4g +- %.2g nm/V",
            label,
            inv.contact.n,
            inv.contact.mean * 1e9,
            inv.contact.u * 1e9,
        )
    for i, r in enumerate(rows):
        name = Path(r["file"]).name
        if r["reason"]:
            log.info("%s: curve %s rejected: %s", label, name, r["reason"])
        elif "po" in r:
            po = r["po"]["_po"]
            log.info(
                "%s: curve %s: Delta = %.4g nm +- %.2g (%s)%s, weight %.3f",
                label,
                name,
                col["delta_m"][i] * 1e9,
                col["u_delta_m"][i] * 1e9,
                po.shape,
                "; outlier, not averaged" if st.outlier[i] else "",
                st.weight[i],
            )
    log.info(
        "%s: F_p = %.4g nN, standard error %.2g nN, SD %.2g nN over %d curve(s) (%s)",
        label,
        st.mean * 1e9,
        np.nan_to_num(st.sem) * 1e9,
        np.nan_to_num(st.std) * 1e9,
        st.n_used,
        MEAN_RULE.split(",")[0],
    )


def _figure_title(tip, interval, st) -> str:
    if st.n_used < 2 or not np.isfinite(st.sem):
        return f"{tip} {interval}: F_p = {st.mean * 1e9:.3g} nN from {st.n_used} curve (no scatter estimate)"
    return f"{tip} {interval}: F_p = {st.mean * 1e9:.3g} +- {st.sem * 1e9:.2g} nN (standard error, n={st.n_used})"


def _nan(row, attr):
    c = row["curve"]
    v = getattr(c, attr, None) if c is not None else None
    return np.nan if v is None else v


def calibration_parts(cal: Calibration, inv: IntervalInvols) -> CalibrationParts:
    """Relative uncertainties of F_p = k InvOLS delta_V and the factor k InvOLS.

    A tip-level InvOLS keeps its correlation with k (the reference-lever k uses the same
    hard-sample InvOLS); an interval's own InvOLS is independent of k."""
    u_k_rel = cal.u_k_rel
    if not np.isfinite(inv.value):
        return CalibrationParts(u_k_rel, np.nan, u_k_rel, np.nan, np.nan, np.nan)
    u_inv_rel = inv.u / inv.value
    factor = cal.k * inv.value
    if inv.shared and np.isfinite(cal.factor):
        return CalibrationParts(u_k_rel, u_inv_rel, cal.u_factor_rel, cal.factor, cal.u_factor, cal.corr_k_invols)
    u_rel = float(np.hypot(u_k_rel, u_inv_rel))
    return CalibrationParts(u_k_rel, u_inv_rel, u_rel, factor, factor * u_rel, 0.0)


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
    po = detect_pulloff(
        c.z_retract,
        d,
        path=c.path,
        baseline_gap=reader["baseline_gap"],
        min_baseline_points=int(reader["min_baseline_points"]),
        method=reader["pulloff_method"],
        fit_points=int(reader["pulloff_fit_points"]),
        min_snr=float(reader["min_pulloff_snr"]),
    )
    return {
        "delta_V": po.delta if volts else np.nan,
        "delta_m": po.delta * to_m,
        "u_delta_m": po.u_delta * to_m,
        "delta_min_m": po.delta_min * to_m,
        "off": po.baseline.offset,
        "slope": po.baseline.slope,
        "noise": po.baseline.rms,
        "nb": po.n_baseline,
        "zpo": po.z_pulloff,
        "_po": po,
    }


def _plot_item(r, k, invols, outlier):
    c = r["curve"]
    try:
        d, to_m, _ = _volts_or_m(c, invols)
    except CalibrationError:
        return {
            "x": np.zeros(0),
            "force": np.zeros(0),
            "baseline": None,
            "x_po": 0,
            "F_po": 0,
            "accepted": False,
            "outlier": False,
        }
    fac = k * to_m
    po = r.get("_po") or (r.get("po") or {}).get("_po")
    if po is None or r["reason"]:
        x = c.z_retract.max() - c.z_retract
        return {
            "x": x,
            "force": fac * (d - np.median(d[-max(10, d.size // 5) :])),
            "baseline": None,
            "x_po": 0,
            "F_po": 0,
            "accepted": False,
            "outlier": False,
        }
    x = po.z_pulloff - c.z_retract
    ref = po.baseline(po.z_pulloff)
    return {
        "x": x,
        "force": fac * (d - ref),
        "baseline": fac * (po.baseline(c.z_retract) - ref),
        "x_po": 0.0,
        "F_po": -fac * po.delta,
        "accepted": True,
        "outlier": bool(outlier),
    }


def _all_rejected(label, rows) -> str:
    lines = "\n".join(f"  {r['file']}: {r['reason']}" for r in rows)
    return f"{label}: all {len(rows)} force curves were rejected, no output written:\n{lines}"


__all__ = ["run_forces", "CalibrationError", "ForcesStageError", "CANTILEVER_DEFAULTS"]
