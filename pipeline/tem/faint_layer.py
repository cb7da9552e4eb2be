"""Is there a faint outer layer beyond the fitted edge, and how faint a layer could the image show?

The silhouette fit (``silhouette_fit``) sees pixels from ~3 blur sigma + 4 px outside its starting
contour; a thick light layer (a DLC coating 2-20 nm whose attenuation is 5-30 % of the core's)
that the contour did not follow lies outside those pixels, and the fit then reports the core's
edge as the tip's.  This test looks there, in the image itself:

- pixels: outside the fitted outer edge on both flanks, between ``Z_RANGE`` x the profile height
  (away from the apex, where the normal is near horizontal), from ``d0`` to the thickest layer tested
  plus ``VACUUM_MARGIN_NM``.  ``d0`` = 3 sigma + 2 px (the fitted blur's reach) + ``FRINGE_NM``, or
  as far as the image is significantly BRIGHTER than the vacuum further out (a Fresnel fringe: a
  layer only darkens) + ``FRINGE_NM``;
- template: for a layer of normal thickness T over the fitted body (a body of revolution: section
  disk of the two flanks' mean radius, centred between them; the layer widens it by
  T sqrt(1 + rho'^2)), the chord through the layer at each pixel, blurred with the fitted Gaussian;
  the image is background x (1 - A x chord) for a layer attenuation A (1/px), linear in A for faint
  layers.  A is fitted by linear least squares together with the background (illumination: a
  quadratic in row and column, for the gradient and vignetting) and smooth edge tails (the body's
  silhouette blurred by ``TAIL_SCALES_NM``, per flank: detector PSF tails, fringes), once for both
  flanks and once with an A per flank (same background);
- noise: robust SD of the residuals, inflated by their pixel-to-pixel correlation (variance of 2 x 2
  block means against the white-noise value);
- a layer is SEEN where, for some T, A / SE(A) >= ``Z_DETECT`` (both flanks) and >= ``Z_FLANK`` on
  each flank, the weaker flank's A is at least ``FLANK_RATIO`` of the stronger's (a coating dims
  both flanks alike, a particle or a fringe on one does not), no thicker template has
  A / SE < -``Z_FLANK`` (a dark band followed by a bright one is a fringe), and the contrast is at
  least ``MIN_CONTRAST``.  Contrast = A / k_core, k_core the core's attenuation read through the
  axis (-ln(I / background) over the chord, median over 0.5-0.95 x the profile height; the fit's
  where that cannot be read); thickness (beyond the fitted edge) = the best template's T;
- the LIMIT: the contrast a layer of thickness T beyond the edge needs to be seen with probability
  >= 90 %: max((Z_DETECT + 1.64) SE, (Z_FLANK + 1.64) SE_flank) / k_core (each condition at
  95 %), at least ``MIN_CONTRAST``;
- a saturated vacuum (clipped at full scale) hides a faint layer: not tested, and said so.

Layers reaching less than ``d0`` beyond the fitted edge lie in the fitted pixels: they are the coating
search's (``coating_search``).  Measured on the independent wave-optical simulator
(``benchmarks/bench_faint_layer.py``).  Except where a bright band (a Fresnel fringe) pushes ``d0`` out:
the coating search sees ~3 sigma + 4 px beyond its starting contour, so a layer whose outer surface lies
between there and ``d0`` is seen by neither.  The band's width is ``bright_band`` (m), and where it is
wider than ``BRIGHT_BAND_NM`` the note says so; ``pipeline.tem.profiles`` carries ``d0`` / 2 as a
common offset SD of the edge where a faint layer also dims the window.  At one sign of the defocus
(overfocus, on the wave-optical benchmark's images) the bright band of a weak phase object (a DLC layer)
lies INSIDE its outer surface: of the 26 used images of the three image sets whose band is wider than
2 nm, 9 have their edge 1.4-5.8 nm inside a DLC layer, all of them in overfocus.
"""

from __future__ import annotations

import numpy as np
from scipy import ndimage

__all__ = ["faint_layer_test", "LIMIT_THICKNESS_NM"]

