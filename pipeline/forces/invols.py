"""Deflection sensitivity (InvOLS, m/V) of one interval, and the check that catches a forgotten remount.

In a TEM wear test the cantilever chip is taken out of the AFM after every wear interval,
imaged, and mounted again; the laser spot moves on the lever and InvOLS changes by several
per cent between intervals, while the spring constant k (a property of the lever) stays.  The
counter-surface is hard (DLC, Si, sapphire: contact stiffness hundreds of N/m against a lever of
0.1-50 N/m), so the contact part of every force curve is itself an InvOLS measurement: its slope
in V/m is 1/InvOLS (1 + k/k_contact), i.e. 1/InvOLS to well below 1 %.

Sources (``cantilever.deflection_sensitivity_method``):

* ``auto`` (default): per interval, the interval's own ``deflection_sensitivity`` > its
  ``calibration_curves`` > the InvOLS stored in its force-curve files (the instrument's
  calibration at that mounting) > ``contact`` (its own force curves) > the tip-level value if
  ``contact_fallback: tip``;
* ``contact``: the contact slope of each of the interval's curves (``contact_segment``, approach
  by default); InvOLS = mean of the per-curve values, u = their standard error with the
  systematic floor ``contact_invols_floor`` (relative) in quadrature;
* ``interval_curves``: the same on the interval's ``calibration_curves`` (a hard calibration
  sample measured at that mounting);
* ``interval_given``: the interval's ``deflection_sensitivity`` (+ ``_uncertainty``);
* ``given`` / ``hard_sample`` / ``file``: one value for the whole tip (``calibration.calibrate``),
  for setups that are never remounted; drawn once per tip in the Monte Carlo.

Whatever the source, the contact slope of the interval's own curves is measured and recorded
(``contact_slope.contact_slope``, which says why a curve gives none); where it differs from the
InvOLS in use by more than ``invols_check_sigma`` combined standard uncertainties, the interval is flagged in
words.  A curve whose contact part is too short or not
linear cannot give InvOLS; the reason is recorded, and if no curve of the interval gives one the
interval falls back to the tip-level value (``contact_fallback: tip``) or fails naming the
interval and the setting (``fail``, the default).
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from pipeline.forces.contact_slope import contact_slope
from pipeline.forces.curve import ForceCurve
from pipeline.forces.errors import CalibrationError, ForceCurveError
from pipeline.forces.settings import resolve_paths

PER_INTERVAL_METHODS = ("auto", "contact", "interval_curves", "interval_given", "interval_file")
TIP_METHODS = ("given", "hard_sample", "file")


@dataclass
class ContactInvols:
    """Per-curve InvOLS from contact slopes (NaN with a reason where a curve gives none)."""

    files: list
    invols: np.ndarray  # m/V per curve
    u_fit: np.ndarray  # m/V, fit standard error per curve
    reason: list  # '' where the curve gave a value
    floor: float  # relative systematic uncertainty
    fit_range_V: np.ndarray = field(
        default_factory=lambda: np.zeros((0, 2))
    )  # per curve: deflection (V) at the ends of the fit

    @property
    def fit_range_m(self) -> np.ndarray:
        """Mean deflection above the baseline (m) at the two ends of the contact fit (the load
        range the slope was measured over; ``contact_compliance`` needs it)."""
        ok = self.ok & np.all(np.isfinite(self.fit_range_V), axis=1) if self.fit_range_V.size else self.ok[:0]
        if not np.any(ok):
            return np.full(2, np.nan)
        return np.mean(self.fit_range_V[ok] * self.invols[ok, None], axis=0)

    @property
    def ok(self) -> np.ndarray:
        return np.isfinite(self.invols)

    @property
    def n(self) -> int:
        return int(self.ok.sum())

    @property
    def mean(self) -> float:
        return float(np.mean(self.invols[self.ok])) if self.n else np.nan

    @property
    def u(self) -> float:
        """Standard error of the mean (fit error for one curve) with the floor in quadrature."""
        v = self.invols[self.ok]
        if v.size == 0:
            return np.nan
        stat = v.std(ddof=1) / np.sqrt(v.size) if v.size > 1 else float(self.u_fit[self.ok][0])
        return float(np.hypot(stat, self.floor * v.mean()))


@dataclass
class IntervalInvols:
    """The InvOLS used for one interval, where it came from, and the contact-slope check."""

    value: float  # m/V (NaN: deflection recorded in metres, no InvOLS needed)
    u: float  # m/V, 1 sigma
    method: str
    source: str  # in words
    shared: bool  # one value for the whole tip (its error is common to all intervals)
    contact: ContactInvols | None = None
    check: str = ""  # '' or a sentence saying what disagrees
    check_z: float = np.nan  # (value - contact) / combined u
    warnings: list = field(default_factory=list)


def measure_contact_invols(
    curves: list[ForceCurve], *, fit_range=(0.2, 0.8), segment="approach", floor=0.005
) -> ContactInvols:
    """Contact-slope InvOLS of every curve: in volts as recorded, or converted back to volts with
    the file's own InvOLS (instrument files in metres: a stale file InvOLS is then caught);
    curves in metres without one are skipped with the reason."""
    files, vals, us, reasons, ranges = [], [], [], [], []
    for c in curves:
        files.append(c.path)
        ranges.append((np.nan, np.nan))
        if c.defl_units != "V" and c.invols is None:
            (
                vals.append(np.nan),
                us.append(np.nan),
                reasons.append("deflection recorded in metres with no InvOLS in the file"),
            )
            continue
        z = c.z_approach if segment == "approach" else c.z_retract
        try:
            cs = contact_slope(z, c.deflection_volts(segment), fit_range=fit_range, path=c.path)
            vals.append(cs.invols), us.append(cs.u_invols), reasons.append("")
            ranges[-1] = (cs.fit_lo, cs.fit_hi)
        except ForceCurveError as exc:
            vals.append(np.nan), us.append(np.nan), reasons.append(exc.reason)
    return ContactInvols(
        files, np.array(vals, float), np.array(us, float), reasons, float(floor), np.array(ranges, float).reshape(-1, 2)
    )


def _method(cant: dict, interval: dict, file_invols) -> str:
    m = cant["deflection_sensitivity_method"]
    if m != "auto":
        return m
    if "deflection_sensitivity" in interval:
        return "interval_given"
    if "calibration_curves" in interval:
        return "interval_curves"
    return "interval_file" if file_invols is not None else "contact"


def _file_invols(curves: list[ForceCurve], label: str):
    """The InvOLS stored in the interval's files (None if none; an error if they differ)."""
    vals = np.array([c.invols for c in curves if c.invols is not None], float)
    if vals.size == 0:
        return None
    if np.ptp(vals) > 1e-6 * abs(vals.mean()):
        raise CalibrationError(
            f"{label}: the curve files store different InvOLS values ({vals.min():.6g} .. {vals.max():.6g} m/V); "
            "give intervals[].deflection_sensitivity for this interval"
        )
    return float(vals[0])


