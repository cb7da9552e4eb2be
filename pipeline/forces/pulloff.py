"""Pull-off detection on the retract segment: Delta = largest adhesive deflection before the jump-off.

1. Baseline (offset + tilt in z) fitted on the free part of the retract, i.e. the
   points farther from the sample than the jump-off, leaving out the fraction
   ``baseline_gap`` of that range next to the jump (ringing, long-range forces).
   A first pass uses the farthest 30 % of the piezo range to locate the jump.
2. The jump-off is the last point, after the deepest minimum, still below half of
   that minimum; the lever snaps back to the baseline after it.
3. ``method='fit'`` (default): a line through the last ``fit_points`` contact points
   before the jump, evaluated half-way to the next sample (the instability lies
   between them; unbiased over the sampling phase) -- also removes the bias of
   picking the most negative noise sample.  Where the height record is noisy (sensor noise,
   piezo jitter) the line is fitted against the sample index instead (errors in the
   abscissa flatten a line; see ``_contact_extrapolation``).  If the jump is not sharp (the rise over
   the next 3 samples is < 50 % of Delta: gradual detachment, soft samples) the
   minimum of a 5-point running mean is used instead.
   ``method='min'``: the raw minimum.
4. Rejected (``ForceCurveError``) when there is no jump back to the baseline, the
   free part is too short, or Delta < ``min_snr`` x baseline noise rms.

The sampling step limits what any method can see: the true instability lies
between the last contact sample and the next one, so u(Delta) includes the
contact step over sqrt(12) besides the fit error (per-curve error up to half a
step, e.g. 0.1 nm for 0.2 nm piezo steps on a hard contact).
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from pipeline.forces.baseline import Line, fit_line
from pipeline.forces.errors import ForceCurveError


@dataclass
class PullOff:
    """Result in the deflection units of the curve (V or m); z in m."""

    delta: float
    u_delta: float
    delta_min: float
    i_jump: int
    z_pulloff: float
    baseline: Line
    n_baseline: int
    jump_fraction: float  # rise over 3 samples after the jump-off / Delta (< 0.5: gradual detachment)


def _jump_index(dc: np.ndarray, path) -> int:
    """Last contact point: before the largest one-sample rise between the minimum and
    the return above half of it."""
    i_min = int(np.argmin(dc))
    if dc[i_min] >= 0:
        raise ForceCurveError(path, "no pull-off event: the retract curve never goes below its baseline")
    back = np.flatnonzero(dc[i_min:] >= 0.5 * dc[i_min])
    if back.size == 0:
        raise ForceCurveError(path, "no pull-off event: the deflection does not jump back to the baseline before the end of the retract")
    i_half = i_min + int(back[0])
    return i_min + int(np.argmax(np.diff(dc[i_min : i_half + 1])))


def _baseline(z, d, mask, min_points, path, what) -> Line:
    n = int(mask.sum())
    if n < min_points:
        raise ForceCurveError(path, f"free part of the retract {what} is too short for a baseline ({n} points < {min_points})")
    return fit_line(z[mask], d[mask])


def _line_at(x, y, x_eval, line):
    """Value of ``line`` (fitted to x, y) at ``x_eval`` and its standard error."""
    sxx = max(float(np.sum((x - x.mean()) ** 2)), 1e-300)
    lever = 1.0 / x.size + (x_eval - x.mean()) ** 2 / sxx
    return float(line(x_eval)), line.rms * np.sqrt(lever)


def _last_contact(dc, i_j, fit_points, rms):
    """Move the jump-off past samples that look free but are followed, within ``fit_points``
    samples, by samples that can only be in contact (deeper than half the adhesive dip and than
    4 x the baseline noise): a jittering piezo moves the lever back and forth along its contact
    line, so its deflection can rise and fall again before the lever lets go."""
    for _ in range(100):
        thr = -max(0.5 * -dc[i_j], 4.0 * rms)
        hi = min(dc.size - 1, i_j + 1 + fit_points)
        later = np.flatnonzero(dc[i_j + 1 : hi] < thr)
        if later.size == 0:
            return i_j
        i_j = i_j + 1 + int(later[-1])
    return i_j


def _contact_extrapolation(z, dc, i_j, fit_points, robust=False):
    """(Delta, u_fit, step) from a line through the last ``fit_points`` contact points,
    evaluated half-way between the last contact sample and the first free one.

    The regressor is the recorded height, or the sample index (time) where the height record
    is noisier than the deflection it drives (height-sensor noise: a line fitted against a
    noisy abscissa is flattened towards the window's mean -- errors in variables -- and reads
    Delta up to ~20 % low).  The piezo moves at a steady rate in time, so the index is an
    abscissa without that error; it is used when its residuals are clearly the smaller
    (rms < 0.8 x), so clean ramps keep the height fit.  The lever stayed in contact at every
    contact sample, so the instability lies between the lowest of their heights and the first
    free sample's (the two neighbours on a clean ramp); ``step`` is the change of the line over
    that bracket.  ``robust``: one 3-sigma rejection pass (free samples interleaved by jitter)."""
    lo = max(0, i_j + 1 - fit_points)
    zc, yc, ic = z[lo : i_j + 1], dc[lo : i_j + 1], np.arange(lo, i_j + 1, dtype=float)
    line_z, line_i = fit_line(zc, yc, clip=np.inf), fit_line(ic, yc, clip=np.inf)
    by_index = line_i.rms < 0.8 * line_z.rms
    x = ic if by_index else zc
    if robust:
        keep = np.abs(yc - (line_i if by_index else line_z)(x)) <= 3.0 * (line_i if by_index else line_z).rms
        x, yc, zc = x[keep], yc[keep], zc[keep]
    line = fit_line(x, yc, clip=np.inf)
    if by_index:
        v, u = _line_at(x, yc, i_j + 0.5, line)
        return -v, u, abs(line.slope)
    z_last = float(zc.min()) if robust else float(z[i_j])
    v, u = _line_at(x, yc, 0.5 * (z_last + z[i_j + 1]), line)
    return -v, u, abs(line.slope) * abs(z_last - float(z[i_j + 1]))


def detect_pulloff(z, d, *, path="", baseline_gap=0.2, min_baseline_points=50, method="fit",
                   fit_points=20, min_snr=5.0) -> PullOff:
    """Find Delta on a retract segment (``z`` decreasing, m; ``d`` deflection, V or m)."""
    z, d = np.asarray(z, float), np.asarray(d, float)
    idx = np.arange(z.size)
    zmin, zmax = z.min(), z.max()
    line = _baseline(z, d, z <= zmin + 0.3 * (zmax - zmin), min_baseline_points, path, "(farthest 30 %)")
    i_j = _jump_index(d - line(z), path)
    if i_j + 1 >= z.size:
        raise ForceCurveError(path, "no pull-off event: the minimum is at the end of the retract")
    zj = z[i_j + 1]
    free = (idx > i_j) & (z <= zj - baseline_gap * (zj - zmin))
    line = _baseline(z, d, free, min_baseline_points, path, "after the jump-off")
    dc = d - line(z)
    i_j = _jump_index(dc, path)
    delta_min = float(-dc[: i_j + 1].min())
    step = 0.0
    jump_fraction = float((dc[i_j + 1 : i_j + 4].max() - dc[i_j]) / delta_min)
    if method == "fit" and jump_fraction < 0.5:  # gradual detachment: minimum of a 5-point running mean
        m = np.convolve(dc[: i_j + 3], np.ones(5) / 5.0, mode="valid") if i_j >= 2 else dc[: i_j + 1]
        delta = float(-m.min())
        u_fit = line.rms / np.sqrt(5.0)
    elif method == "fit" and i_j + 1 >= 3:
        i_last = _last_contact(dc, i_j, int(fit_points), line.rms)
        delta, u_fit, step = _contact_extrapolation(z, dc, i_last, int(fit_points), robust=i_last != i_j)
        i_j = i_last
    elif method in ("fit", "min"):
        delta, u_fit = delta_min, line.rms
    else:
        raise ValueError(f"unknown pull-off method {method!r} (fit | min)")
    if not delta > min_snr * line.rms:
        raise ForceCurveError(path, f"no pull-off event: adhesive deflection {delta:.3g} is below {min_snr:g} x baseline noise rms {line.rms:.3g}")
    u = float(np.hypot(u_fit, step / np.sqrt(12.0)))
    return PullOff(delta, u, delta_min, int(i_j), float(z[i_j]), line, line.n, jump_fraction)