THICKNESS_NM = (1.0, 1.5, 2.0, 3.0, 4.0, 5.0, 7.0, 10.0, 14.0, 20.0)  # layer thicknesses tested (nm)
LIMIT_THICKNESS_NM = (2.0, 5.0, 10.0, 20.0)  # thicknesses whose limit is stated
# thresholds set on the independent simulator (module doc): with no layer beyond the fitted edge the
# largest A / SE of 82 images was 5.05 (a 1.6 % "layer", flanks 3.0 and 5.0), the next 4.8 (flanks 3.7)
Z_DETECT = 6.0  # both flanks together: A / SE(A) of the best template to claim a layer
Z_FLANK = 2.5  # ... and on each flank (same background)
FLANK_RATIO = 0.15  # the weaker flank's layer attenuation at least this share of the stronger's (module doc)
MIN_CONTRAST = 0.03  # no layer claimed or promised below this attenuation ratio: the background model's own error
Z_POWER = 1.64  # one-sided 95 % quantile: each of the two conditions met with 95 % (together ~90 %)
Z_RANGE = (0.3, 0.95)  # heights (x profile height) of the pixels tested
VACUUM_MARGIN_NM = 6.0  # vacuum beyond the thickest layer tested, for the illumination background
FRINGE_NM = 1.5  # left out beyond the edge's blur: Fresnel fringes (sqrt(lambda df) ~ 1-2 nm at 0.5-2 um)
TAIL_SCALES_NM = (0.7, 1.5)  # edge-tail nuisance blurs (nm): PSF tails, Fresnel fringes (~sqrt(lambda df))
SATURATED_MAX = 0.05  # share of the tested pixels at the image's maximum above which the vacuum is clipped
# a bright band wider than this beyond the edge's blur (a Fresnel fringe, ``_bright_reach``; the width as
# measured, which reads a band up to ~0.6 nm wide: block pixels and the blur's tail) is a blind zone where a
# layer's outer surface could hide from both tests; 2 nm: the thinnest layer whose detection limit is stated
BRIGHT_BAND_NM = 2.0
TEST_PIXEL_NM = 0.4  # finer images are tested on b x b block means (b = floor(0.4 nm / pixel)): a 1-20 nm
# layer's template is smooth on that scale, and the test's cost no longer grows with the pixel count


def _flank_geometry(pts, frame, hpx):
    """Per-height section of the fitted body on a 1 px grid of z: (z, centre, radius, slope
    d radius / dz), window px, tip frame; None where a flank has too few points."""
    x, z = frame.to_tip(pts)
    zg = np.arange(0.0, hpx + 1.0, 1.0)
    rad = []
    for m in (x < 0, x >= 0):
        m = m & (z >= -1) & (z <= 1.05 * hpx + 2)
        if m.sum() < 10:
            return None
        o = np.argsort(z[m], kind="stable")
        zz, rr = z[m][o], np.maximum.accumulate(np.abs(x[m][o]))
        rad.append(np.interp(zg, zz, rr))
    rl, rr = rad
    centre = 0.5 * (rr - rl)
    rho = 0.5 * (rr + rl)
    slope = np.gradient(ndimage.uniform_filter1d(rho, 5, mode="nearest"), zg)
    return zg, centre, rho, slope


def _region(img, origin, pts, extent, b=1):
    """(row slice, column slice) of the image region around the edge points (window px) grown by
    ``extent`` px, whole ``b`` x ``b`` blocks, and the region's corner in window px."""
    p = pts + origin
    r0 = int(max(0, np.floor(p[:, 0].min() - extent)))
    r1 = int(min(img.shape[0], np.ceil(p[:, 0].max() + extent) + 1))
    c0 = int(max(0, np.floor(p[:, 1].min() - extent)))
    c1 = int(min(img.shape[1], np.ceil(p[:, 1].max() + extent) + 1))
    r1, c1 = r0 + (r1 - r0) // b * b, c0 + (c1 - c0) // b * b
    return (slice(r0, r1), slice(c0, c1)), np.array([r0, c0], float) - origin


