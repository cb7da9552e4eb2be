"""Deflection sensitivity (InvOLS, m/V) from the contact slope of curves on a hard sample."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from pipeline.forces.baseline import fit_line
from pipeline.forces.curve import ForceCurve
from pipeline.forces.errors import ForceCurveError


@dataclass
class ContactSlope:
    invols: float  # m/V
    u_invols: float  # m/V, from the fit
    slope: float  # V/m
    n_points: int
    fit_lo: float = float("nan")  # deflection above the baseline (V) at the lower end of the fit range
    fit_hi: float = float("nan")  # ... and at its upper end


MIN_CONTACT_POINTS = 10
MAX_NONLINEARITY = 0.10  # relative slope change between the two halves of the contact fit range
NONLINEARITY_SIGMA = 4.5  # ... and in combined standard errors (3 sigma: 7 false alarms in 6400 linear curves)


def contact_slope(z, d, *, fit_range=(0.2, 0.8), path="") -> ContactSlope:
    """Slope of deflection (V) vs extension z (m) over the contact part of one segment.

    The baseline is fitted on the 30 % of the z range farthest from the sample; the fit uses the
    contiguous contact run next to the turnaround where the deflection above baseline lies
    between ``fit_range`` fractions of its maximum.  Rejected (``ForceCurveError``, with the
    reason) when there is no repulsive contact, fewer than MIN_CONTACT_POINTS points in the
    range, a slope that is not positive, or a contact part that is not linear (the slopes of its
    lower and upper halves differ by more than MAX_NONLINEARITY and by more than
    NONLINEARITY_SIGMA of their combined errors: a Hertzian soft sample changes it by 30 % and
    more, drift or a non-linear detector too).
    """
    z, d = np.asarray(z, float), np.asarray(d, float)
    zmin, zmax = z.min(), z.max()
    far = z <= zmin + 0.3 * (zmax - zmin)
    if far.sum() < 10:
        raise ForceCurveError(path, "too few free points for a baseline before the contact slope fit")
    base = fit_line(z[far], d[far])
    dc = d - base(z)
    order = np.argsort(-z, kind="stable")  # from the turnaround outwards
    dco = dc[order]
    dmax = float(dc.max())
    if not dmax > 10 * base.rms:
        raise ForceCurveError(
            path, f"no repulsive contact part: maximum deflection {dmax:.3g} V is below 10 x noise {base.rms:.3g} V"
        )
    lo, hi = fit_range[0] * dmax, fit_range[1] * dmax
    below = np.flatnonzero(dco < lo)
    run = order[: int(below[0]) if below.size else dco.size]
    sel = run[(dc[run] >= lo) & (dc[run] <= hi)]
    if sel.size < MIN_CONTACT_POINTS:
        raise ForceCurveError(
            path,
            f"contact part too short for a slope: {sel.size} points in the fit range "
            f"{list(fit_range)} (need {MIN_CONTACT_POINTS})",
        )
    line = fit_line(z[sel], dc[sel])
    if not line.slope > 0:
        raise ForceCurveError(path, "contact slope is not positive (deflection does not rise in contact)")
    mid = 0.5 * (lo + hi)
    halves = [sel[dc[sel] < mid], sel[dc[sel] >= mid]]
    if min(h.size for h in halves) >= 5:
        a, b = (fit_line(z[h], dc[h]) for h in halves)
        diff = abs(b.slope - a.slope)
        if diff > MAX_NONLINEARITY * line.slope and diff > NONLINEARITY_SIGMA * np.hypot(a.u_slope, b.u_slope):
            raise ForceCurveError(
                path,
                f"contact part not linear: slope {a.slope * 1e-9:.4g} V/nm in its lower half, "
                f"{b.slope * 1e-9:.4g} V/nm in its upper half (soft sample or drift): no InvOLS",
            )
    return ContactSlope(1.0 / line.slope, line.u_slope / line.slope**2, line.slope, line.n, float(lo), float(hi))


def invols_from_curves(curves: list[ForceCurve], *, fit_range=(0.2, 0.8), segment="approach"):
    """Mean InvOLS over hard-sample curves: (mean, u, per-curve values, per-curve fit u, rejected).

    A curve whose contact part gives no slope (too short, not linear: a spike, drift) or whose
    InvOLS is an outlier among the others (generalized ESD at 1 %, up to a third of them) is left
    out with the reason; ``rejected`` lists (file, reason).  u = standard error of the mean for
    >= 2 curves, else the fit error.  Raises ForceCurveError when no curve gives a slope."""
    from pipeline.forces.statistics import generalized_esd

    vals, us, paths, rejected = [], [], [], []
    for c in curves:
        z = c.z_approach if segment == "approach" else c.z_retract
        try:
            cs = contact_slope(z, c.deflection_volts(segment), fit_range=fit_range, path=c.path)
        except ForceCurveError as exc:
            rejected.append((c.path, exc.reason))
            continue
        vals.append(cs.invols)
        us.append(cs.u_invols)
        paths.append(c.path)
    vals, us = np.array(vals), np.array(us)
    if vals.size == 0:
        why = "; ".join(f"{p}: {r}" for p, r in rejected[:3])
        raise ForceCurveError(curves[0].path if curves else "", f"no hard-sample curve gives a contact slope ({why})")
    if vals.size >= 3:
        out = generalized_esd(vals, alpha=0.01)
        for p, v in zip(np.array(paths)[out], vals[out]):
            rejected.append(
                (
                    str(p),
                    f"its InvOLS {v * 1e9:.4g} nm/V is an outlier among the {vals.size} curves "
                    f"(median {np.median(vals) * 1e9:.4g} nm/V)",
                )
            )
        vals, us = vals[~out], us[~out]
    mean = float(vals.mean())
    u = float(vals.std(ddof=1) / np.sqrt(vals.size)) if vals.size > 1 else float(us[0])
    return mean, u, vals, us, rejected
