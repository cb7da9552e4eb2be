"""Synthetic side-view TEM image of a power-law AFM tip with known truth.

Geometry (tip frame, SI metres): the OUTER surface, the one that touches the
sample, is the power law of paper Eq. 1, z = r^n / (n Q), up to ``cone_above``
(default 25 nm above the apex, well above a 6 nm fit window); above that the
radius continues along the tangent cone (C1 join), so the shank widens linearly.
An optional lighter coating (DLC, native oxide) of constant thickness along the
surface normal lies INSIDE that outer surface: the core is the morphological
erosion of the outer body (``pipeline.tem.projection.eroded_radius``).

Contrast: Beer-Lambert through the projected thickness of the body of
revolution, T = exp(-t_coat/lambda_coat - t_core/lambda_core), computed
analytically at ``supersample``^2 points per pixel and averaged (no thresholded
mask), then a Gaussian blur (sigma in px), noise and an 8/16-bit quantisation.
Extras: slight in-plane rotation, a scale bar with a cv2.putText label, an
optional contamination blob far above the apex, a weak illumination gradient.

Edge SNR: (background - intensity on the tip axis 3 nm above the apex, noise
free) / noise standard deviation at the background level.
"""
from __future__ import annotations

import math

import cv2
import numpy as np
from scipy import ndimage

from pipeline.tem.projection import chord, eroded_radius

__all__ = ["power_law_radius", "outer_radius", "render_tem_image", "write_tem_tiff"]


def power_law_radius(z, n, Q):
    """r(z) = (n Q z)^(1/n) for z >= 0 (inverse of Eq. 1), 0 below; SI."""
    z = np.asarray(z, float)
    return np.power(n * Q * np.maximum(z, 0.0), 1.0 / n)


def outer_radius(z, n, Q, cone_above=25e-9):
    """Outer tip radius (m): power law below ``cone_above``, tangent cone above."""
    z = np.asarray(z, float)
    r = power_law_radius(np.minimum(z, cone_above), n, Q)
    if cone_above is not None and np.isfinite(cone_above):
        rb = float(power_law_radius(cone_above, n, Q))
        slope = rb / (n * cone_above)  # dr/dz of the power law at the join
        r = np.where(z > cone_above, rb + (z - cone_above) * slope, r)
    return np.where(z < 0, -1.0, r)


def _radius_tables(n, Q, zmax, dz, coating):
    zt = np.arange(-max(coating, dz) - 2 * dz, zmax + 2 * dz, dz)
    ro = outer_radius(zt, n, Q)
    rc = eroded_radius(zt, ro, coating) if coating > 0 else ro
    return zt, ro, rc