def _block_means(data, b):
    """Means of the ``b`` x ``b`` blocks of ``data`` (its shape a multiple of b)."""
    if b == 1:
        return data
    h, w = data.shape
    return data.reshape(h // b, b, w // b, b).mean(axis=(1, 3))


def _window_px(R, C, corner, b):
    """Window px (row, column) of the centres of block-pixels (R, C) of the region."""
    off = 0.5 * (b - 1)
    return np.column_stack([np.ravel(R) * b + off + corner[0], np.ravel(C) * b + off + corner[1]])


def _pixel_geometry(shape, corner, frame, geo, b=1):
    """Tip-frame height z, lateral distance from the section centre |x - c| and the section's
    radius and slope (all in image px) at every block-pixel (``b`` x ``b`` image px) of the region."""
    zg, centre, rho, slope = geo
    R, C = np.mgrid[0 : shape[0], 0 : shape[1]]
    x, z = frame.to_tip(_window_px(R, C, corner, b))
    zc = np.clip(z, zg[0], zg[-1])
    xc = np.abs(x - np.interp(zc, zg, centre))
    return (
        z.reshape(shape),
        xc.reshape(shape),
        np.interp(zc, zg, rho).reshape(shape),
        np.interp(zc, zg, slope).reshape(shape),
    )


def _templates(pix, t_px, sigma):
    """Blurred chord (px) through a layer of normal thickness ``t_px`` over the fitted body at every
    pixel of the region: one map per thickness."""
    z, xc, rho, slope = pix
    inside = np.sqrt(np.clip(rho**2 - xc**2, 0, None))
    out = []
    for t in t_px:
        th = t * np.sqrt(1.0 + slope**2)
        ch = 2.0 * (np.sqrt(np.clip((rho + th) ** 2 - xc**2, 0, None)) - inside)
        out.append(ndimage.gaussian_filter(ch, sigma, mode="nearest"))
    return out


def _noise_correlation(res_map, valid):
    """Variance inflation of means over many pixels from the residuals' short-range correlation:
    4 var(2 x 2 block means) / var(pixels), over blocks of valid pixels (>= 1)."""
    h, w = (res_map.shape[0] // 2) * 2, (res_map.shape[1] // 2) * 2
    r = np.where(valid, res_map, 0.0)[:h, :w]
    v = valid[:h, :w]
    blk = r.reshape(h // 2, 2, w // 2, 2).sum(axis=(1, 3))
    full = v.reshape(h // 2, 2, w // 2, 2).all(axis=(1, 3))
    if full.sum() < 50:
        return 1.0
    pv = float(np.var(res_map[valid]))
    return float(max(1.0, np.var(blk[full] / 4.0) * 4.0 / max(pv, 1e-300)))


def _normal_equations(vals, nuisance):
    """The nuisance columns (scaled to unit maximum; tails that vanish this far out dropped) and
    their blocks N^T N, N^T v of the normal equations, shared by every template."""
    ns = np.abs(nuisance).max(axis=0)
    keep = ns > 1e-6 * ns.max()
    N = nuisance[:, keep] / ns[keep]
    return N, N.T @ N, N.T @ vals


def _amplitude(vals, shared, g, side):
    """Least-squares layer attenuation A (1/px) and its unit-noise SE, on both flanks together and,
    with the same background and edge tails, on each flank: ((A, s), (A_left, s_left), (A_right,
    s_right)) with s = SE / noise SD (the background alone would absorb a thick layer on one flank).
    ``shared``: ``_normal_equations`` of the nuisance columns."""
    N, NtN, Ntv = shared
    gs = max(float(np.abs(g).max()), 1e-300)
    out = []
    for cols in ([g], [g * (side < 0), g * (side > 0)]):
        G = np.column_stack(cols) / gs
        NtG = N.T @ G
        XtX = np.block([[NtN, NtG], [NtG.T, G.T @ G]])
        try:
            inv = np.linalg.inv(XtX)
        except np.linalg.LinAlgError:
            out += [(np.nan, np.nan)] * len(cols)
            continue
        a = inv @ np.concatenate([Ntv, G.T @ vals])
        k = len(cols)
        out += [(float(a[-k + j]) / gs, float(np.sqrt(max(inv[-k + j, -k + j], 0.0))) / gs) for j in range(k)]
    return out


def _edge_tails(pix, side, valid, plane, scales_px):
    """Nuisance columns for what lies just outside the fitted edge besides a layer (the detector
    PSF's tail, a Fresnel fringe, a blur the Gaussian does not describe): the body's silhouette
    blurred by each of ``scales_px``, on each flank separately, at the valid pixels."""
    z, xc, rho, slope = pix
    body = (xc < rho).astype(float)
    cols = []
    for sc in scales_px:
        b = ndimage.gaussian_filter(body, sc, mode="nearest")[valid] * plane
        cols += [b * (side < 0), b * (side > 0)]
    return np.column_stack(cols)


def _axis_attenuation(data, pix, plane_map, hpx):
    """Mean attenuation (1/px) of the body through its axis: -ln(I / background) / chord at the
    pixels within 0.3 x the radius of the axis, 0.5-0.95 x the profile height up (median)."""
    z, xc, rho, slope = pix
    m = (xc < 0.3 * rho) & (z >= 0.5 * hpx) & (z <= 0.95 * hpx) & (rho > 2)
    if m.sum() < 20:
        return float("nan")
    ratio = np.clip(data[m] / plane_map[m], 1e-6, None)
    return float(np.median(-np.log(ratio) / (2.0 * np.sqrt(rho[m] ** 2 - xc[m] ** 2))))


def _background_fit(vals, plane_cols):
    """(fitted background, residuals, robust residual SD) of the background columns ``plane_cols``
    fitted to ``vals`` (three passes dropping pixels > 4 SD off: particles, shank contamination)."""
    keep = np.ones(vals.size, bool)
    for _ in range(3):
        coef, *_ = np.linalg.lstsq(plane_cols[keep], vals[keep], rcond=None)
        res = vals - plane_cols @ coef
        s = 1.4826 * float(np.median(np.abs(res[keep]))) + 1e-12
        keep = np.abs(res) < 4 * s
    return plane_cols @ coef, res, s


def background_and_noise(data, valid):
    """The quadratic illumination background of the ``valid`` pixels of ``data`` (``_background_fit``):
    (its columns, its values, the robust residual SD, that SD inflated by the residuals' correlation)."""
    vals = data[valid]
    R, C = np.nonzero(valid)
    scale = max(data.shape)
    rn, cn = R / scale - 0.5, C / scale - 0.5
    plane_cols = np.column_stack([np.ones(vals.size), rn, cn, rn**2, rn * cn, cn**2])
    plane, res, s_noise = _background_fit(vals, plane_cols)
    if np.all(vals == np.round(vals)):
        s_noise = max(s_noise, 1.0 / np.sqrt(12.0))  # integer counts: the rounding step
    res_map = np.zeros(data.shape)
    res_map[valid] = res
    return plane_cols, plane, s_noise, s_noise * np.sqrt(_noise_correlation(res_map, valid))


def faint_layer_test(img, origin, pts, frame, sigma_px, k_body, hpx, pixel_size, coat_model="single"):
    """The faint-layer test and the detection limit (module doc) of one fitted silhouette.

    ``img``: the image (tip pointing down, as fitted); ``origin``: the fit window's corner in it;
    ``pts``: fitted outer edge (window px); ``frame``: its symmetry frame; ``sigma_px``: fitted blur;
    ``k_body``: fitted attenuation of the body (1/px); ``hpx``: profile height (px).
    Returns a dict (lengths in m, contrasts as fractions of the core's attenuation, ``note`` in
    words); ``tested`` False with ``note`` where the image leaves no room for the test."""
    px = float(pixel_size)
    geo = _flank_geometry(np.asarray(pts, float), frame, hpx)
    if geo is None or not (k_body > 0):
        return dict(tested=False, note="faint-layer test not done (too few edge points on a flank)")
    nm = 1e-9 / px
    b = max(1, int(TEST_PIXEL_NM / (px * 1e9) + 1e-9))
    extent = 1.3 * max(THICKNESS_NM) * nm + 3 * sigma_px + VACUUM_MARGIN_NM * nm
    sl, corner = _region(img, origin, np.asarray(pts, float), extent, b)
    data = _block_means(np.asarray(img[sl], float), b)
    pix = _pixel_geometry(data.shape, corner, frame, geo, b)
    z, xc, rho, slope = pix
    d = (xc - rho) / np.sqrt(1.0 + slope**2)  # normal distance outside the fitted edge (image px)
    band = (z >= Z_RANGE[0] * hpx) & (z <= Z_RANGE[1] * hpx)
    d_blur = 3.0 * sigma_px + 2.0
    bright = _bright_reach(data, d, band, d_blur, nm, b) - d_blur  # the bright band beyond the blur (px)
    d0 = d_blur + bright + FRINGE_NM * nm
    t_px = [t * nm for t in THICKNESS_NM if t * nm >= d0 + 1.0]
    if not t_px:
        out = dict(tested=False, note=f"faint-layer test not done (no layer thicker than {d0 / nm:.1f} nm tested)")
    else:
        valid = (d >= d0) & band
        # the blur in block-pixels: the fitted Gaussian's and the block average's (variance (b^2 - 1)/12 px^2)
        sigma_b = float(np.sqrt(sigma_px**2 + (b * b - 1) / 12.0)) / b
        ctx = (sigma_b, k_body, px, d0, corner, frame, coat_model, hpx, b, bright)
        out = _test_and_limit(data, pix, d, valid, t_px, ctx)
    out["bright_band"] = bright * px
    return out


def _bright_reach(data, d, band, d_blur, nm, b=1):
    """How far (image px) beyond the fitted edge the image is significantly BRIGHTER than the vacuum
    further out (a Fresnel fringe; a layer only darkens): the largest bin of distance (``b`` image px:
    one block-pixel) within 6 nm whose mean exceeds the vacuum 6-12 nm out by 4 SE (``d_blur`` where
    none does)."""
    far = band & (d >= d_blur + 6 * nm) & (d < d_blur + 12 * nm)
    if far.sum() < 50:
        return d_blur
    level, sd = float(np.median(data[far])), 1.4826 * float(np.median(np.abs(data[far] - np.median(data[far]))))
    near = band & (d >= d_blur) & (d < d_blur + 6 * nm)
    k = np.floor((d[near] - d_blur) / b).astype(int)
    n = np.bincount(k)
    mean = np.bincount(k, data[near]) / np.maximum(n, 1)
    # 2x the white-noise SE: neighbouring pixels are correlated (detector PSF)
    bright = (n >= 10) & (mean - level > 4.0 * 2.0 * sd / np.sqrt(np.maximum(n, 1)))
    return d_blur + (b * (float(np.nonzero(bright)[0].max()) + 1.0) if bright.any() else 0.0)


def _test_and_limit(data, pix, d, valid, t_px, ctx):
    """The fits of ``faint_layer_test`` over the valid pixels: result dict."""
    sigma_b, k_body, px, d0, corner, frame, coat_model, hpx, b, bright = ctx
    if valid.sum() < 200:
        return dict(tested=False, note="faint-layer test not done (too little vacuum beside the tip in the image)")
    R, C = np.nonzero(valid)
    side_x, _ = frame.to_tip(_window_px(R, C, corner, b))
    vals = data[valid]
    clipped = float(np.mean(vals >= data.max()))
    if clipped > SATURATED_MAX:
        return dict(
            tested=False,
            note=f"faint-layer test not done: the vacuum beside the tip is saturated ({100 * clipped:.0f} % of its "
            "pixels at full scale), which hides a faint layer's dimming",
        )
    plane_cols, plane, s_noise, s_eff = background_and_noise(data, valid)
    maps = _templates(pix, t_px, sigma_b)
    tails = _edge_tails(pix, side_x, valid, plane, [s_nm * 1e-9 / px / b for s_nm in TAIL_SCALES_NM])
    shared = _normal_equations(vals, np.column_stack([plane_cols, tails]))
    rows = []
    for t, g in zip(t_px, maps):
        (a, s), (al, sl_), (ar, sr) = _amplitude(vals, shared, -plane * g[valid], side_x)
        rows.append((t, a, s * s_eff, al, sl_ * s_eff, ar, sr * s_eff))
    # the core's attenuation: through the axis where that can be read, else the fitted body's
    R_all, C_all = np.mgrid[0 : data.shape[0], 0 : data.shape[1]]
    scale = max(data.shape)
    rn, cn = R_all / scale - 0.5, C_all / scale - 0.5
    coef, *_ = np.linalg.lstsq(plane_cols, plane, rcond=None)
    plane_map = np.stack([np.ones_like(rn), rn, cn, rn**2, rn * cn, cn**2], -1) @ coef
    k_axis = _axis_attenuation(data, pix, plane_map, hpx)
    k_core = k_axis if np.isfinite(k_axis) and k_axis > 0 else k_body
    out = _statement(np.array(rows), k_core, px, (d0, bright), coat_model, max_d=float(d[valid].max()))
    out.update(core_attenuation=k_core / px, body_attenuation=k_body / px)
    return out


def _statement(rows, k_core, px, start, coat_model, max_d):
    """Decision, limits and the note in words from the per-thickness rows
    (T px, A, SE, A_left, SE_left, A_right, SE_right); ``start``: (d0, the bright band's width), image px."""
    d0, bright = start
    t, a, se, al, sel, ar, ser = rows.T
    zc, zl, zr = a / se, al / sel, ar / ser
    seen = (zc >= Z_DETECT) & (np.minimum(zl, zr) >= Z_FLANK) & (a / k_core >= MIN_CONTRAST)
    # a layer darkens every template at least as thick as itself; a Fresnel fringe's dark band is
    # followed by a bright one, which turns the thicker templates' A negative
    seen &= np.array([zc[j:].min() >= -Z_FLANK for j in range(zc.size)])
    # a coating dims both flanks alike; a particle or a fringe on one flank does not
    seen &= np.minimum(al, ar) >= FLANK_RATIO * np.maximum(al, ar)
    limit = np.maximum((Z_DETECT + Z_POWER) * se, (Z_FLANK + Z_POWER) * np.maximum(sel, ser)) / k_core
    limit = np.maximum(limit, MIN_CONTRAST)
    t_nm = t * px * 1e9
    out = dict(
        tested=True,
        start=d0 * px,
        reach=max_d * px,
        thickness=t * px,
        contrast_limit=limit,
        z_both=zc,
        z_left=zl,
        z_right=zr,
        se_both=se / k_core,
        se_flank=np.maximum(sel, ser) / k_core,
        contrast_left=al / k_core,
        contrast_right=ar / k_core,
        found=bool(seen.any()),
    )
    lim_at = {T: float(np.interp(T, t_nm, limit)) for T in LIMIT_THICKNESS_NM if t_nm[0] <= T <= t_nm[-1]}
    out["limit_table"] = lim_at
    where = "beyond the fitted (coated) outer edge" if coat_model == "coated" else "beyond the fitted edge"
    if seen.any():
        j = int(np.argmax(np.where(seen, zc, -np.inf)))
        c = float(a[j] / k_core)
        sure = min(zl[j], zr[j]) >= Z_DETECT
        # seen on each flank alone: the fitted profile is the core's (stage 2 flags it edge_is_core)
        out.update(found_thickness=float(t[j] * px), found_contrast=c, found_z=float(zc[j]), edge_is_core=bool(sure))
        out["note"] = (
            f"a faint outer layer of ~{t_nm[j]:.0f} nm (contrast {100 * c:.0f} % of the core's, {zc[j]:.1f} SD; "
            f"left {zl[j]:.1f}, right {zr[j]:.1f}) is seen {where}: the profile "
            + (
                "is the core's, not the tip's outer surface"
                if sure
                else "may be the core's, not the tip's outer surface"
            )
        )
        return out
    lim_words = ", ".join(f"{T:g} nm: {100 * v:.0f} %" for T, v in lim_at.items())
    head = min(lim_at) if lim_at else float(t_nm[0])
    # every layer thicker than ``head`` must be seen: the largest limit from there on
    worst = float(max(np.interp(head, t_nm, limit), limit[t_nm >= head].max(initial=0.0)))
    out["contrast_limit_beyond"] = worst
    out["limit_from"] = head * 1e-9
    out["note"] = (
        f"no coating found {where}; a layer thicker than {head:g} nm with contrast above "
        f"{100 * worst:.0f} % of the core's would have been seen "
        f"(90 % detection; {lim_words}; " + _nearer_layers(d0 * px, bright * px)
    )
    return out


def _nearer_layers(start, band):
    """The note's words on layers nearer the edge than ``start`` (m), the test's first distance; ``band``
    (m): the bright band beyond the edge's blur that pushed it out (``_bright_reach``)."""
    if band <= BRIGHT_BAND_NM * 1e-9:
        return f"layers within {start * 1e9:.1f} nm of the edge are the coating test's)"
    return (
        f"the coating test sees ~3 blur sigma + 4 px beyond its start, and the image is brighter than the "
        f"vacuum up to {band * 1e9:.1f} nm beyond the edge's blur (a Fresnel fringe): a layer whose outer surface "
        f"lies within {start * 1e9:.1f} nm of the edge is seen by neither test)"
    )
