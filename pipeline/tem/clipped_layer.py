"""A light layer hidden by a clipped vacuum, seen by its outer surface's Fresnel fringe.

Where the detector clips the vacuum (an 8- or 16-bit image whose beam is above full scale), a thick
light layer (a DLC coating 2-20 nm) that transmits more than full scale / vacuum reads full scale too:
it is as white as the vacuum, the contour and the silhouette fit stop at the core, and the faint-layer
test (``faint_layer``) sees no dim band beyond the edge.  Out of focus, the layer's outer surface still
shows as a line of unclipped pixels (its dark Fresnel fringe) parallel to the edge, separated from it
by a band of clipped ones.  On the independent wave-optical simulator (``pipeline.synth.tem_wave``;
``bench_tem_independent`` DLC set, seed0 3000) two such images were used with the edge 10.5 and 11.7 nm
inside the outer surface, the pull-off 29 % and 76 % off, outside their intervals.

This module reads, along the fitted edge's outward normals near the apex, the share of unclipped
pixels at each distance, on each flank.  A layer's fringe is a run where that share stands well above
the far vacuum's, at least ``MIN_DISTANCE_NM`` out and behind at least ``MIN_GAP_NM`` of clipped pixels
(the edge's own blur and fringes lie next to it), seen on both flanks at distances that agree (a
particle stands on one flank).  The edge is then the core's and is moved out by that distance
(``profiles._outer_from_fringe``), with the distance's standard error in the edge covariance.

Where there is no such line but unclipped pixels run on from the edge over at least ``BAND_MIN_NM`` on
both flanks, the fitted edge lies inside material that the clipped vacuum does not hide entirely (a
layer partly below full scale, in focus: DLC-set image 62, 13.7 nm at 0.1 um defocus, its edge 10.4 nm
inside with unclipped pixels 4.3-4.5 nm beyond it, the pull-off 58 % off), and where that material ends
is not in the image: the profile is the core's (``edge_is_core``).  Beside a bare or oxidised edge that
run is at most 1.5 nm on the simulator's saturated images, 2.0 nm at the largest defocus (1.7 um).
"""

from __future__ import annotations

import numpy as np

from pipeline.tem.edges import curve_normals

__all__ = ["fringe_beyond_the_edge"]

D_MAX_NM = 25.0  # thickest layer looked for (nm; the DLC: 2-20 nm)
VACUUM_NM = (27.0, 32.0)  # where the far vacuum's unclipped share is read (nm beyond the edge)
STEP_NM = 0.25  # sampling step along the normals (nm)
Z_MAX_NM = 12.0  # edge points up to this height above the apex (nm)
MAX_VACUUM_SHARE = 0.2  # the far vacuum must be clipped: at most this share of it unclipped
MIN_SHARE = 0.5  # a fringe: at least this share of the normals unclipped ...
MIN_RISE = 0.4  # ... and this much above the far vacuum's share
MIN_GAP_NM = 2.0  # clipped (share <= the vacuum's + GAP_RISE) over at least this between edge and fringe
GAP_RISE = 0.2
MIN_DISTANCE_NM = 3.0  # the surface's own Fresnel fringes lie within ~sqrt(lambda |df|) ~ 2 nm of it
AGREE_NM = 2.0  # both flanks' distances must agree within this (or 25 % of their mean)
SD_FLOOR_NM = 0.5  # the fringe's position against the surface (a dark fringe lies at, or just beyond, it)
BAND_MIN_NM = 3.0  # unclipped pixels running on from the edge this far on both flanks: the edge is the core's


def _outward_normals(pts, frame):
    """Unit normals of ``pts`` (window px) pointing away from the tip: a step along one moves a flank's
    point away from the axis and the apex down (tip frame), judged over all points (one may sit on a
    small loop of the edge)."""
    x, _ = frame.to_tip(pts)
    nrm, _ = curve_normals(np.asarray(pts, float), smooth=2.0)
    score = np.sign(x) * (nrm @ frame.v) - nrm @ frame.u
    return nrm if np.nanmedian(score) >= 0 else -nrm


def _unclipped_share(clipped, pts, nrm, ds_px):
    """Share of the points ``pts`` (image px) whose pixel at ``ds_px`` along ``nrm`` is not clipped;
    NaN where fewer than 5 of those pixels lie in the image."""
    q = pts[:, None, :] + ds_px[None, :, None] * nrm[:, None, :]
    r, c = np.round(q[..., 0]).astype(int), np.round(q[..., 1]).astype(int)
    inside = (r >= 0) & (r < clipped.shape[0]) & (c >= 0) & (c < clipped.shape[1])
    val = np.zeros(r.shape)
    val[inside] = ~clipped[r[inside], c[inside]]
    n_in = inside.sum(axis=0)
    with np.errstate(invalid="ignore", divide="ignore"):
        return np.where(n_in >= 5, val.sum(axis=0) / n_in, np.nan)


def _vacuum_share(share, ds_nm):
    """The far vacuum's unclipped share in one flank's profile (NaN where none of it is in the image)."""
    vac = (ds_nm >= VACUUM_NM[0]) & (ds_nm <= VACUUM_NM[1])
    return np.nanmedian(share[vac]) if np.isfinite(share[vac]).any() else np.nan


