"""Tip silhouette to sub-pixel precision (the OUTER surface, coating included).

1. ``locate_tip``: block-averaged copy (<= ~256 px), background flattened, mask
   threshold just below the background (so a light coating belongs to the tip);
   the largest dark component entering from the top/bottom edge is the tip
   (scale bar and label are small and detached); coarse apex, and the axis from
   a robust line through the component midline over up to 3x the window height.
2. ``initial_contour``: iso-contour 2 % (>= 4 noise sigma) below the flattened
   background in a full-resolution window around the apex: it lies OUTSIDE
   the surface by about 2 blur sigma.  (A mid-level threshold would sit inside:
   the projected thickness t = 2 sqrt(r^2 - x^2) rises from 0 like a square root.)
3. ``refine_edges``: along the normal of every contour point (1 px apart), fit
   I(s) = a_i + b_i [G_sigma * T](s - delta_i),  T = exp(-k_o t_outer - (k_c - k_o) t_core),
   t_outer/t_core the EXACT chords of the axisymmetric body described by the
   current silhouette (disk cross-sections; coating = erosion by c along the
   normal), G the 2-D Gaussian blur (separable: Gauss-Hermite along the tangent,
   1-D along the normal).  Global (k_o, sigma) or (k_o, sigma, k_c, c) by least
   squares on a subset of normals with the shifts smoothed along the arc
   (single layer vs coating chosen by the residual); a_i, b_i linear; delta_i by
   Gauss-Newton, smoothed along the arc just enough to reach ~0.15 px precision
   (adaptive, 2-12 px).  The silhouette moves by delta and the body is rebuilt:
   the fixed point is the body whose blurred projection matches the image.
   Noise-free synthetic images: edge within 0.01 nm of the true surface.
All coordinates here are pixels (row, col); the tip points down (callers flip "up" images).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy import ndimage

from pipeline.tem.projection import chord, core_radius_table

__all__ = ["CoarseTip", "locate_tip", "initial_contour", "TipFrame", "refine_edges"]


SATURATED_FRACTION = 2e-3  # share of the window at its maximum that marks a clipped (saturated) detector
PLATEAU_RATIO = 3.0  # ... if the maximum is held by more than this x the pixels at the next lower value
_LAPLACE_3X3 = np.array([[1.0, -2.0, 1.0], [-2.0, 4.0, -2.0], [1.0, -2.0, 1.0]])


@dataclass
class CoarseTip:
    apex: np.ndarray  # (row, col) px, full image, tip pointing down
    angle: float  # rad, tilt of the tip axis (body leaning to +col going up is > 0)
    background: float
    dark: float
    width_px: np.ndarray  # coarse full width per px of height above the apex
    bbox: tuple = ((0, 0), (0, 0))  # ((row0, row1), (col0, col1)) full image, tip region


class _Fail(Exception):  # noqa: N818 - a control-flow signal inside the stage, worded by its caller
    pass


def _downsample(img, factor):
    if factor <= 1:
        return img
    h, w = (img.shape[0] // factor) * factor, (img.shape[1] // factor) * factor
    return img[:h, :w].reshape(h // factor, factor, w // factor, factor).mean(axis=(1, 3))


def _tip_mask(img, orientation):
    """(block size f, (mask of the tip in the block-averaged image, flipped), dark level) of
    ``locate_tip``: the largest dark object entering from the top (or bottom) edge."""
    from skimage.filters import threshold_otsu

    H, W = img.shape
    f = max(1, int(np.ceil(max(H, W) / 256)))
    small = _downsample(img, f)
    lo, hi = np.percentile(small, [1, 99])
    if hi - lo <= 1e-9 * max(1.0, abs(hi)):
        raise _Fail("no tip in the image (no contrast)")
    flat, noise = flatten_background(small)
    sm = ndimage.gaussian_filter(flat, 1.0, mode="nearest")
    otsu = threshold_otsu(sm)
    dark_level = float(np.percentile(sm[sm <= otsu], 20)) if (sm <= otsu).any() else otsu
    contrast = 1.0 - dark_level
    if contrast < 8 * noise / (2 * np.sqrt(np.pi)):
        raise _Fail("no tip in the image (contrast below the noise)")
    thr = 1.0 - max(0.05 * contrast, 4.0 * noise / (2 * np.sqrt(np.pi)))
    dark = sm < thr
    dark = ndimage.binary_opening(dark, iterations=1)
    lab, nlab = ndimage.label(dark)
    if nlab == 0:
        raise _Fail("no tip in the image (no dark object)")
    sizes = np.bincount(lab.ravel())
    sizes[0] = 0
    top = np.bincount(lab[0], minlength=nlab + 1)
    bot = np.bincount(lab[-1], minlength=nlab + 1)
    top[0] = bot[0] = 0
    cand = {"down": top, "up": bot}.get(orientation, np.maximum(top, bot))
    score = np.where(cand > 0, sizes, 0)
    k = int(np.argmax(score))
    if score[k] < 0.01 * small.size:
        raise _Fail("no tip in the image (no large dark object entering from the top or bottom edge)")
    flipped = orientation == "up" or (orientation == "auto" and bot[k] > top[k])
    return f, (lab == k, flipped), dark_level


def _midline_slope(mask, apex_r, hgt):
    """d(midline column)/d(height) of the tip mask, robust line fit (``locate_tip``)."""
    long_rr = np.arange(max(0, apex_r - 3 * hgt), apex_r + 1)
    lsub = mask[long_rr]
    lhas = lsub.any(axis=1)
    ll = np.argmax(lsub, axis=1)
    lr = lsub.shape[1] - 1 - np.argmax(lsub[:, ::-1], axis=1)
    lh = (apex_r - long_rr).astype(float)
    use = lhas & (lh > 0.3 * hgt) & (ll > 0) & (lr < lsub.shape[1] - 1)
    slope = 0.0
    if use.sum() >= 3:
        hh, mm = lh[use], 0.5 * (ll + lr)[use]
        keep = np.ones(hh.size, bool)
        for _ in range(3):
            c = np.polyfit(hh[keep], mm[keep], 1)
            res = mm - np.polyval(c, hh)
            keep = np.abs(res) <= max(2.0, 3 * 1.4826 * np.median(np.abs(res[keep])))
        slope = c[0]
    return slope


def locate_tip(img, max_height_px, orientation="auto"):
    """Coarse tip: returns (CoarseTip, flipped) with ``flipped`` True if the tip pointed up.

    Works on a block-averaged copy (<= ~256 px) with the background flattened;
    the mask threshold sits just below the background (5 % of the tip contrast,
    >= 4 noise sigma) so that a light coating belongs to the tip.  Raises _Fail.
    """
    f, (mask, flipped), dark_level = _tip_mask(img, orientation)
    if flipped:
        mask = mask[::-1]
    rows = np.nonzero(mask.any(axis=1))[0]
    apex_r = rows.max()
    if apex_r >= mask.shape[0] - 2:
        raise _Fail("apex touches the image border (tip reaches the far edge)")
    hgt = max(4, int(np.ceil(max_height_px / f)))
    rr = np.arange(max(0, apex_r - hgt), apex_r + 1)
    sub = mask[rr]
    has = sub.any(axis=1)
    left = np.argmax(sub, axis=1)
    right = sub.shape[1] - 1 - np.argmax(sub[:, ::-1], axis=1)
    height = (apex_r - rr).astype(float)
    near = has & (height < 0.5 * hgt)
    if (left[near] == 0).any() or (right[near] == sub.shape[1] - 1).any():
        raise _Fail("apex touches the image border (tip cut by the left/right edge)")
    # axis direction from the midline over a longer stretch of the tip (up to 3x the
    # window height, bottom 30 % excluded), robust line fit against contamination
    slope = _midline_slope(mask, apex_r, hgt)
    apex_cols = np.nonzero(mask[apex_r])[0]
    theta = _perpendicular_cut_axis(mask, apex_r, apex_cols.mean(), np.arctan(slope), hgt)
    apex = np.array([(apex_r + 0.5) * f - 0.5, (apex_cols.mean() + 0.5) * f - 0.5])
    bbox = ((rr[0] * f, (apex_r + 1) * f), (left[has].min() * f, (right[has].max() + 1) * f))
    width = (right - left + 1.0)[::-1] * f
    return CoarseTip(apex, float(theta), 1.0, dark_level, width, bbox), flipped


def axis_tilt(z, left, right, keep=None):
    """Tilt (rad, small) and offset (px) of a body's axis from its silhouette x at cuts z.

    For an axis tilted by d_theta from the cut normal, the midpoint of the cut at
    height z is a + d_theta (z + r dr/dz) to first order (r = half width): the two
    flanks are sampled at heights shifted by -+ r d_theta.  The plain slope of the
    midpoints is biased by the factor 1 + d(r dr/dz)/dz, negative for flat tips
    (r dr/dz falls with z for n > 2), so a fixed-point iteration on it runs away from
    the axis.  r dr/dz = d(r^2)/dz / 2 from a cubic fit of r^2(z) over the ``keep``
    cuts.  Returns (tilt, offset, residuals of all midpoints)."""
    keep = np.ones(z.size, bool) if keep is None else keep
    mid, r = 0.5 * (left + right), 0.5 * (right - left)
    z0 = z[keep].mean()
    deg = int(min(3, keep.sum() - 2))
    rr_p = 0.5 * np.polyval(np.polyder(np.polyfit(z[keep] - z0, r[keep] ** 2, deg)), z - z0)
    A = np.column_stack([np.ones_like(z), z + rr_p])
    (off, tilt), *_ = np.linalg.lstsq(A[keep], mid[keep], rcond=None)
    return float(tilt), float(off), mid - A @ [off, tilt]


def _robust_slope(h, m, r):
    """``axis_tilt`` from cut midpoints ``m`` and half widths ``r``, outliers
    (contamination) rejected.  Started from all cuts, from the lower and from the upper half;
    a half's fit replaces the best so far where its median |residual| over all cuts is less than
    ``HALF_START_GAIN`` x the first's and by more than ``HALF_START_MIN_PX`` (clearly better: the
    midpoints lie on the block-averaged pixel grid, and near-equal fits must not swap on a
    rounding or on a faint layer the mask follows on one flank only).  A particle on one flank shifts
    a contiguous block of cuts, which a line through all of them absorbs by tilting, so that no
    cut looks like an outlier (a particle 45 nm up one flank held 30 of 108 cuts and the axis
    settled 7 deg off); a start from the half without it rejects the block."""
    best = None
    for start in (np.ones(h.size, bool), h <= np.median(h), h >= np.median(h)):
        keep = start
        if keep.sum() < 5:
            continue
        for _ in range(3):
            tilt, _, res = axis_tilt(h, m - r, m + r, keep)
            keep = np.abs(res) <= max(1.0, 3 * 1.4826 * np.median(np.abs(res[keep])))
        score = float(np.median(np.abs(res)))
        if best is None or score < min(HALF_START_GAIN * best[0], best[0] - HALF_START_MIN_PX):
            best = (score, tilt)
    return best[1]


HALF_START_GAIN = 0.5  # ``_robust_slope``: a half's start must halve the median |residual| ...
HALF_START_MIN_PX = 1.0  # ... and cut it by more than this (px of the block-averaged mask)


def _perpendicular_cut_axis(mask, apex_r, apex_c, theta, hgt, iters=6):
    """Axis angle from midpoints of cuts PERPENDICULAR to the current axis estimate.

    Horizontal cuts of a tilted body are not centred on its axis (the two flanks
    have different slopes in the image), cuts perpendicular to the axis are:
    iterate to the fixed point.  Boundary pixels 0.3-3 x ``hgt`` above the apex, and below the
    lowest height at which the mask touches the image's top or side edge (the cuts above are cut
    short by the border).
    """
    from scipy.ndimage import binary_erosion

    H, W = mask.shape
    bd = mask & ~binary_erosion(mask)
    bd[:, 0] = bd[:, -1] = bd[0, :] = False
    r, c = np.nonzero(bd)
    d = np.column_stack([r - apex_r, c - apex_c]).astype(float)
    # where the tip leaves the image (its top, or a flank through a side edge) the cuts above are
    # incomplete: their midpoints are not the axis (a wide tip leaving through a side pulled the
    # axis 58 degrees round onto a corner of its flat apex)
    edge = np.zeros_like(mask)
    edge[:, 0] = edge[:, -1] = edge[0, :] = True
    er, ec = np.nonzero(mask & edge)
    d_out = np.column_stack([er - apex_r, ec - apex_c]).astype(float)
    for _ in range(iters):
        u = np.array([-np.cos(theta), np.sin(theta)])
        v = np.array([np.sin(theta), np.cos(theta)])
        x, z = d @ v, d @ u
        z_out = float((d_out @ u).min()) - 1.0 if d_out.size else np.inf
        sel = (z > 0.3 * hgt) & (z < min(3 * hgt, z_out))
        if sel.sum() < 10:
            break
        b = np.floor(z[sel]).astype(int)
        b_min = b.min()
        b -= b_min
        lo = np.full(b.max() + 1, np.inf)
        hi = np.full(b.max() + 1, -np.inf)
        np.minimum.at(lo, b, x[sel])
        np.maximum.at(hi, b, x[sel])
        ok = np.isfinite(lo) & np.isfinite(hi) & (hi - lo > 2)
        if ok.sum() < 5:
            break
        zz = np.nonzero(ok)[0].astype(float) + b_min
        step = np.arctan(_robust_slope(zz, 0.5 * (lo[ok] + hi[ok]), 0.5 * (hi[ok] - lo[ok])))
        theta += step
        if abs(step) < 1e-4:
            break
    return theta


def saturated_pixels(win, min_fraction=SATURATED_FRACTION):
    """Pixels a saturated detector clipped (bool, ``win``'s shape), or None: those at the window's
    maximum where more than ``min_fraction`` of the window holds it AND it is a plateau, held by
    more than ``PLATEAU_RATIO`` times as many pixels as the next lower value.  An unclipped image
    reaches its maximum in a handful of pixels (a float image in one), and a quantised noise tail
    falls off towards it; an over-exposed vacuum (8- or 16-bit, the beam above full scale) piles up
    there."""
    top = float(np.max(win))
    at_top = win >= top
    n_top = int(np.count_nonzero(at_top))
    if n_top <= min_fraction * win.size:
        return None
    rest = win[~at_top]
    n_next = int(np.count_nonzero(win == rest.max())) if rest.size else 0
    return at_top if n_top > PLATEAU_RATIO * n_next else None


def clipped_plane_fit(A, vals):
    """Least-squares coefficients of ``A @ coef`` ~ ``vals`` (a plane: columns 1, row, col; or any
    surface linear in its coefficients), refitted three times on the values within 3 robust SDs
    (1.4826 x MAD) of the last fit."""
    keep = np.ones(vals.size, bool)
    for _ in range(3):
        Ak = A[keep]
        coef = np.linalg.solve(Ak.T @ Ak, Ak.T @ vals[keep])  # normal equations (3 x 3 for a plane)
        res = vals - A @ coef
        s = 1.4826 * np.median(np.abs(res[keep])) + 1e-12
        keep = np.abs(res) < 3 * s
    return coef


def flatten_background(win, saturated=None):
    """Divide by a plane fitted to the background pixels; returns (flat window, noise sigma).

    Removes slow illumination gradients so one iso-level follows the outer surface.
    ``saturated`` (``saturated_pixels``): the plateau of a clipped vacuum has no noise, so the
    noise is read from the pixels that are not clipped (``_unclipped_noise``).
    """
    from skimage.filters import threshold_otsu

    sm = ndimage.gaussian_filter(win, 2.0, mode="nearest")
    bgmask = sm > threshold_otsu(sm)
    rr, cc = np.nonzero(bgmask)
    A = np.column_stack([np.ones(rr.size), rr / win.shape[0], cc / win.shape[1]])
    coef = clipped_plane_fit(A, sm[bgmask])
    R, C = np.mgrid[0 : win.shape[0], 0 : win.shape[1]]
    plane = coef[0] + coef[1] * R / win.shape[0] + coef[2] * C / win.shape[1]
    flat = win / plane
    if saturated is not None:
        return flat, _unclipped_noise(flat, saturated)
    pair = bgmask[:, :-1] & bgmask[:, 1:]
    noise = 1.4826 * float(np.median(np.abs(np.diff(flat, axis=1)[pair]))) / np.sqrt(2)
    return flat, noise


def _unclipped_noise(flat, saturated):
    """Noise sigma at the flattened level 1 where the vacuum is clipped, from the pixels that are
    not (nor next to a clipped one), each scaled by the square root of its level (Poisson).

    Where the image is smooth (the 5 x 5 range of its sigma-1.5 smoothing below 10 % of its level:
    the tip's interior), horizontal pair differences, the estimator of the unclipped vacuum's
    (``flatten_background``): a detector PSF correlates neighbouring pixels and every estimator
    reads that differently, so the same one keeps the noise scale of saturated and unsaturated
    images alike.  With fewer than 200 such pairs (a nearly opaque tip: what is neither clipped nor
    dark lies on the edge, whose slope first differences would measure, 14-28x too high), the 3 x 3
    Laplacian mask of Immerkaer (1996; zero on any plane, sd 6 sigma on white noise; within 1.0-1.3x
    on such test images, lower where the noise is correlated)."""
    clip = ndimage.binary_dilation(saturated, np.ones((3, 3), bool))
    sm = ndimage.gaussian_filter(flat, 1.5, mode="nearest")
    smooth = ndimage.maximum_filter(sm, 5) - ndimage.minimum_filter(sm, 5) < 0.1 * np.abs(sm)
    level = 0.5 * (flat[:, :-1] + flat[:, 1:])
    ok = ~clip[:, :-1] & ~clip[:, 1:] & smooth[:, :-1] & smooth[:, 1:] & (level > 0.05)
    if np.count_nonzero(ok) >= 200:
        return 1.4826 * float(np.median(np.abs(np.diff(flat, axis=1))[ok] / np.sqrt(level[ok]))) / np.sqrt(2)
    lap = ndimage.convolve(flat, _LAPLACE_3X3, mode="nearest")
    level = ndimage.uniform_filter(flat, 3, mode="nearest")
    ok = ~clip & (level > 0.05)
    ok[[0, -1], :] = False
    ok[:, [0, -1]] = False
    if np.count_nonzero(ok) < 50:
        raise _Fail("the detector is saturated almost everywhere (fewer than 50 unclipped pixels to read the noise)")
    return 1.4826 * float(np.median(np.abs(lap[ok]) / np.sqrt(level[ok]))) / 6.0


def initial_contour(win, level, apex_hint, smooth=1.0):
    """Longest iso-contour at ``level`` passing near ``apex_hint`` (row, col), smoothed image."""
    from skimage.measure import find_contours

    sm = ndimage.gaussian_filter(win, smooth, mode="nearest")
    cs = find_contours(sm, level)
    if not cs:
        raise _Fail("no tip in the image (no edge near the apex)")
    d = [np.min(np.hypot(*(c - apex_hint).T)) for c in cs]
    best = [c for c, dd in zip(cs, d) if dd < 0.1 * max(win.shape) + 5]
    if not best:
        raise _Fail("no tip in the image (no edge near the apex)")
    return max(best, key=len)


def resample_curve(pts, step=1.0):
    """Resample a polyline (N, 2) at uniform arc length ``step`` (px)."""
    seg = np.hypot(*np.diff(pts, axis=0).T)
    s = np.concatenate([[0.0], np.cumsum(seg)])
    keep = np.concatenate([[True], seg > 1e-9])
    s, pts = s[keep], pts[keep]
    n = max(2, int(s[-1] / step) + 1)
    si = np.linspace(0.0, s[-1], n)
    return np.column_stack([np.interp(si, s, pts[:, 0]), np.interp(si, s, pts[:, 1])])


def curve_normals(pts, smooth=3.0):
    """Unit normals of a polyline, rotated +90 deg from the smoothed tangent."""
    sm = ndimage.gaussian_filter1d(pts, smooth, axis=0, mode="nearest")
    tan = np.gradient(sm, axis=0)
    tan /= np.hypot(*tan.T)[:, None] + 1e-12
    return np.column_stack([tan[:, 1], -tan[:, 0]]), tan


@dataclass
class TipFrame:
    """Tip coordinates: x = (p - apex) . v (lateral), z = (p - apex) . u (up the tip), px."""

    apex: np.ndarray
    angle: float

    @property
    def u(self):
        return np.array([-np.cos(self.angle), np.sin(self.angle)])

    @property
    def v(self):
        return np.array([np.sin(self.angle), np.cos(self.angle)])

    def to_tip(self, p):
        d = np.asarray(p, float) - self.apex
        return d @ self.v, d @ self.u

    def to_image(self, x, z):
        return self.apex + np.multiply.outer(x, self.v) + np.multiply.outer(z, self.u)


class BodyModel:
    """Axisymmetric body from a silhouette polyline: chord lengths at any point.

    Cross-section at height z: disk of radius rho(z) = (x_R - x_L)/2 centred at
    (x_R + x_L)/2 (exact for a body of revolution, the natural generalisation
    for slightly asymmetric tips).  Core = erosion of rho by c (px).
    """

    def __init__(self, frame, pts, coat_px=0.0):
        self.frame = frame
        x, z = frame.to_tip(pts)
        i0 = int(np.argmin(z))
        zl, xl = z[: i0 + 1][::-1], x[: i0 + 1][::-1]
        zr, xr = z[i0:], x[i0:]
        if np.median(xl) > np.median(xr):  # make "l" the -x flank
            zl, xl, zr, xr = zr, xr, zl, xl
        zl = np.maximum.accumulate(zl)
        zr = np.maximum.accumulate(zr)
        z0 = z[i0]
        top = min(zl[-1], zr[-1])
        self.dz = 0.1
        self.zg = np.arange(z0, max(top, z0 + 2 * self.dz) + 1e-9, self.dz)
        xlg = np.interp(self.zg, zl + 1e-9 * np.arange(zl.size), xl)
        xrg = np.interp(self.zg, zr + 1e-9 * np.arange(zr.size), xr)
        self.rho = np.maximum(0.5 * (xrg - xlg), 0.0)
        self.cen = 0.5 * (xrg + xlg)
        self.z0 = z0
        self.top = top
        self.set_coat(coat_px)

    def set_coat(self, coat_px):
        self.coat = float(coat_px)
        self.rho_core = core_radius_table(self.zg, self.rho, self.coat, self.dz) if self.coat > 0 else self.rho

    def _lookup(self, z, tables):
        """Linear interpolation on the uniform z grid (faster than np.interp); below = -1."""
        f = (z - self.zg[0]) / self.dz
        below = f < 0
        f = np.clip(f, 0.0, self.zg.size - 1.000001)
        i = f.astype(np.intp)
        w = f - i
        out = [t[i] * (1 - w) + t[i + 1] * w for t in tables]
        return out, below

    def chords(self, pts):
        x, z = self.frame.to_tip(pts)
        tabs = (self.rho, self.cen, self.rho_core) if self.coat > 0 else (self.rho, self.cen)
        vals, below = self._lookup(z, tabs)
        rho = np.where(below, -1.0, vals[0])
        t_o = chord(rho, x - vals[1])
        if self.coat > 0:
            return t_o, chord(np.where(below, -1.0, vals[2]), x - vals[1])
        return t_o, t_o


# Gauss-Hermite nodes for the tangential part of the 2-D Gaussian blur
_GH_X, _GH_W = np.polynomial.hermite_e.hermegauss(5)
_GH_W = _GH_W / _GH_W.sum()


class NormalSampler:
    """Intensity samples along the normals and the forward model on them."""

    def __init__(self, win, pts, normals, tangents, s_in, s_out, step=0.5):
        self.pts, self.nrm, self.tan = pts, normals, tangents
        self.s = np.arange(-s_in, s_out + 1e-9, step)
        q = pts[:, None, :] + self.s[None, :, None] * normals[:, None, :]
        self.I = ndimage.map_coordinates(win, [q[..., 0], q[..., 1]], order=3, mode="nearest")
        self.h = 0.4
        self.pad = 6.0
        self.u = np.arange(-s_in - self.pad, s_out + self.pad + 1e-9, self.h)

    def transmission(self, body, k_o, k_c, sigma, sel=slice(None)):
        """Blurred transmission on the fine grid u (rows = normals)."""
        p, n, t = self.pts[sel], self.nrm[sel], self.tan[sel]
        a = sigma * _GH_X
        q = (
            p[:, None, None, :]
            + self.u[None, :, None, None] * n[:, None, None, :]
            + a[None, None, :, None] * t[:, None, None, :]
        )
        t_o, t_c = body.chords(q.reshape(-1, 2))
        T = np.exp(-(k_o * t_o + (k_c - k_o) * t_c)).reshape(q.shape[:3]) @ _GH_W
        return ndimage.gaussian_filter1d(T, sigma / self.h, axis=1, mode="nearest") if sigma > 0 else T

    def model_at(self, Tf, delta):
        """Tf (N, U) sampled at s - delta; returns (N, S) by linear interpolation."""
        pos = (self.s[None, :] - delta[:, None] - self.u[0]) / self.h
        pos = np.clip(pos, 0, self.u.size - 1.000001)
        i = pos.astype(int)
        w = pos - i
        rows = np.arange(Tf.shape[0])[:, None]
        return Tf[rows, i] * (1 - w) + Tf[rows, i + 1] * w

    @staticmethod
    def affine(M, I):
        """Per-row least squares I ~ a + b M; returns a, b, residual (N, S)."""
        Mm, Im = M.mean(1, keepdims=True), I.mean(1, keepdims=True)
        dM, dI = M - Mm, I - Im
        b = (dM * dI).sum(1) / np.maximum((dM * dM).sum(1), 1e-30)
        a = Im[:, 0] - b * Mm[:, 0]
        return a, b, I - a[:, None] - b[:, None] * M


def fit_shifts(ns, Tf, delta0, sel=slice(None), iters=6, max_step=1.5, smooth_ab=0.0, lo=-np.inf, hi=np.inf):
    """Gauss-Newton for the per-normal shift delta (px); a, b (background, contrast)
    eliminated by linear least squares, optionally smoothed along the arc
    (``smooth_ab`` normals, Gaussian) since illumination varies slowly."""
    I = ns.I[sel]
    d = delta0.copy()
    for _ in range(iters):
        M = ns.model_at(Tf, d)
        a, b, r = ns.affine(M, I)
        dM = (ns.model_at(Tf, d + 0.05) - ns.model_at(Tf, d - 0.05)) / 0.1
        if smooth_ab > 0:
            a = ndimage.gaussian_filter1d(a, smooth_ab, mode="nearest")
            b = ndimage.gaussian_filter1d(b, smooth_ab, mode="nearest")
            r = I - a[:, None] - b[:, None] * M
            J = -b[:, None] * dM
        else:
            J = -b[:, None] * dM
            J = J - J.mean(1, keepdims=True)
        step = -(J * r).sum(1) / np.maximum((J * J).sum(1), 1e-30)
        d = np.clip(d + np.clip(step, -max_step, max_step), lo, hi)
    M = ns.model_at(Tf, d)
    a, b, r = ns.affine(M, I)
    if smooth_ab > 0:
        a = ndimage.gaussian_filter1d(a, smooth_ab, mode="nearest")
        b = ndimage.gaussian_filter1d(b, smooth_ab, mode="nearest")
        r = I - a[:, None] - b[:, None] * M
    return d, a, b, r


@dataclass
class EdgeFit:
    points: np.ndarray  # (N, 2) refined silhouette (row, col), window px
    normals: np.ndarray
    good: np.ndarray  # bool per point
    k_outer: float  # 1/px attenuation of the outer layer
    k_core: float
    coat_px: float
    sigma_px: float
    rms_intensity: float
    contrast: np.ndarray


def _axis_attenuation(win, body, background):
    """k (1/px) from the transmission on the axis 6-30 px above the apex (blur-free zone)."""
    z = body.zg
    ok = (body.rho > 5) & (z - z[0] > 6) & (z - z[0] < 30)
    if ok.sum() < 5 or not background > 0:
        return float("nan")
    pts = body.frame.to_image(body.cen[ok], z[ok])
    I = ndimage.map_coordinates(win, pts.T, order=1, mode="nearest")
    T = np.clip(I / background, 1e-3, 0.999)
    return float(np.median(-np.log(T) / (2 * body.rho[ok])))


def _shift_sigma(ns, Tf, d, b, r):
    """1-sigma precision (px) of each per-normal shift: s_res / sqrt(sum J^2)."""
    dM = (ns.model_at(Tf, d + 0.05) - ns.model_at(Tf, d - 0.05)) / 0.1
    J = b[:, None] * dM
    J = J - J.mean(1, keepdims=True)
    s_res = np.sqrt((r**2).sum(1) / max(1, r.shape[1] - 3))
    # samples every 0.5 px are interpolated from pixels: ~2 samples per independent pixel
    return s_res / np.sqrt(np.maximum((J * J).sum(1), 1e-30)) * np.sqrt(2.0)


def smooth_along(d, sigma):
    """Robust smoothing of per-normal shifts along the arc: median(5) then Gaussian(sigma) px."""
    d = ndimage.median_filter(d, size=5, mode="nearest")
    return ndimage.gaussian_filter1d(d, sigma, mode="nearest") if sigma > 0 else d


class _GlobalSearch:
    """The global parameters of ``refine_edges``: residuals for (log k_o, log sigma[, log k_c, log c])
    with the shifts fitted on a subset of the normals and smoothed along the arc, their bounded
    least squares, and the choice single layer vs coated.  ``body`` and ``lo_shift`` are the
    caller's current ones (it replaces them between iterations)."""

    def __init__(self, ns, body, sub, step_sub, smooth, lo_shift, k_est, k_lim, coat_hint, s_in):
        self.ns, self.body, self.sub, self.step_sub = ns, body, sub, step_sub
        self.smooth, self.lo_shift = smooth, lo_shift
        self.k_est, (self.k_lo, self.k_hi), self.coat_hint, self.s_in = k_est, k_lim, coat_hint, s_in
        k_lo, k_hi = k_lim
        self.lb1, self.ub1 = [np.log(k_lo), np.log(0.25)], [np.log(k_hi), np.log(6.0)]
        self.lb2 = [np.log(1e-4), self.lb1[1], np.log(k_lo), np.log(0.5)]  # outer layer may be much lighter
        self.ub2 = [self.ub1[0], self.ub1[1], np.log(k_hi), np.log(s_in + 3)]

    def glob_resid(self, p, with_coat):
        """Residuals for global (k_o, sigma[, k_c, c]) with shifts fitted, then smoothed
        along the arc like the final edge (no per-normal freedom to fit noise)."""
        ns, body, sub = self.ns, self.body, self.sub
        k_o_, sig_ = np.exp(p[0]), np.exp(p[1])
        if with_coat:
            k_c_, c_ = np.exp(p[2]), np.exp(p[3])
            body.set_coat(c_)
        else:
            k_c_ = k_o_
            body.set_coat(0.0)
        Tf = ns.transmission(body, k_o_, k_c_, sig_, sub)
        d, _, _, _ = fit_shifts(ns, Tf, np.zeros(len(sub)), sel=sub, iters=4, lo=self.lo_shift)
        d = smooth_along(d, self.smooth / self.step_sub)
        M = ns.model_at(Tf, d)
        return ns.affine(M, ns.I[sub])[2].ravel()

    def cost(self, p, with_coat):
        r = self.glob_resid(p, with_coat)
        return float(r @ r)

    def refine(self, p0, with_coat):
        lb, ub = (self.lb2, self.ub2) if with_coat else (self.lb1, self.ub1)
        p0 = np.clip(p0, np.add(lb, 1e-6), np.subtract(ub, 1e-6))
        from scipy import optimize  # the "normals" refinement only: kept out of the profiles job's start-up

        res = optimize.least_squares(
            self.glob_resid, p0, args=(with_coat,), bounds=(lb, ub), diff_step=1e-3, max_nfev=20
        )
        return 0.5 * float(res.fun @ res.fun), res.x

    def choose_globals(self, x1):
        """Single layer vs coated (outer layer k_o, core k_c, normal thickness c px)."""
        coat_hint, k_est, k_lo, k_hi, s_in = self.coat_hint, self.k_est, self.k_lo, self.k_hi, self.s_in
        c1, x1 = self.refine(x1, False)
        best = (c1, x1, False)
        if coat_hint is None or coat_hint > 0:
            kr = k_est if np.isfinite(k_est) else np.exp(x1[0])
            cands = [
                (np.log(kr * fo), x1[1], np.log(np.clip(kr * fc, k_lo, k_hi)), np.log(c))
                for c in ([coat_hint] if coat_hint else (1.5, 4.0, 8.0))
                for fo in (0.1, 0.35)
                for fc in (0.7, 1.5)
                if c < s_in + 3
            ]
            p2 = min(cands, key=lambda p: self.cost(p, True))
            c2, x2 = self.refine(p2, True)
            ko2, kc2, cc2 = np.exp(x2[0]), np.exp(x2[2]), np.exp(x2[3])
            physical = 1.5 * ko2 < kc2 and ko2 > 0.05 * kc2 and 1.0 < cc2 < s_in + 2
            if coat_hint or (c2 < 0.85 * c1 and physical):
                best = (c2, x2, True)
        _, x, with_coat = best
        k_o, sigma = np.exp(x[0]), np.exp(x[1])
        k_c, coat = (np.exp(x[2]), np.exp(x[3])) if with_coat else (k_o, 0.0)
        return k_o, k_c, coat, sigma


def _outward_normals(win, pts):
    """Normals and tangents of the curve, the normals pointing towards the brighter background."""
    nrm, tan = curve_normals(pts)
    # outward = towards brighter background
    q_out = pts + 2 * nrm
    q_in = pts - 2 * nrm
    io = ndimage.map_coordinates(win, q_out.T, order=1, mode="nearest")
    ii = ndimage.map_coordinates(win, q_in.T, order=1, mode="nearest")
    if np.median(io - ii) < 0:
        nrm, tan = -nrm, -tan
    return nrm, tan


def refine_edges(
    win, pts, frame, coat_hint=None, outer_iters=4, smooth_px=2.0, smooth_ab=0.0, frame_update=None, target_px=0.15
):
    """Model-based sub-pixel silhouette along the normals (see module doc).

    ``smooth_px``: minimum Gaussian smoothing of the edge shifts along the arc
    (px, 1-px contour spacing); raised adaptively (up to 12 px) until the
    smoothed shift precision reaches ``target_px``.
    """
    pts = resample_curve(pts, 1.0)
    nrm, tan = _outward_normals(win, pts)
    s_in, s_out = 10.0, 6.0
    body = BodyModel(frame, pts)
    sigma, k_o, k_c, coat = 1.0, 0.02, 0.02, 0.0
    ns = NormalSampler(win, pts, nrm, tan, s_in, s_out)
    N = len(pts)
    step_sub = max(1, N // 60)
    sub = np.arange(0, N, step_sub)

    moved = pts.copy()
    # physical prior on the attenuation: axis transmission vs background with zero
    # offset, T = exp(-k 2 rho); k is bounded to [0.25, 4] x this estimate
    k_est = _axis_attenuation(win, body, np.median(ns.I[:, -3:]))
    k_lo, k_hi = (max(1e-4, 0.2 * k_est), min(2.0, 5.0 * k_est)) if np.isfinite(k_est) else (1e-4, 2.0)
    k_o = float(np.clip(k_o, k_lo, k_hi))
    # prior: the initial contour is an iso-level just below the background, so the
    # OUTER surface lies at most a few px inside it (a stronger core edge further in
    # must not capture the fit); relaxed once the model has settled
    gs = _GlobalSearch(ns, body, sub, step_sub, smooth_px, -2.5, k_est, (k_lo, k_hi), coat_hint, s_in)

    for it in range(outer_iters):
        if it == 0:  # coarse grid (single layer), then model choice (globals on a subset)
            grid = [
                (np.log(k), np.log(sg)) for k in np.geomspace(k_lo * 1.01, k_hi * 0.99, 6) for sg in (0.6, 1.2, 2.2)
            ]
            k_o, k_c, coat, sigma = gs.choose_globals(np.array(min(grid, key=lambda p: gs.cost(p, False))))
        elif it == 1:  # edges now close: refine the choice
            k_o, k_c, coat, sigma = gs.choose_globals(np.log([k_o, sigma]))
        body.set_coat(coat)
        Tf = ns.transmission(body, k_o, k_c, sigma)
        delta, a, b, r = fit_shifts(ns, Tf, np.zeros(N), smooth_ab=smooth_ab, lo=gs.lo_shift)
        # adaptive smoothing along the arc: per-normal shift precision from the
        # Gauss-Newton curvature; smooth enough to reach ~target_px (>= smooth_px)
        sig_d = _shift_sigma(ns, Tf, delta, b, r)
        s_eff = float(np.clip((np.median(sig_d) / target_px) ** 2 / (2 * np.sqrt(np.pi)), smooth_px, 12.0))
        delta = smooth_along(delta, s_eff)
        gs.smooth = s_eff
        # move the silhouette along the (fixed) sampling normals, rebuild the body
        moved = moved + delta[:, None] * nrm
        gs.lo_shift = -2.5 if it < 1 else -1.0
        if frame_update is not None and it < 2:
            frame = frame_update(moved)
        body = gs.body = BodyModel(frame, ndimage.gaussian_filter1d(moved, 2.0, axis=0, mode="nearest"), coat)
    rms = np.sqrt((r**2).mean(1))
    off = ((moved - pts) * nrm).sum(1)
    good = (b > 0) & (off > -s_in + 2) & (off < s_out - 1) & (rms < 5 * np.median(rms))
    return EdgeFit(moved, nrm, good, k_o, k_c, coat, sigma, float(np.median(rms)), b)
