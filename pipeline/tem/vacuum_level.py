"""The vacuum's illumination where a thick faint layer fills the fit window's "background".

``edges.flatten_background`` divides the window by a plane fitted to its pixels brighter than the
Otsu threshold of the window.  A thick light layer (a DLC coating 2-20 nm whose attenuation is 5-30 %
of the core's) is brighter than that threshold, so its pixels join the vacuum's and pull the plane
down: on the independent wave-optical simulator (``pipeline.synth.tem_wave``) the vacuum 3-10 nm
beyond the true outer surface read 1.00 +- 0.01 of the plane on uncoated and oxidised tips but
1.01-1.09 on DLC-coated ones, so the iso-level 2 % below the plane (``profiles._edge_level``) lay
inside the layer, where its dimming is only a few per cent, and the starting contour wandered
through the layer (end-to-end tip 1043: the reference's edge 2.5 nm inside, W_A +96 %).

This module reads the vacuum where no layer can be: pixels of a region around the window (padded
by ``PAD_NM`` where the image allows) further than ``LAYER_MAX_NM`` + ``MARGIN_NM`` from the region's
Otsu mask of the tip (the core: a layer is lighter than that threshold), and fits the same plane
to them.  Where that plane stands more than ``MIN_GAIN`` above the window's over the pixels near
the tip (within ``LAYER_MAX_NM`` of the mask: where a layer would be), the window is divided by it
instead; elsewhere (no dim band: uncoated and oxidised tips, thin layers) the window's flattening is
kept as it is.
"""

from __future__ import annotations

import numpy as np
from scipy import ndimage

__all__ = ["vacuum_flattening"]

LAYER_MAX_NM = 25.0  # thickest layer that may dim the window's background (the DLC: 2-20 nm)
MARGIN_NM = 5.0  # beyond it: the layer's blur and Fresnel fringes
PAD_NM = 35.0  # the region read around the window (nm), where the image allows
MIN_FAR_PIXELS = 2000  # fewer far pixels than this: the vacuum is not read (the window's plane is kept)
MAX_CLIPPED_SHARE = 0.01  # more of the region clipped than this: not read (a saturated vacuum)
MIN_GAIN = 0.01  # the far plane must stand this much (relative) above the window's near the tip


def _plane_fit(vals, rr, cc, shape):
    """Plane (3 coefficients in rows / shape[0], cols / shape[1]) fitted to ``vals`` with the
    3-sigma clipping of ``edges.flatten_background``."""
    A = np.column_stack([np.ones(rr.size), rr / shape[0], cc / shape[1]])
    keep = np.ones(vals.size, bool)
    for _ in range(3):
        Ak = A[keep]
        coef = np.linalg.solve(Ak.T @ Ak, Ak.T @ vals[keep])
        res = vals - A @ coef
        s = 1.4826 * np.median(np.abs(res[keep])) + 1e-12
        keep = np.abs(res) < 3 * s
    return coef


def vacuum_flattening(img, bounds, win, flat, px):
    """``flat`` = ``win`` / (the window's plane) re-divided by the vacuum's plane where a dim band
    (a thick light layer) pulled the window's down (module doc).

    ``img``: the image (as the window was cut from it); ``bounds``: (r0, r1, c0, c1) of the window in
    it; ``px``: pixel size (m).  Returns (flat, info): ``info["gain"]`` the median far / window plane
    ratio - 1 over the near-tip background, ``info["used"]`` whether the far plane replaced the
    window's, ``info["note"]`` in words where it did; ``flat`` is returned unchanged otherwise."""
    r0, r1, c0, c1 = bounds
    H, W = img.shape
    nm = 1e-9 / px
    pad = int(np.ceil(PAD_NM * nm))
    R0, R1, C0, C1 = max(0, r0 - pad), min(H, r1 + pad), max(0, c0 - pad), min(W, c1 + pad)
    b = max(1, int(round(0.5 * nm)))  # ~0.5 nm blocks: the plane and the distances need no finer grid
    reg = np.asarray(img[R0:R1, C0:C1], float)
    hb, wb = reg.shape[0] // b, reg.shape[1] // b
    if hb < 8 or wb < 8:
        return flat, dict(gain=np.nan, used=False)
    blocks = reg[: hb * b, : wb * b].reshape(hb, b, wb, b).mean(axis=(1, 3))
    # blocks holding a pixel at the image's maximum (a clipped detector) are no reading of the vacuum
    clipped = (reg[: hb * b, : wb * b] >= float(np.max(img))).reshape(hb, b, wb, b).any(axis=(1, 3))
    from skimage.filters import threshold_otsu

    sm = ndimage.gaussian_filter(blocks, max(1.0, 2.0 / b), mode="nearest")
    tip = sm < threshold_otsu(sm)
    dist = ndimage.distance_transform_edt(~tip) * b  # image px from the tip mask
    far = (~tip) & (dist >= (LAYER_MAX_NM + MARGIN_NM) * nm)
    if np.count_nonzero(clipped) > MAX_CLIPPED_SHARE * clipped.size:
        # a clipped vacuum: the illumination's bright part is cut flat, no plane to read (grid image 31:
        # 3 % of the region clipped, the far plane 2.9 % above the near vacuum of an oxidised tip)
        return flat, dict(gain=np.nan, used=False)
    far &= ~clipped
    if far.sum() * b * b < MIN_FAR_PIXELS:
        return flat, dict(gain=np.nan, used=False)
    rr, cc = np.nonzero(far)
    # block centres in window px
    rw, cw = (rr + 0.5) * b - 0.5 + R0 - r0, (cc + 0.5) * b - 0.5 + C0 - c0
    coef = _plane_fit(sm[far], rw, cw, win.shape)
    Rg, Cg = np.mgrid[0 : win.shape[0], 0 : win.shape[1]]
    far_plane = coef[0] + coef[1] * Rg / win.shape[0] + coef[2] * Cg / win.shape[1]
    # the window's plane, recovered from its division
    with np.errstate(divide="ignore", invalid="ignore"):
        win_plane = np.asarray(win, float) / flat
    near_b = (~tip) & (dist < LAYER_MAX_NM * nm)
    # near-tip background blocks that fall inside the window
    rn, cn = np.nonzero(near_b)
    rwn = np.round((rn + 0.5) * b - 0.5 + R0 - r0).astype(int)
    cwn = np.round((cn + 0.5) * b - 0.5 + C0 - c0).astype(int)
    ok = (rwn >= 0) & (rwn < win.shape[0]) & (cwn >= 0) & (cwn < win.shape[1])
    if ok.sum() < 20:
        return flat, dict(gain=np.nan, used=False)
    ratio = far_plane[rwn[ok], cwn[ok]] / win_plane[rwn[ok], cwn[ok]]
    gain = float(np.nanmedian(ratio) - 1.0)
    if not gain > MIN_GAIN:
        return flat, dict(gain=gain, used=False)
    note = (
        f"the window's background was {100 * gain:.1f} % below the vacuum read beyond "
        f"{LAYER_MAX_NM + MARGIN_NM:g} nm of the tip: a faint layer filled it; the window is flattened on that vacuum"
    )
    return np.asarray(win, float) / far_plane, dict(gain=gain, used=True, note=note)