def _contact_reasons(ci: ContactInvols, most=3) -> str:
    bad = [(f, r) for f, r in zip(ci.files, ci.reason) if r]
    txt = "; ".join(f"{f}: {r}" for f, r in bad[:most])
    return txt + (f"; and {len(bad) - most} more" if len(bad) > most else "")


def resolve_interval_invols(
    cant: dict, interval: dict, curves: list[ForceCurve], tip_cal, *, reader: dict, label: str
) -> IntervalInvols:
    """The InvOLS to use for one interval (module doc); ``tip_cal`` is the tip-level
    :class:`~pipeline.forces.calibration.Calibration` (its ``invols`` NaN where none is configured)."""
    interval = interval or {}
    fit_range = tuple(cant["contact_fit_range"])
    seg = cant["contact_segment"]
    floor = float(cant["contact_invols_floor"])
    contact = measure_contact_invols(curves, fit_range=fit_range, segment=seg, floor=floor)
    file_invols = _file_invols(curves, label)
    method = _method(cant, interval, file_invols)
    in_volts = any(c.defl_units == "V" or c.invols is not None for c in curves)
    if method in TIP_METHODS:
        res = _tip_value(tip_cal, in_volts, contact, label)
    elif method == "interval_file":
        res = _from_interval_file(file_invols, cant, contact, label)
    elif method == "interval_given":
        res = _from_interval_given(interval, contact, label)
    elif method == "interval_curves":
        if "calibration_curves" not in interval:
            raise CalibrationError(
                f"{label}: deflection_sensitivity_method 'interval_curves' needs intervals[].calibration_curves"
            )
        res = _from_calibration_curves(cant, interval, reader, fit_range, seg, floor, contact, label)
    elif method == "contact":
        res = _from_contact(contact, len(curves), tip_cal, cant, in_volts, label)
    else:
        raise CalibrationError(f"{label}: unknown deflection_sensitivity_method {method!r}")
    _check(res, float(cant["invols_check_sigma"]))
    return res


def _tip_value(tip_cal, in_volts: bool, contact, label: str) -> IntervalInvols:
    """The tip-level InvOLS (shared by the intervals); none needed for curves in metres."""
    if not np.isfinite(tip_cal.invols):
        if not in_volts:
            return IntervalInvols(
                np.nan, np.nan, "none", "not used: deflection recorded in metres by the instrument", True, contact
            )
        raise CalibrationError(
            f"{label}: no deflection sensitivity (InvOLS); give cantilever.deflection_sensitivity or "
            "hard_sample_curves (one value for the tip), or intervals[].deflection_sensitivity / calibration_curves"
        )
    return IntervalInvols(tip_cal.invols, tip_cal.u_invols, tip_cal.invols_method, tip_cal.invols_source, True, contact)


def _from_interval_file(file_invols, cant, contact, label: str) -> IntervalInvols:
    if file_invols is None:
        raise CalibrationError(
            f"{label}: deflection_sensitivity_method 'interval_file' but the interval's curve files store no InvOLS"
        )
    u = float(cant.get("deflection_sensitivity_uncertainty", 0.0))
    return IntervalInvols(
        file_invols,
        u,
        "interval_file",
        "InvOLS stored in the interval's force-curve files (the instrument's calibration at this "
        "mounting)" + ("" if u else "; uncertainty unknown: 0"),
        False,
        contact,
    )


