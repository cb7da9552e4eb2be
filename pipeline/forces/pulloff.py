"""Pull-off detection on the retract segment: Delta = largest adhesive deflection.

The pull-off force is the largest attraction the lever feels, k Delta, where Delta is the
deepest point of the (noise-free) retract curve below the baseline.  Where that point lies
depends on the lever and the force law, and the reading follows the shape the curve shows:

* **sharp jump** (a soft lever: the adhesive force reaches its largest value and the lever
  lets go within a sample): the deepest point is where the contact line ends.  A line through
  the last ``fit_points`` contact points is evaluated at the moment of the jump, taken where
  the signal crosses half-way between the contact line and the level after the jump
  (interpolated between samples: half-way between the last contact sample and the first free
  one on an unfiltered record; on a record through an anti-alias filter, whose step response
  crosses 50 % near its group delay, this also undoes the filter's lag on the contact line).
  Where the height record is noisy (sensor noise, piezo jitter) the line is fitted against the
  sample index instead (errors in the abscissa flatten a line; see ``_contact_extrapolation``),
  and samples that a jittering piezo puts back on the contact line after an apparent jump-off
  are still contact (``_last_contact``).
* **corner** (a stiffer lever under a force law that is largest at contact, such as a Dugdale
  law over a tip: the lever follows the law past the contact point, so the curve turns up
  at a corner and rises along a detaching branch before any jump) or **rounded minimum** (a
  force law whose largest attraction is away from contact, e.g. L-J or an exponential law,
  under a stiff lever; also a contact line that bends towards a minimum just before the jump):
  two straight arms joined by a hyperbola whose rounding is fitted (0: a sharp corner), through
  the samples within max(25 % of the depth, 8 x the noise) of the minimum on both sides (at
  least 4 on each), up to the jump; Delta is its lowest point, and its uncertainty includes how far that moves
  over the roundings the noise cannot tell apart.  Where the hinge does not describe the
  samples (an irregular release on a soft sample), the minimum of a 5-sample running mean.
``method='min'`` gives the raw minimum (biased deep by the noise).

Baseline (offset + tilt in z): fitted on the free part of the retract, the points farther from
the sample than the jump-off, leaving out the fraction ``baseline_gap`` of that range next to the
jump (ringing, long-range forces); a first pass on the farthest 30 % of the piezo range locates
the jump.  Rejected (``ForceCurveError``) when there is no jump back to the baseline, the free
part is too short, or Delta < ``min_snr`` x baseline noise rms.

The sampling step limits what any method sees at a sharp jump: the instability lies between the
last contact sample and the next one, so u(Delta) includes the contact step over sqrt(12)
besides the fit error.
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
    shape: str = "sharp jump"  # how Delta was read: sharp jump | corner | rounded minimum | raw minimum


def _first_release(dc: np.ndarray, noise: float) -> int:
    """Index after which the lever has let go (end of the region to search for the pull-off):
    the first sample, in time, that rose by more than half the depth reached so far (and that
    depth beyond 8 x the noise), plus a few samples for a filter's transition; the whole record
    where there is none (a smooth detachment).  After a jump a lever of high Q rings, and
    without an anti-alias filter the samples of its ringing can dip below the pull-off: they
    are after its release and no pull-off."""
    run_min = np.minimum.accumulate(dc)
    half = 0.5 * run_min[:-2]
    # a rise above half the depth reached so far that stays there for two samples (a piezo's
    # jitter excursion comes back at once)
    big = np.flatnonzero((dc[1:-1] > half) & (dc[2:] > half) & (run_min[:-2] < -8.0 * noise))
    return dc.size if big.size == 0 else min(dc.size, int(big[0]) + 4)


def _jump_index(dc: np.ndarray, path, noise: float = 0.0) -> int:
    """Last contact point: before the largest one-sample rise between the minimum and the
    return above half of it, the minimum searched up to the first release (``_first_release``)."""
    end = _first_release(dc, noise) if noise > 0 else dc.size
    i_min = int(np.argmin(dc[:end]))
    if dc[i_min] >= 0:
        raise ForceCurveError(path, "no pull-off event: the retract curve never goes below its baseline")
    back = np.flatnonzero(dc[i_min:] >= 0.5 * dc[i_min])
    if back.size == 0:
        raise ForceCurveError(
            path, "no pull-off event: the deflection does not jump back to the baseline before the end of the retract"
        )
    i_half = i_min + int(back[0])
    return i_min + int(np.argmax(np.diff(dc[i_min : i_half + 1])))


def _baseline(z, d, mask, min_points, path, what) -> Line:
    n = int(mask.sum())
    if n < min_points:
        raise ForceCurveError(
            path, f"free part of the retract {what} is too short for a baseline ({n} points < {min_points})"
        )
    return fit_line(z[mask], d[mask])


def _line_at(x, y, x_eval, line):
    """Value of ``line`` (fitted to x, y) at ``x_eval`` and its standard error."""
    sxx = max(float(np.sum((x - x.mean()) ** 2)), 1e-300)
    lever = 1.0 / x.size + (x_eval - x.mean()) ** 2 / sxx
    return float(line(x_eval)), line.rms * np.sqrt(lever)


def _last_contact(dc, i_j, fit_points, rms):
    """Move the jump-off past samples that look free but are followed, within ``fit_points``
    samples, by samples that can only be in contact (back near the contact line: deeper than 70 %
    of the adhesive dip and than 4 x the baseline noise): a jittering piezo moves the lever back and
    forth along its contact line, so its deflection can rise and fall again before the lever lets
    go; a lever of high Q rings after it let go, and its aliased swings dip to about half the depth.  Such a sample
    must follow the contact samples without a break, or come after a free-looking one (above half
    the dip): a jump seen through an anti-alias filter rises monotonically and is no jitter."""
    for _ in range(100):
        thr = -max(0.7 * -dc[i_j], 4.0 * rms)
        hi = min(dc.size - 1, i_j + 1 + fit_points)
        seg = dc[i_j + 1 : hi]
        # back on the contact line: right after (the contact goes on) or after a free-looking excursion
        prior = np.maximum.accumulate(np.concatenate([[-np.inf], seg[:-1]]))
        run = int(np.argmax(seg >= thr)) if np.any(seg >= thr) else seg.size  # contiguous contact samples
        later = np.flatnonzero((seg < thr) & ((np.arange(seg.size) < run) | (prior > 0.5 * dc[i_j])))
        if later.size == 0:
            return i_j
        i_j = i_j + 1 + int(later[-1])
    return i_j


def _abscissa(z, dc, lo, hi):
    """The regressor for lines over samples lo..hi: the recorded height, or the sample index
    (time; the piezo moves at a steady rate) where the height record is clearly noisier than
    the deflection it drives (its residuals < 0.8 x the height fit's).  Returns (x, by_index)."""
    zc, yc, ic = z[lo : hi + 1], dc[lo : hi + 1], np.arange(lo, hi + 1, dtype=float)
    by_index = fit_line(ic, yc, clip=np.inf).rms < 0.8 * fit_line(zc, yc, clip=np.inf).rms
    return (np.arange(z.size, dtype=float) if by_index else z), by_index


def _clipped_run(z, d, dc, i_min, fit_points, min_run=5):
    """Why the adhesive dip is flat at the rail of the recorded range (a saturated detector or ADC:
    never a pull-off), or ''.  A run of >= ``min_run`` samples at exactly the lowest recorded
    value, around the deepest point, where the contact line before the run would have gone on down
    (its value at the run's end below the run by > 4 x its noise and > 10 % of the depth): a
    coarsely quantised genuine minimum or a corner has a few equal samples at most, and its contact
    line ends near them."""
    rail = float(d.min())
    at = np.abs(d - rail) <= 1e-12 * max(abs(rail), 1e-300)
    if not at[i_min]:
        return ""
    a = b = i_min
    while a > 0 and at[a - 1]:
        a -= 1
    while b < d.size - 1 and at[b + 1]:
        b += 1
    if b - a + 1 < min_run or a < 5:
        return ""
    lo = max(0, a - fit_points)
    line = fit_line(np.arange(lo, a, dtype=float), dc[lo:a], clip=np.inf)
    below = float(dc[a] - line(float(b)))
    if below > max(4.0 * line.rms, 0.1 * -float(dc[a])):
        return (
            f"the adhesive dip is clipped: {b - a + 1} samples sit at the lowest recorded value ({rail:.6g}, the "
            f"detector's or the ADC's limit) where the contact line still falls: its real depth is not recorded, "
            f"so this is no pull-off (re-record with a larger deflection range or a lower gain)"
        )
    return ""


def _noise_near(dc, i, half=10):
    """Noise rms of the samples just before ``i`` about a straight line (m or V)."""
    lo = max(0, i - 2 * half)
    if i - lo < 4:
        return 0.0
    return fit_line(np.arange(lo, i, dtype=float), dc[lo:i], clip=np.inf).rms


def _crossing_index(dc, i_last, i_rise, line_value):
    """Fractional sample index where the jump crosses half-way between the contact line's value
    ``line_value`` and the level after the jump (median of the samples 2-6 after the largest rise)."""
    after = dc[i_rise + 2 : i_rise + 7]
    level = float(np.median(after)) if after.size else float(dc[min(i_rise + 1, dc.size - 1)])
    mid = 0.5 * (line_value + level)
    m = i_last + 1
    while m < dc.size - 1 and dc[m] < mid and m <= i_rise + 1:
        m += 1
    a, b = float(dc[m - 1]), float(dc[m])
    frac = float(np.clip((mid - a) / (b - a), 0.0, 1.0)) if b > a else 0.5
    return (m - 1) + frac


def _contact_extrapolation(z, dc, i_j, fit_points, i_rise, robust=False):
    """(Delta, u_fit, step, last contact index) at a sharp jump: a line through the last
    ``fit_points`` contact points, evaluated where the jump crosses half-way (``_crossing_index``).

    The regressor is the recorded height or the sample index (``_abscissa``).  The lever stayed
    in contact at every contact sample, so on a jittered ramp the instability lies between the
    lowest of their heights and the first free sample's; ``step`` is the change of the line over
    the sample interval the jump falls in.  ``robust``: one 3-sigma rejection pass (free samples
    interleaved by jitter).  ``i_j``: the last sample before the jump's transition
    (``_transition_start``); the samples a filter lifts with the jump are left to the crossing."""
    lo = max(0, i_j + 1 - fit_points)
    x_all, by_index = _abscissa(z, dc, lo, i_j)
    x, yc = x_all[lo : i_j + 1], dc[lo : i_j + 1]
    line = fit_line(x, yc, clip=np.inf)
    if robust:
        keep = np.abs(yc - line(x)) <= 3.0 * line.rms
        x, yc = x[keep], yc[keep]
        line = fit_line(x, yc, clip=np.inf)
    s50 = _crossing_index(dc, i_j, max(i_rise, i_j), float(line(x_all[i_j])))
    if by_index:
        x_eval = s50
    else:
        k = int(np.clip(np.floor(s50), 0, z.size - 2))
        x_eval = float(z[k] + (s50 - k) * (z[k + 1] - z[k]))
        if robust:  # jitter: the instability lies beyond the lowest contact height
            x_eval = 0.5 * (float(z[lo : i_j + 1].min()) + float(z[i_j + 1]))
    v, u = _line_at(x, yc, x_eval, line)
    step = abs(line.slope) * (1.0 if by_index else abs(float(z[i_j]) - float(z[i_j + 1])))
    if robust and not by_index:
        step = abs(line.slope) * abs(float(z[lo : i_j + 1].min()) - float(z[i_j + 1]))
    return -v, u, step, i_j


UNRESOLVED_ROUNDING = 2.0  # samples


def _rounded_hinge(s, y, n_corner=120, n_round=14):
    """Two straight arms joined by a rounded corner (a hyperbola with the arms as asymptotes):
    y = a + b u + c_r sqrt(u^2 + c^2), u = s - s_k.  c = 0 is a sharp corner (a Dugdale-like
    force law, largest at contact), c > 0 a rounded minimum (a smooth law whose largest
    attraction the lever passes before it lets go); a wide c is a parabola.  The corner s_k and
    the rounding c are searched on grids, (a, b, c_r) by least squares.  Returns (lowest value of
    the fitted curve over the window, its standard error, rss, c).  The standard error includes
    half the spread of that value over the (s_k, c) that fit within Delta chi^2 < 1 of the best:
    a rounding the noise cannot resolve widens it.  The lowest point of the curve is read where the
    rounding spans more than UNRESOLVED_ROUNDING samples; a narrower one may be the anti-alias
    filter's or the sampling's, so there the midpoint between the curve's lowest point and the arms'
    corner is read, half their difference added to the uncertainty (reading the corner alone
    was 10 % deep on a stiff lever passing a smooth maximum, the lowest point alone 3 % shallow
    on a filtered Dugdale corner)."""
    scale = abs(float(s[-1] - s[0])) / max(s.size - 1, 1) or 1.0
    s = (np.asarray(s, float) - float(s[0])) / scale  # in sample steps: a well-conditioned basis
    ds, span = 1.0, float(s[-1])
    sk = np.linspace(s[1], s[-2], n_corner)
    cc = np.concatenate([[0.0], np.geomspace(0.3 * ds, 0.5 * abs(span), n_round - 1)])
    K, C = (g.ravel() for g in np.meshgrid(sk, cc, indexing="ij"))
    u = s[None, :] - K[:, None]
    A = np.stack([np.ones_like(u), u, np.sqrt(u * u + C[:, None] ** 2)], axis=-1)  # (G, N, 3)
    AtA = np.einsum("gni,gnj->gij", A, A)
    Aty = np.einsum("gni,n->gi", A, y)
    AtA_r = AtA + 1e-12 * np.einsum("gii->g", AtA)[:, None, None] * np.eye(3)
    coef = np.linalg.solve(AtA_r, Aty[..., None])[..., 0]
    rss = np.sum((np.einsum("gni,gi->gn", A, coef) - y) ** 2, axis=1)
    # the lowest point of each fitted curve inside the window
    tt = np.linspace(s[0], s[-1], 201)
    uu = tt[None, :] - K[:, None]
    vals = coef[:, :1] + coef[:, 1:2] * uu + coef[:, 2:3] * np.sqrt(uu * uu + C[:, None] ** 2)
    jmin = np.argmin(vals, axis=1)
    low = vals[np.arange(K.size), jmin]
    # a rounding within UNRESOLVED_ROUNDING samples may be the anti-alias filter's or the
    # sampling's rather than the force law's: the largest deflection then lies between the curve's
    # lowest point and its arms' corner (their asymptotes meet at u = 0, y = a); the midpoint is
    # read, half the difference enters the uncertainty
    narrow = (C <= UNRESOLVED_ROUNDING * ds) & (coef[:, 2] > 0)
    half_gap = np.where(narrow, 0.5 * (low - coef[:, 0]), 0.0)
    low = low - half_gap
    g = int(np.argmin(rss))
    sigma2 = rss[g] / max(s.size - 5, 1)
    row = np.array([1.0, uu[g, jmin[g]], np.sqrt(uu[g, jmin[g]] ** 2 + C[g] ** 2)])
    var = sigma2 * float(row @ np.linalg.solve(AtA_r[g], row))
    near = (rss - rss[g]) / max(sigma2, 1e-300) < 1.0
    spread = 0.5 * float(np.ptp(low[near])) if near.sum() > 1 else 0.0
    u = float(np.sqrt(max(var, 0.0) + spread**2 + half_gap[g] ** 2))
    return float(low[g]), u, float(rss[g]), float(C[g]) * scale


def _transition_start(dc, i_rise, i_min, step_c, noise):
    """The last sample before the jump's transition: walking back from the largest rise
    ``i_rise``, samples that rose from their predecessor by more than max(1.5 x the contact line's
    change per sample ``step_c``, 4 x noise) belong to the jump (an anti-alias filter spreads it
    over several samples); a detaching branch near its corner rises about as fast as the contact
    line fell.

    A causal filter's step response rises no longer than it settles, so the walk goes back at most
    one sample more than the rises after the largest one last: a lever that left the contact line
    along the force law for several samples before a sharp jump is a detaching branch, not a filter
    transition."""
    thr = max(1.5 * step_c, 4.0 * noise)
    after = 0
    while i_rise + 2 + after < dc.size and dc[i_rise + 2 + after] - dc[i_rise + 1 + after] > thr:
        after += 1
    j = i_rise
    while j > i_min and i_rise - j <= after and dc[j] - dc[j - 1] > thr:
        j -= 1
    return j


def _detaching_branch(dc, i_min, i_end, line, x, noise):
    """Samples after the deepest one, before the jump, that leave the contact line upwards
    (residual above it by > 3 x noise): the lever detaching along the force law."""
    if i_end <= i_min:
        return np.zeros(0, int)
    idx = np.arange(i_min + 1, i_end + 1)
    return idx[dc[idx] - line(x[idx]) > 3.0 * noise]


def _band_window(dc, i_min, i_end, noise, min_side=4, most=200):
    """Samples around the minimum within max(25 % of its depth, 8 x the noise) of it (>= ``min_side``
    on each side), up to ``i_end``."""
    band = float(dc[i_min]) + max(0.25 * -float(dc[i_min]), 8.0 * noise)
    lo = i_min
    while lo > 0 and (dc[lo - 1] <= band or i_min - lo < min_side) and i_min - lo < most:
        lo -= 1
    hi = i_min
    while hi < i_end and (dc[hi + 1] <= band or hi - i_min < min_side) and hi - i_min < most:
        hi += 1
    return lo, hi


def _smooth_minimum(dc, x, lo, hi, noise):
    """(Delta, u, shape) from the rounded hinge through samples lo..hi (``_rounded_hinge``).

    Where the hinge does not describe the samples (residual rms > 2 x the baseline ``noise``: a
    soft sample's irregular release, several unbinding events) the minimum of a 5-sample running
    mean is taken instead, with the misfit and the two readings' difference in its uncertainty."""
    s, y = x[lo : hi + 1], dc[lo : hi + 1]
    if s[0] > s[-1]:  # the height falls during the retract: order the abscissa in time
        s = -s
    low, u, rss, c = _rounded_hinge(s, y)
    ds = abs(float(s[-1] - s[0])) / max(s.size - 1, 1)
    rms = float(np.sqrt(rss / max(s.size - 5, 1)))
    if rms <= 2.0 * noise:
        return -low, u, ("corner" if c < ds else "rounded minimum")
    m = np.convolve(y, np.ones(5) / 5.0, mode="valid")
    low_m = float(m.min())
    return -low_m, float(np.hypot(rms / np.sqrt(5.0), 0.5 * (low - low_m))), "irregular minimum (running mean)"


def _bends_before_the_jump(dc, x, lo, hi, m=4, t_min=3.5):
    """Whether the last ``m`` samples before the jump lie above the contact line through the ones
    before them (lo..hi-m) on average, by more than ``t_min`` standard errors: the lever left the
    line before it let go (a force law past its largest attraction followed by a stiff lever)."""
    s, y = x[lo : hi + 1], dc[lo : hi + 1]
    if s.size < m + 6:
        return False
    line = fit_line(s[:-m], y[:-m], clip=np.inf)
    r = y[-m:] - line(s[-m:])
    sxx = float(np.sum((s[:-m] - s[:-m].mean()) ** 2))
    lever = 1.0 / (s.size - m) + (float(s[-m:].mean()) - float(s[:-m].mean())) ** 2 / max(sxx, 1e-300)
    se = line.rms * np.sqrt(1.0 / m + lever)
    return bool(r.mean() > t_min * se)


def _fitted_minimum(z, dc, line, i_j, i_min, jump_fraction, fit_points):
    """Delta of method "fit" on the corrected deflection ``dc`` (jump index ``i_j``, deepest
    sample ``i_min``): (delta, its fit uncertainty, the shape, the extrapolation step, the index
    of the last contact sample)."""
    step = 0.0
    shape = "sharp jump"  # unless a smooth minimum is found below
    # where the curve turns: a jump right after the deepest sample, or a detaching branch first
    lo = max(0, i_min - int(fit_points))
    x, _ = _abscissa(z, dc, lo, i_min)
    contact = fit_line(x[lo : i_min + 1], dc[lo : i_min + 1], clip=np.inf) if i_min - lo >= 3 else None
    if jump_fraction >= 0.5:
        step_c = abs(contact.slope) * float(np.median(np.abs(np.diff(x[lo : i_min + 1])))) if contact else 0.0
        i_end = _transition_start(dc, i_j, i_min, step_c, line.rms)
    else:
        i_end = i_j + int(np.argmax(dc[i_j:] >= 0.5 * dc[i_min]))
    branch = (
        _detaching_branch(dc, i_min, i_end, contact, x, max(contact.rms, 1e-300))
        if contact is not None
        else np.zeros(0, int)
    )
    # jitter: samples after the largest rise that are back on the contact line (not a filter's transition)
    i_jit = _last_contact(dc, i_j, int(fit_points), line.rms) if jump_fraction >= 0.5 else i_j
    i_last = i_jit if i_jit != i_j else i_end
    if branch.size >= 1 or jump_fraction < 0.5:
        delta, u_fit, shape = _smooth_minimum(dc, x, *_band_window(dc, i_min, i_end, line.rms), line.rms)
        i_j = i_min
    else:
        lo_w = max(0, i_last + 1 - int(fit_points))
        xw, _ = _abscissa(z, dc, lo_w, i_last)
        if i_last == i_end and i_last - lo_w >= 8 and _bends_before_the_jump(dc, xw, lo_w, i_last):
            # the line bends to a minimum before the jump: the lever passed the largest
            # attraction before it let go
            delta, u_fit, shape = _smooth_minimum(dc, xw, lo_w, i_last, line.rms)
            shape += " before the jump"
            i_last = lo_w + int(np.argmin(dc[lo_w : i_last + 1]))
        else:
            delta, u_fit, step, i_last = _contact_extrapolation(
                z, dc, i_last, int(fit_points), i_j, robust=i_last != i_end
            )
        i_j = i_last
    return delta, u_fit, shape, step, i_j


def detect_pulloff(
    z, d, *, path="", baseline_gap=0.2, min_baseline_points=50, method="fit", fit_points=20, min_snr=5.0
) -> PullOff:
    """Find Delta on a retract segment (``z`` decreasing, m; ``d`` deflection, V or m)."""
    z, d = np.asarray(z, float), np.asarray(d, float)
    idx = np.arange(z.size)
    zmin, zmax = z.min(), z.max()
    line = _baseline(z, d, z <= zmin + 0.3 * (zmax - zmin), min_baseline_points, path, "(farthest 30 %)")
    i_j = _jump_index(d - line(z), path, line.rms)
    if i_j + 1 >= z.size:
        raise ForceCurveError(path, "no pull-off event: the minimum is at the end of the retract")
    zj = z[i_j + 1]
    free = (idx > i_j) & (z <= zj - baseline_gap * (zj - zmin))
    line = _baseline(z, d, free, min_baseline_points, path, "after the jump-off")
    dc = d - line(z)
    i_j = _jump_index(dc, path, line.rms)
    i_min = int(np.argmin(dc[: i_j + 1]))
    delta_min = float(-dc[i_min])
    clipped = _clipped_run(z, d, dc, i_min, int(fit_points))
    if clipped:
        raise ForceCurveError(path, clipped)
    step = 0.0
    jump_fraction = float((dc[i_j + 1 : i_j + 4].max() - dc[i_j]) / delta_min)
    if method == "min":
        delta, u_fit, shape = delta_min, line.rms, "raw minimum"
    elif method != "fit":
        raise ValueError(f"unknown pull-off method {method!r} (fit | min)")
    elif i_min < 5:
        delta, u_fit, shape = delta_min, line.rms, "raw minimum (too few contact points for a line)"
    else:
        delta, u_fit, shape, step, i_j = _fitted_minimum(z, dc, line, i_j, i_min, jump_fraction, int(fit_points))
    if not delta > min_snr * line.rms:
        raise ForceCurveError(
            path,
            f"no pull-off event: adhesive deflection {delta:.3g} is below force_curves.min_pulloff_snr "
            f"({min_snr:g}) x the baseline noise rms {line.rms:.3g} (same units as the deflection)",
        )
    u = float(np.hypot(u_fit, step / np.sqrt(12.0)))
    return PullOff(delta, u, delta_min, int(i_j), float(z[i_j]), line, line.n, jump_fraction, shape)
