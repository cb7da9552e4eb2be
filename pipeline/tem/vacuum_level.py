"""The vacuum's illumination where a thick faint layer fills the fit window's "background".

``edges.flatten_background`` divides the window by a plane fitted to its pixels brighter than the
Otsu threshold of the window.  A thick light layer (a DLC coating 2-20 nm whose attenuation is 5-30 %
of the core's) is brighter than that threshold, so its pixels join the vacuum's and pull the plane
down: on the independent wave-optical simulator (``pipeline.synth.tem_wave``) the vacuum 3-10 nm
beyond the true outer surface read 1.00 +- 0.01 of the plane on uncoated and oxidised tips but
1.01-1.12 on DLC-coated ones, so the iso-level 2 % below the plane (``profiles._edge_level``) lay
inside the layer, where its dimming is only a few per cent, and the starting contour wandered
through the layer (end-to-end tip 1043: the reference's edge 2.5 nm inside, W_A +96 %).

This module reads the vacuum where no layer can be: pixels of a region around the window (padded
by ``PAD_NM`` where the image allows, on ~0.5 nm block means) further than ``LAYER_MAX_NM`` +
``MARGIN_NM`` from the region's Otsu mask of the tip (the core: a layer is lighter than that
threshold).  Two surfaces are fitted to them:

- a quadratic one **decides**: where it stands more than ``MIN_GAIN`` above the window's plane over
  the background within ``LAYER_MAX_NM`` of the mask (where a layer would be), the window's plane
  took a layer in;
- the plane **flattens**: there the window is divided by the far vacuum's plane instead of its own;
  elsewhere (no dim band: uncoated and oxidised tips, thin layers) the window's flattening is kept.

The quadratic reads the vacuum next to the tip through the illumination's curvature, which the plane
extrapolated from the far vacuum carries: under vignetting (the simulator's 0-10 %) the plane stood
-3.1 to +1.5 % off the window's on an uncoated tip and read a 3 % layer as -0.1 to +4.7 %, the
quadratic -0.3 to +0.1 % and +2.8 to +3.2 % (helper-5's synthetic images); on one of our own
model's images (a 4 % gradient, SNR 10) the plane read +1.9 %, the quadratic +0.7 %.  But the
quadratic, extrapolated into the tip's body where no far vacuum is, bent the contour of end-to-end
tip 1043's reference into a loop when the window was divided by it, so the plane flattens.  A test
of the near-tip background's own dimming could not tell a layer from the tip's semi-transparent
periphery (the Otsu mask lies nanometres inside the edge of a weakly absorbing tip: uncoated tips
read 7-16 %).  Not read where more than ``MAX_CLIPPED_SHARE`` of the region's blocks hold a pixel at
the image's maximum (a clipped vacuum is no surface to read).
"""

from __future__ import annotations

import numpy as np
from scipy import ndimage

from pipeline.tem.edges import clipped_plane_fit

__all__ = ["vacuum_flattening"]

LAYER_MAX_NM = 25.0  # thickest layer that may dim the window's background (the DLC: 2-20 nm)
MARGIN_NM = 5.0  # beyond it: the layer's blur and Fresnel fringes
PAD_NM = 35.0  # the region read around the window (nm), where the image allows
MIN_FAR_PIXELS = 2000  # fewer far pixels than this: the vacuum is not read (the window's plane is kept)
MAX_CLIPPED_SHARE = 0.01  # more of the region's blocks clipped than this: not read (a saturated vacuum)
# the vacuum's quadratic surface must stand this much above the window's plane next to the tip: on the
# independent simulator's images (bench_tem_independent: the grid, the held-out and the DLC sets)
# uncoated tips read -0.5 to +0.7 %, oxidised ones up to +1.9 % (1-2 nm layers), DLC-coated ones mostly
# 1-20 %.  At 1.5 % the DLC sets did as well (grid image 56 recovered, five DLC edges better by > 0.05 nm),
# but 7 oxidised intervals of the end-to-end study (bench_wear_test_wave) were flattened too, one of them
# then 2.7 sigma_n off (2 such intervals at 2 %, both closer to their true n)
MIN_GAIN = 0.02


def _plane_terms(rr, cc, shape):
    """Columns of a plane in rows / shape[0], cols / shape[1] at rows ``rr`` and columns ``cc``."""
    return np.stack([np.ones_like(rr), rr / shape[0], cc / shape[1]], axis=-1)


def _quadratic_terms(rr, cc, shape):
    """Columns of a quadratic surface in rows / shape[0], cols / shape[1] (``_plane_terms`` and their
    squares and product)."""
    a, b = rr / shape[0], cc / shape[1]
    return np.stack([np.ones_like(rr), a, b, a * a, a * b, b * b], axis=-1)


def _surface_fit(terms, vals, rr, cc, shape):
    """Surface ``terms`` (``_plane_terms`` or ``_quadratic_terms``) fitted to ``vals`` at window px
    ``rr``, ``cc`` with the 3-sigma clipping of ``edges.flatten_background``'s own plane."""
    return clipped_plane_fit(terms(rr, cc, shape), vals)