def _from_interval_given(interval, contact, label: str) -> IntervalInvols:
    if "deflection_sensitivity" not in interval:
        raise CalibrationError(
            f"{label}: deflection_sensitivity_method 'interval_given' needs intervals[].deflection_sensitivity"
        )
    u = float(interval.get("deflection_sensitivity_uncertainty", 0.0))
    if not (float(interval["deflection_sensitivity"]) > 0 and u >= 0):
        raise CalibrationError(
            f"{label}: intervals[].deflection_sensitivity must be positive and its uncertainty "
            f">= 0 (got {interval['deflection_sensitivity']:g} +- {u:g} m/V)"
        )
    return IntervalInvols(
        float(interval["deflection_sensitivity"]),
        u,
        "interval_given",
        "intervals[].deflection_sensitivity of the tip YAML" + ("" if u else " (no uncertainty given: 0)"),
        False,
        contact,
    )


def _from_contact(contact, n_curves: int, tip_cal, cant, in_volts: bool, label: str) -> IntervalInvols:
    """The interval's own contact slopes; without any, the tip's InvOLS where allowed."""
    if contact.n:
        src = (
            f"contact slope ({cant['contact_segment']}) of {contact.n} of the interval's {n_curves} curves on the "
            f"counter-surface, u = SEM with a {100 * contact.floor:g} % floor"
        )
        if np.isfinite(tip_cal.invols):
            src += (
                f"; the tip-level InvOLS of the calibration session ({tip_cal.invols * 1e9:.4g} nm/V) differs by "
                f"{100 * (tip_cal.invols / contact.mean - 1):+.1f} % "
                "(not used: the chip is remounted for every interval)"
            )
        res = IntervalInvols(contact.mean, contact.u, "contact", src, False, contact)
        if contact.n < n_curves:
            res.warnings.append(f"{n_curves - contact.n} curve(s) gave no contact slope ({_contact_reasons(contact)})")
        return res
    if not in_volts:
        return _tip_value(tip_cal, in_volts, contact, label)
    if np.isfinite(tip_cal.invols) and cant["contact_fallback"] == "tip":
        res = _tip_value(tip_cal, in_volts, contact, label)
        res.warnings.append(
            f"no curve of the interval gives a contact slope ({_contact_reasons(contact)}); "
            f"the tip-level InvOLS {tip_cal.invols * 1e9:.4g} nm/V is used (cantilever.contact_fallback: tip)"
        )
        return res
    raise CalibrationError(
        f"{label}: no curve gives an InvOLS from its contact part ({_contact_reasons(contact)}); give "
        "intervals[].deflection_sensitivity or calibration_curves for this interval, or set "
        "cantilever.contact_fallback: tip to use the tip-level InvOLS"
    )


def _from_calibration_curves(cant, interval, reader, fit_range, seg, floor, contact, label) -> IntervalInvols:
    from pipeline.forces.reading import read_curves

    files = resolve_paths(cant, interval["calibration_curves"])
    if not files:
        raise CalibrationError(
            f"{label}: intervals[].calibration_curves: no files match {interval['calibration_curves']!r}"
        )
    curves = []
    try:
        for p in files:
            curves.extend(read_curves(p, reader))
    except ForceCurveError as exc:
        raise CalibrationError(f"{label}: intervals[].calibration_curves: {exc}") from None
    cal = measure_contact_invols(curves, fit_range=fit_range, segment=seg, floor=floor)
    if not cal.n:
        raise CalibrationError(
            f"{label}: intervals[].calibration_curves give no contact slope ({_contact_reasons(cal)})"
        )
    res = IntervalInvols(
        cal.mean,
        cal.u,
        "interval_curves",
        f"contact slope of {cal.n} calibration curve(s) in {interval['calibration_curves']}, u = SEM "
        f"with a {100 * floor:g} % floor",
        False,
        contact,
    )
    if cal.n < len(curves):
        res.warnings.append(
            f"{len(curves) - cal.n} calibration curve(s) gave no contact slope ({_contact_reasons(cal)})"
        )
    return res


def _check(res: IntervalInvols, n_sigma: float) -> None:
    """Compare the InvOLS in use with the interval's own contact slope (a forgotten remount)."""
    ci = res.contact
    if res.method == "contact" or ci is None or not ci.n or not np.isfinite(res.value):
        return
    diff = res.value - ci.mean
    comb = float(np.hypot(np.nan_to_num(res.u), ci.u))
    res.check_z = diff / comb if comb > 0 else np.inf
    if abs(res.check_z) > n_sigma:
        res.check = (
            f"InvOLS in use ({res.method}) {res.value * 1e9:.4g} nm/V differs from this interval's contact slope "
            f"{ci.mean * 1e9:.4g} +- {ci.u * 1e9:.2g} nm/V by {100 * diff / ci.mean:+.1f} % "
            f"({res.check_z:+.1f} sigma): either the InvOLS was not measured again after the chip was remounted "
            f"(F_p scales with it), or the counter-surface is not hard (then its contact slope is no InvOLS)"
        )
