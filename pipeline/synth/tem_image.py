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

``expected_tem_image`` is the noise-free image (before noise, scale bar and
quantisation) with the geometry, illumination and material as explicit inputs
and an optional outer-profile override; ``pipeline.synth.tem_fisher`` builds the
Cramér-Rao bound of n on it.
"""

from __future__ import annotations

import math

import cv2
import numpy as np
from scipy import ndimage

from pipeline.tem.projection import chord, eroded_radius

__all__ = [
    "power_law_radius",
    "outer_radius",
    "radius_tables",
    "expected_tem_image",
    "axis_contrast",
    "background_dose",
    "render_tem_image",
    "write_tem_tiff",
]


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


def radius_tables(n, Q, pixel_size, shape, coating_thickness=0.0, outer=None, cone_above=25e-9):
    """Cross-section tables ``(zt, r_outer, r_core)`` (m) used by the renderer.

    Uniform grid zt (step pixel_size/20) from below the apex to 1.5 (H + W) pixel
    sizes above it; r_outer = ``outer(zt)`` if given (a callable z -> r, m; use a
    negative radius where there is no material) else ``outer_radius``; r_core its
    erosion by ``coating_thickness`` (= r_outer without coating).
    """
    H, W = shape
    zmax = (H + W) * pixel_size * 1.5
    dz = pixel_size / 20.0
    zt = np.arange(-max(coating_thickness, dz) - 2 * dz, zmax + 2 * dz, dz)
    ro = outer_radius(zt, n, Q, cone_above) if outer is None else np.asarray(outer(zt), float)
    rc = eroded_radius(zt, ro, coating_thickness) if coating_thickness > 0 else ro
    return zt, ro, rc


def silhouette_band(m_out, m_core, width=3):
    """Pixels within ``width`` px of the outer or core silhouette (supersampled there)."""
    st = np.ones((3, 3), bool)
    band = np.zeros(m_out.shape, bool)
    for m in (m_out, m_core):
        band |= ndimage.binary_dilation(m, st, width) & ~ndimage.binary_erosion(m, st, width)
    return band


def expected_tem_image(
    n,
    Q,
    pixel_size,
    shape,
    apex_px,
    *,
    rotation_deg=0.0,
    blur_sigma_px=1.0,
    coating_thickness=0.0,
    orientation="down",
    lambda_core=40e-9,
    lambda_coat=120e-9,
    background=1.0,
    gradient=0.04,
    gradient_perp=0.0,
    supersample=5,
    contamination=False,
    contamination_height=35e-9,
    cone_above=25e-9,
    outer=None,
    tables=None,
    band=None,
    band_width=3,
    return_band=False,
):
    """Noise-free expected image relative to the background (before noise, scale bar, quantisation).

    Expected counts are this times the background dose N_bg.  apex_px: (row, col)
    of the apex, floats, pixel centres at integers; rotation_deg: tip axis rotated
    counter-clockwise as displayed; blur_sigma_px: Gaussian sigma (px);
    lambda_core/lambda_coat: attenuation lengths (m); illumination (before the
    blur) = background * (1 + gradient (0.8 u + 0.6 v) + gradient_perp (0.6 u - 0.8 v))
    with u = col/W - 0.5, v = row/H - 0.5 (two free linear-gradient amplitudes).
    The outer profile is ``outer_radius(z, n, Q, cone_above)`` unless ``outer``
    (callable z -> r, m) or ``tables`` ((zt, r_outer, r_core) as from
    ``radius_tables``) overrides it; n and Q then only place the contamination blob.
    band: boolean (H, W) mask of the supersampled pixels (default: within
    ``band_width`` px of a silhouette at pixel centres).  Returns the image (and
    the band if ``return_band``).
    """
    H, W = shape
    px = float(pixel_size)
    th = math.radians(rotation_deg)
    r_a, c_a = float(apex_px[0]), float(apex_px[1])
    if orientation not in ("down", "up"):
        raise ValueError(f"orientation must be 'down' or 'up', got {orientation!r}")
    sgn = 1.0 if orientation == "down" else -1.0
    if tables is None:
        tables = radius_tables(n, Q, px, shape, coating_thickness, outer, cone_above)
    zt, ro_t, rc_t = tables
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
    if band is None:
        band = silhouette_band(m_out, m_core, band_width)
    _supersample_band(clean, band, attenuation, int(supersample))
    # weak illumination gradient, then blur (optics) on the transmitted intensity
    u, v = cols / W - 0.5, rows / H - 0.5
    illum = 1.0 + (gradient * (u * 0.8 + v * 0.6) + gradient_perp * (u * 0.6 - v * 0.8))
    img = clean * (illum * background)
    if blur_sigma_px and blur_sigma_px > 0:
        img = ndimage.gaussian_filter(img, blur_sigma_px, mode="nearest")
    return (img, band) if return_band else img


def _supersample_band(clean, band, attenuation, ss):
    """Replace the transmission of the pixels of ``band`` (in place) by the mean over ss x ss
    sub-pixels (where the projected thickness has its square-root kink)."""
    sub = (np.arange(ss) + 0.5) / ss - 0.5
    rb, cb = np.nonzero(band)
    rr = rb[:, None, None] + sub[None, :, None]
    cc = cb[:, None, None] + sub[None, None, :]
    att_b, _ = attenuation(rr, cc)
    clean[rb, cb] = np.exp(-att_b).mean(axis=(1, 2))


def axis_contrast(tables, lambda_core, lambda_coat, z=3e-9):
    """1 - T on the tip axis at height z (m) above the apex (noise free, no blur)."""
    zt, ro_t, rc_t = tables
    ro3 = float(np.interp(z, zt, ro_t))
    rc3 = float(np.interp(z, zt, rc_t))
    t_core3 = 2 * max(rc3, 0.0)
    att3 = (2 * ro3 - t_core3) / lambda_coat + t_core3 / lambda_core
    return 1.0 - math.exp(-att3)


def background_dose(edge_snr, contrast):
    """Background counts per pixel N_bg = (edge_snr / contrast)^2 of the Poisson model."""
    return (edge_snr / contrast) ** 2


def _apex_position(shape, apex_frac, orientation, rng):
    """The apex (row, col): at ``apex_frac`` of the image with a random sub-pixel offset so
    tests do not sit on pixel centres (row mirrored for ``orientation`` "up")."""
    H, W = shape
    r_a = apex_frac[0] * H + rng.uniform(-0.5, 0.5)
    c_a = apex_frac[1] * W + rng.uniform(-0.5, 0.5)
    if orientation == "up":
        r_a = H - 1 - r_a
    elif orientation != "down":
        raise ValueError(f"orientation must be 'down' or 'up', got {orientation!r}")
    return r_a, c_a


def _as_dtype(noisy, dtype, maxval):
    """The image in ``dtype`` (integers: rounded and clipped to 0..maxval)."""
    if np.issubdtype(dtype, np.integer):
        return np.clip(np.rint(noisy), 0, maxval).astype(dtype)
    return noisy.astype(dtype)


def render_tem_image(
    n,
    Q,
    pixel_size,
    shape=(512, 512),
    blur_sigma_px=1.0,
    edge_snr=20.0,
    rotation_deg=3.0,
    coating_thickness=0.0,
    orientation="down",
    seed=0,
    *,
    apex_frac=(0.68, 0.5),
    lambda_core=40e-9,
    lambda_coat=120e-9,
    noise="poisson",
    background_counts=None,
    dtype=np.uint16,
    supersample=5,
    scale_bar=True,
    contamination=False,
    contamination_height=35e-9,
    gradient=0.04,
    S=1.0,
    cone_above=25e-9,
):
    """Render a side-view TEM image of a tip whose outer profile is z = r^n/(nQ) (Eq. 1).

    n: power index; Q: m^(n-1); pixel_size: m; blur_sigma_px: Gaussian sigma (px);
    edge_snr: see module doc (``None`` or ``inf`` = noise free); rotation_deg: tip
    axis rotated counter-clockwise as displayed; coating_thickness: m along the
    normal; orientation: "down" (apex at the bottom of the tip) or "up".
    Returns ``(image, truth)``; truth holds n, Q, R (from Eq. 2 with S), S,
    pixel_size, rotation_deg, apex_px (row, col; pixel centres at integers),
    orientation, coating_thickness, blur_sigma_px, edge_snr, noise_sigma.
    The noise-free image is ``expected_tem_image`` (times ``truth["background"]``).
    """
    rng = np.random.default_rng(seed)
    px = float(pixel_size)
    r_a, c_a = _apex_position(shape, apex_frac, orientation, rng)

    tables = radius_tables(n, Q, px, shape, coating_thickness, cone_above=cone_above)
    img = expected_tem_image(
        n,
        Q,
        px,
        shape,
        (r_a, c_a),
        rotation_deg=rotation_deg,
        blur_sigma_px=blur_sigma_px,
        coating_thickness=coating_thickness,
        orientation=orientation,
        lambda_core=lambda_core,
        lambda_coat=lambda_coat,
        gradient=gradient,
        supersample=supersample,
        contamination=contamination,
        contamination_height=contamination_height,
        tables=tables,
    )
    # reference contrast on the axis 3 nm above the apex (noise free, no blur)
    contrast = axis_contrast(tables, lambda_core, lambda_coat)

    maxval = np.iinfo(dtype).max if np.issubdtype(dtype, np.integer) else 1.0
    bg = background_counts if background_counts is not None else 0.8 * maxval / (1 + gradient)
    noisy, sigma_noise = _with_noise(img, bg, edge_snr, noise, contrast, rng)
    if scale_bar:
        _draw_scale_bar(noisy, px, orientation)
    out = _as_dtype(noisy, dtype, maxval)
    R = (Q / S ** (n - 2)) ** (1.0 / (n - 1))
    truth = dict(
        n=float(n),
        Q=float(Q),
        R=float(R),
        S=float(S),
        pixel_size=px,
        rotation_deg=float(rotation_deg),
        apex_px=(float(r_a), float(c_a)),
        orientation=orientation,
        coating_thickness=float(coating_thickness),
        blur_sigma_px=float(blur_sigma_px),
        edge_snr=float(edge_snr) if edge_snr else float("inf"),
        noise_sigma=float(sigma_noise),
        background=float(bg),
        cone_above=float(cone_above),
        lambda_core=float(lambda_core),
        lambda_coat=float(lambda_coat),
        seed=int(seed),
    )
    return out, truth


def _with_noise(img, bg, edge_snr, noise, contrast, rng):
    """(image in counts with noise, the noise sigma at the background): Poisson counts with
    sigma_bg = sqrt(N_bg), N_bg = (snr / contrast)^2, or Gaussian noise; none for an SNR of None/inf."""
    if edge_snr is None or not np.isfinite(edge_snr):
        return img * bg, 0.0
    if noise == "poisson":
        nbg = background_dose(edge_snr, contrast)
        counts = rng.poisson(img * nbg).astype(float)
        return counts * (bg / nbg), bg / math.sqrt(nbg)
    sigma_noise = bg * contrast / edge_snr
    return img * bg + rng.normal(0.0, sigma_noise, img.shape), sigma_noise


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


def _draw_scale_bar(img, px, orientation):
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
    cv2.putText(
        mask,
        label,
        (margin, top - h - 2),
        cv2.FONT_HERSHEY_SIMPLEX,
        scale,
        255,
        max(1, int(round(scale * 2))),
        cv2.LINE_AA,
    )
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
    tifffile.imwrite(
        path, image, imagej=True, resolution=(ppu, ppu), metadata={"unit": "nm" if unit == "nm" else "micron"}
    )