def _region_blocks(img, bounds, px):
    """The region around the window (module doc) on ~0.5 nm block means: (smoothed blocks, the tip's
    Otsu mask, distance (image px) from it, blocks holding a clipped pixel, b, the region's corner
    in window px), or None where it is under 8 blocks a side."""
    from skimage.filters import threshold_otsu

    r0, r1, c0, c1 = bounds
    H, W = img.shape
    nm = 1e-9 / px
    pad = int(np.ceil(PAD_NM * nm))
    R0, R1, C0, C1 = max(0, r0 - pad), min(H, r1 + pad), max(0, c0 - pad), min(W, c1 + pad)
    b = max(1, int(round(0.5 * nm)))  # ~0.5 nm blocks: the surface and the distances need no finer grid
    reg = np.asarray(img[R0:R1, C0:C1], float)
    hb, wb = reg.shape[0] // b, reg.shape[1] // b
    if hb < 8 or wb < 8:
        return None
    rows = reg[: hb * b, : wb * b].reshape(hb, b, wb * b)  # reduced along the rows first: 2-3x faster
    blocks = rows.sum(axis=1).reshape(hb, wb, b).sum(axis=2) / (b * b)
    # blocks holding a pixel at the image's maximum (a clipped detector) are no reading of the vacuum
    clipped = rows.max(axis=1).reshape(hb, wb, b).max(axis=2) >= float(np.max(img))
    sm = ndimage.gaussian_filter(blocks, max(1.0, 2.0 / b), mode="nearest")
    tip = sm < threshold_otsu(sm)
    dist = ndimage.distance_transform_edt(~tip) * b
    return sm, tip, dist, clipped, b, (R0 - r0, C0 - c0)


def _window_px(mask, b, corner):
    """Window px (rows, cols) of the centres of the blocks in ``mask``."""
    rr, cc = np.nonzero(mask)
    return (rr + 0.5) * b - 0.5 + corner[0], (cc + 0.5) * b - 0.5 + corner[1]


def _plane_on_window(plane, shape):
    """The plane ``plane`` (``_plane_terms``) on every pixel of a window of ``shape``."""
    Rg, Cg = np.mgrid[0 : shape[0], 0 : shape[1]]
    return _plane_terms(Rg.astype(float), Cg.astype(float), shape) @ plane


def _gain_over_window(win, flat, terms, coefs, rwn, cwn):
    """Median ratio - 1 of the vacuum's surface (``terms`` @ ``coefs``) to the window's own plane
    (recovered as ``win`` / ``flat``) at the pixels of the near-tip blocks at ``rwn``, ``cwn`` inside the
    window; NaN where fewer than 20 are."""
    inside = (rwn >= 0) & (rwn <= win.shape[0] - 1) & (cwn >= 0) & (cwn <= win.shape[1] - 1)
    if inside.sum() < 20:
        return np.nan
    iw, jw = np.round(rwn[inside]).astype(int), np.round(cwn[inside]).astype(int)
    vacuum = terms(iw.astype(float), jw.astype(float), win.shape) @ coefs
    with np.errstate(divide="ignore", invalid="ignore"):
        ratio = vacuum * flat[iw, jw] / np.asarray(win, float)[iw, jw]
    return float(np.nanmedian(ratio) - 1.0)


def vacuum_flattening(img, bounds, win, flat, px):
    """``flat`` = ``win`` / (the window's plane), or ``win`` / (the far vacuum's plane) where a dim band
    (a thick light layer) pulled the window's plane down (module doc).

    ``img``: the image (as the window was cut from it); ``bounds``: (r0, r1, c0, c1) of the window in
    it; ``px``: pixel size (m).  Returns (flat, info): ``info["gain"]`` the median ratio - 1 of the
    far vacuum's quadratic surface to the window's plane over the near-tip background (what decides),
    ``info["plane_gain"]`` that of the far vacuum's plane (what the window is divided by, so its noise
    is in units of 1 + plane_gain of the window's), ``info["used"]`` whether the far plane replaced the
    window's, ``info["note"]`` in words where it did; ``flat`` is returned unchanged otherwise."""
    nothing = dict(gain=np.nan, plane_gain=np.nan, used=False)
    got = _region_blocks(img, bounds, px)
    if got is None:
        return flat, nothing
    sm, tip, dist, clipped, b, corner = got
    nm = 1e-9 / px
    if np.count_nonzero(clipped) > MAX_CLIPPED_SHARE * clipped.size:
        # a clipped vacuum: the illumination's bright part is cut flat, no surface to read (grid image 31:
        # 3 % of the region clipped, the far plane 2.9 % above the near vacuum of an oxidised tip)
        return flat, nothing
    far = (~tip) & (dist >= (LAYER_MAX_NM + MARGIN_NM) * nm) & ~clipped
    near = (~tip) & (dist < LAYER_MAX_NM * nm) & ~clipped
    if far.sum() * b * b < MIN_FAR_PIXELS or near.sum() < 20:
        return flat, nothing
    rw, cw = _window_px(far, b, corner)
    near_px = _window_px(near, b, corner)
    quad = _surface_fit(_quadratic_terms, sm[far], rw, cw, win.shape)
    plane = _surface_fit(_plane_terms, sm[far], rw, cw, win.shape)
    gain = _gain_over_window(win, flat, _quadratic_terms, quad, *near_px)
    plane_gain = _gain_over_window(win, flat, _plane_terms, plane, *near_px)
    if not gain > MIN_GAIN:
        return flat, dict(gain=gain, plane_gain=plane_gain, used=False)
    note = (
        f"the window's background was {100 * gain:.1f} % below the vacuum read beyond "
        f"{LAYER_MAX_NM + MARGIN_NM:g} nm of the tip: a faint layer filled it; the window is flattened on that vacuum"
    )
    out = np.asarray(win, float) / _plane_on_window(plane, win.shape)
    return out, dict(gain=gain, plane_gain=plane_gain, used=True, note=note)