def render_tem_image(n, Q, pixel_size, shape=(512, 512), blur_sigma_px=1.0, edge_snr=20.0,
                     rotation_deg=3.0, coating_thickness=0.0, orientation="down", seed=0, *,
                     apex_frac=(0.68, 0.5), lambda_core=40e-9, lambda_coat=120e-9,
                     noise="poisson", background_counts=None, dtype=np.uint16, supersample=5,
                     scale_bar=True, contamination=False, contamination_height=35e-9,
                     gradient=0.04, S=1.0, cone_above=25e-9):
    """Render a side-view TEM image of a tip whose outer profile is z = r^n/(nQ) (Eq. 1).

    n: power index; Q: m^(n-1); pixel_size: m; blur_sigma_px: Gaussian sigma (px);
    edge_snr: see module doc (``None`` or ``inf`` = noise free); rotation_deg: tip
    axis rotated counter-clockwise as displayed; coating_thickness: m along the
    normal; orientation: "down" (apex at the bottom of the tip) or "up".
    Returns ``(image, truth)``; truth holds n, Q, R (from Eq. 2 with S), S,
    pixel_size, rotation_deg, apex_px (row, col; pixel centres at integers),
    orientation, coating_thickness, blur_sigma_px, edge_snr, noise_sigma.
    """
    rng = np.random.default_rng(seed)
    H, W = shape
    px = float(pixel_size)
    th = math.radians(rotation_deg)
    # apex position with a random sub-pixel offset so tests do not sit on pixel centres
    r_a = apex_frac[0] * H + rng.uniform(-0.5, 0.5)
    c_a = apex_frac[1] * W + rng.uniform(-0.5, 0.5)
    if orientation == "up":
        r_a = H - 1 - r_a
    elif orientation != "down":
        raise ValueError(f"orientation must be 'down' or 'up', got {orientation!r}")
    sgn = 1.0 if orientation == "down" else -1.0

    zmax = (H + W) * px * 1.5
    dz = px / 20.0
    zt, ro_t, rc_t = _radius_tables(n, Q, zmax, dz, coating_thickness)

    cos_t, sin_t = math.cos(th), math.sin(th)

    def attenuation(rr, cc):
        """Beer-Lambert exponent at image points (row, col), exact projection."""
        dx = (cc - c_a) * px
        dy = sgn * (r_a - rr) * px  # "up" along the tip body
        x = dx * cos_t + dy * sin_t
        z = -dx * sin_t + dy * cos_t
        t_out = chord(np.interp(z, zt, ro_t, left=-1.0), x)
        t_core = t_out
        if coating_thickness > 0:
            t_core = chord(np.interp(z, zt, rc_t, left=-1.0), x)
            att = (t_out - t_core) / lambda_coat + t_core / lambda_core
        else:
            att = t_out / lambda_core
        if contamination:
            att = att + _blob_attenuation(x, z, n, Q, contamination_height, lambda_coat)
        return att, (t_out > 0, t_core > 0)

    # pixel centres everywhere, then ss x ss supersampling of the pixels within
    # 3 px of an outer/core silhouette (where T(x) has the square-root kink)
    rows, cols = np.mgrid[0:H, 0:W].astype(float)
    att, (m_out, m_core) = attenuation(rows, cols)
    clean = np.exp(-att)
    st = np.ones((3, 3), bool)
    band = np.zeros((H, W), bool)
    for m in (m_out, m_core):
        band |= ndimage.binary_dilation(m, st, 3) & ~ndimage.binary_erosion(m, st, 3)
    ss = int(supersample)
    sub = (np.arange(ss) + 0.5) / ss - 0.5
    rb, cb = np.nonzero(band)
    rr = rb[:, None, None] + sub[None, :, None]
    cc = cb[:, None, None] + sub[None, None, :]
    att_b, _ = attenuation(rr, cc)
    clean[rb, cb] = np.exp(-att_b).mean(axis=(1, 2))
    # weak illumination gradient, then blur (optics) on the transmitted intensity
    illum = 1.0 + gradient * ((cols / W - 0.5) * 0.8 + (rows / H - 0.5) * 0.6)
    img = clean * illum
    if blur_sigma_px and blur_sigma_px > 0:
        img = ndimage.gaussian_filter(img, blur_sigma_px, mode="nearest")

    # reference contrast on the axis 3 nm above the apex (noise free, no blur)
    z3 = 3e-9
    ro3 = float(np.interp(z3, zt, ro_t))
    rc3 = float(np.interp(z3, zt, rc_t))
    t_core3 = 2 * max(rc3, 0.0)
    att3 = (2 * ro3 - t_core3) / lambda_coat + t_core3 / lambda_core
    contrast = 1.0 - math.exp(-att3)

    maxval = np.iinfo(dtype).max if np.issubdtype(dtype, np.integer) else 1.0
    bg = background_counts if background_counts is not None else 0.8 * maxval / (1 + gradient)
    if edge_snr is None or not np.isfinite(edge_snr):
        noisy = img * bg
        sigma_noise = 0.0
    elif noise == "poisson":
        # Poisson counts: sigma_bg = sqrt(N_bg) with N_bg = (snr / contrast)^2
        nbg = (edge_snr / contrast) ** 2
        counts = rng.poisson(img * nbg).astype(float)
        noisy = counts * (bg / nbg)
        sigma_noise = bg / math.sqrt(nbg)
    else:
        sigma_noise = bg * contrast / edge_snr
        noisy = img * bg + rng.normal(0.0, sigma_noise, img.shape)

    if scale_bar:
        _draw_scale_bar(noisy, px, orientation, maxval)
    if np.issubdtype(dtype, np.integer):
        out = np.clip(np.rint(noisy), 0, maxval).astype(dtype)
    else:
        out = noisy.astype(dtype)
    R = (Q / S ** (n - 2)) ** (1.0 / (n - 1))
    truth = dict(n=float(n), Q=float(Q), R=float(R), S=float(S), pixel_size=px,
                 rotation_deg=float(rotation_deg), apex_px=(float(r_a), float(c_a)),
                 orientation=orientation, coating_thickness=float(coating_thickness),
                 blur_sigma_px=float(blur_sigma_px), edge_snr=float(edge_snr) if edge_snr else float("inf"),
                 noise_sigma=float(sigma_noise), background=float(bg), cone_above=float(cone_above),
                 lambda_core=float(lambda_core), lambda_coat=float(lambda_coat), seed=int(seed))
    return out, truth


def _blob_attenuation(x, z, n, Q, height, lam):
    """Ellipsoidal amorphous-carbon blob stuck on the right flank at ``height``."""
    a, b = 6e-9, 4e-9
    x0 = float(outer_radius(height, n, Q)) + 0.6 * a
    q = 1.0 - ((x - x0) / a) ** 2 - ((z - height) / b) ** 2
    return 2.0 * a * np.sqrt(np.maximum(q, 0.0)) / lam


def _nice_length(target):
    exp = math.floor(math.log10(target))
    for m in (5, 2, 1):
        if m * 10**exp <= target:
            return m * 10**exp
    return 10**exp


def _draw_scale_bar(img, px, orientation, maxval):
    """Dark bar + label in the lower-left (apex side) corner, drawn in place."""
    H, W = img.shape
    length = _nice_length(0.2 * W * px)
    npx = int(round(length / px))
    h = max(3, H // 100)
    margin = max(8, W // 30)
    top = H - margin - h if orientation == "down" else margin + 2 * h + max(12, H // 25)
    mask = np.zeros((H, W), np.uint8)  # cv2.putText draws on 8-bit images only
    cv2.rectangle(mask, (margin, top), (margin + npx, top + h), 255, thickness=-1)
    label = f"{length * 1e9:g} nm"
    scale = max(0.35, H / 1000.0)
    cv2.putText(mask, label, (margin, top - h - 2), cv2.FONT_HERSHEY_SIMPLEX, scale, 255,
                max(1, int(round(scale * 2))), cv2.LINE_AA)
    img *= 1.0 - mask / 255.0


def write_tem_tiff(path, image, pixel_size, unit="nm"):
    """Write ``image`` as TIFF with the pixel size in the resolution tags.

    unit "nm" or "um": ImageJ-style (XResolution = pixels per unit, ``unit=`` in
    the ImageJ description); unit "cm": plain TIFF with ResolutionUnit CENTIMETER.
    """
    import tifffile

    if unit == "cm":
        ppu = 1.0 / (pixel_size * 100.0)
        tifffile.imwrite(path, image, resolution=(ppu, ppu), resolutionunit="CENTIMETER")
        return
    factor = {"nm": 1e9, "um": 1e6}[unit]
    ppu = 1.0 / (pixel_size * factor)
    tifffile.imwrite(path, image, imagej=True, resolution=(ppu, ppu),
                     metadata={"unit": "nm" if unit == "nm" else "micron"})