def _unclipped_run(share, base):
    """Where one flank's ``share`` profile stands well above the far vacuum's ``base`` (bool per distance)."""
    return np.nan_to_num(share, nan=0.0) >= max(MIN_SHARE, base + MIN_RISE)


def _band(share, ds_nm):
    """How far (nm) unclipped pixels run on from the edge in one flank's ``share`` profile (0 where the
    far vacuum is not clipped: no such reading)."""
    base = _vacuum_share(share, ds_nm)
    if not base <= MAX_VACUUM_SHARE:
        return 0.0
    high = _unclipped_run(share, base)
    j = int(np.argmin(high)) if not high.all() else high.size
    return float(ds_nm[j]) if j < ds_nm.size else float(ds_nm[-1])


def _fringe(share, ds_nm):
    """(distance, half-width) (nm) of the first fringe beyond the edge in one flank's ``share`` profile
    (module doc), or None."""
    base = _vacuum_share(share, ds_nm)
    if not base <= MAX_VACUUM_SHARE:
        return None
    high = _unclipped_run(share, base)
    low = np.nan_to_num(share, nan=1.0) <= base + GAP_RISE
    # the edge's own run (its blur), then clipped pixels over MIN_GAP_NM at least, then the fringe
    i = 0
    while i < ds_nm.size and not low[i]:
        i += 1
    gap_start = i
    while i < ds_nm.size and not high[i]:
        i += 1
    if i >= ds_nm.size or ds_nm[i] > D_MAX_NM or ds_nm[i] < MIN_DISTANCE_NM:
        return None
    if np.count_nonzero(low[gap_start:i]) * STEP_NM < MIN_GAP_NM:
        return None
    j = i
    while j < ds_nm.size and high[j]:
        j += 1
    w = share[i:j] - base
    return float(np.sum(w * ds_nm[i:j]) / np.sum(w)), 0.5 * float(ds_nm[j - 1] - ds_nm[i] + STEP_NM)


def fringe_beyond_the_edge(img, origin, pts, frame, px, clipped):
    """The outer surface of a light layer hidden by a clipped vacuum (module doc).

    ``img``: the image; ``origin``: the window's corner in it; ``pts``: the fitted edge (window px);
    ``frame``: its tip frame (window px); ``px``: pixel size (m); ``clipped``: the image's clipped pixels
    (bool, ``img``'s shape).  Returns a dict: ``found``; where found, ``thickness`` and ``thickness_sd``
    (m: how far beyond the edge the outer surface lies), ``left`` / ``right`` (m: each flank's), and
    ``note`` in words; where not found but the edge lies inside material whose end is hidden (module
    doc), ``edge_is_core`` True, ``band`` (m: the shorter flank's run) and ``note``; ``profiles`` (the
    unclipped share per flank) and ``distances`` (m) always."""
    nm = 1e-9 / px
    pts = np.asarray(pts, float)
    x, z = frame.to_tip(pts)
    nrm = _outward_normals(pts, frame)
    ds_nm = np.arange(0.0, VACUUM_NM[1] + STEP_NM / 2, STEP_NM)
    out = dict(found=False, distances=ds_nm * 1e-9, profiles={})
    near = z <= Z_MAX_NM * nm
    got, band = {}, {}
    for name, side in (("left", x < 0), ("right", x >= 0)):
        sel = near & side
        if np.count_nonzero(sel) < 10:
            return out
        share = _unclipped_share(clipped, pts[sel] + origin, nrm[sel], ds_nm * nm)
        out["profiles"][name] = share
        got[name], band[name] = _fringe(share, ds_nm), _band(share, ds_nm)
    if got["left"] is None or got["right"] is None:
        return _inside_material(out, band)
    (dl, wl), (dr, wr) = got["left"], got["right"]
    mean = 0.5 * (dl + dr)
    if abs(dl - dr) > max(AGREE_NM, 0.25 * mean):
        return _inside_material(out, band)
    sd = max(SD_FLOOR_NM, 0.5 * abs(dl - dr), 0.5 * max(wl, wr))
    out.update(
        found=True,
        thickness=mean * 1e-9,
        thickness_sd=sd * 1e-9,
        left=dl * 1e-9,
        right=dr * 1e-9,
        note=(
            f"a line of unclipped pixels parallel to the edge {mean:.1f} +- {sd:.1f} nm beyond it (left {dl:.1f}, "
            f"right {dr:.1f} nm) behind clipped ones: the Fresnel fringe of a light layer's outer surface that "
            "the clipped vacuum hides; the fitted edge is the core's"
        ),
    )
    return out


def _inside_material(out, band):
    """``out`` marked ``edge_is_core`` where unclipped pixels run on from the edge over at least
    ``BAND_MIN_NM`` on both flanks (module doc)."""
    run = min(band["left"], band["right"])
    if run >= BAND_MIN_NM:
        out.update(
            edge_is_core=True,
            band=run * 1e-9,
            note=(
                f"unclipped pixels run on {band['left']:.1f} / {band['right']:.1f} nm (left / right) beyond the fitted "
                "edge in a clipped vacuum: the edge lies inside material (a light layer partly below full scale) "
                "whose outer end the clipped vacuum hides, so the profile is the core's"
            ),
        )
    return out
