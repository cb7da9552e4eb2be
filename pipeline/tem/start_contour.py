"""The silhouette fit's starting contour where the iso-level just below the vacuum folds in a faint layer.

The fit starts from the iso-contour 2 % (at least 4 noise sigma) below the flattened vacuum
(``profiles._edge_level``): outside a bare surface by ~2 blur sigma, and on the outer surface of a
light coating.  A faint thick layer (DLC 2-20 nm at 5-20 % of the core's contrast, often in focus)
dims the image by only a few per cent over its whole depth, so at that level the contour wanders
through the layer's noise, folds back on itself, and the fit that follows it folds too (on the
independent wave-optical simulator, ``benchmarks/bench_tem_independent.py``, 8 of the grid's 11 lost
images).  Here:

1. fold: the share of the contour's points (up to 2 x ``outer_layer.Z_RAMP`` of the profile height)
   that turn back by stage 2's rule (``outer_layer.turned_back_share``);
2. where it exceeds ``FOLD_SHARE`` (20 %: at 30 % grid image 35 stayed folded at 29 %, at 15 % a DLC
   image came back with its pull-off 61 % off, outside its interval), contours at other levels are
   tried, the outermost first: 1 % below the vacuum (where the noise allows 4 sigma there), then 2,
   4, ... ``LOWEST_STEP`` below the first
   level; the first whose fold share is at most ``UNFOLDED_SHARE`` starts the fit.  A lower level lies on
   the core: the faint-layer test after the fit (``faint_layer``, ``outer_layer``) then reads the layer
   from the pixels beyond it, which is what that test is for.  Where the fit from that level finds no
   edge (``profiles._no_fit``), the first contour starts it after all;
3. the folded contour is kept: how far it lies beyond the final edge (the median outward distance of its
   points, ``dim_zone``) says how far out something dims the image by the first level.  Where that is
   more than ``DIM_ZONE_NM`` and no test has marked the edge the core's, the whole edge gets a common
   offset of that SD in its covariance, and a flag says so in words.  On the three wave-optical sets (260 images, 36
   started lower) the folded contour lay at most 1.6 nm beyond final edges within 1.5 nm of the true
   silhouette (26 images), and 3.1-7.1 nm beyond 5 of the 10 edges 1.7-12 nm inside a layer (2.0 nm
   for one more; 4 did not show it): ``DIM_ZONE_NM`` is set between them on those sets, not derived.
"""

from __future__ import annotations

import numpy as np

from pipeline.tem.edges import _Fail, initial_contour
from pipeline.tem.outer_layer import Z_RAMP, turned_back_share

FOLD_SHARE = 0.2  # a start contour with more of its points turning back is folded
UNFOLDED_SHARE = 0.15  # an alternative level is taken where at most this share turns back
LEVEL_STEP = 0.02  # steps of the levels tried below the first (share of the vacuum)
LOWEST_STEP = 0.12  # the lowest level tried: this much below the first
OUTER_LEVEL = 0.01  # the level above the first that is tried first (where 4 noise sigma allow it)
DIM_ZONE_NM = 2.5  # a folded contour this far beyond the final edge (median) widens the edge's SD
SMOOTH_PX = 2.0  # the start contour's Gaussian smoothing (px), as ``profiles._edge_level`` assumes


def clip_height(cont, frame, hmax):
    """The connected run of contour ``cont`` (window px) around its lowest point up to height ``hmax``
    (px above the apex in ``frame``)."""
    x, z = frame.to_tip(cont)
    inside = z <= hmax
    i0 = int(np.argmin(z))
    lo = i0
    while lo > 0 and inside[lo - 1]:
        lo -= 1
    hi = i0
    while hi < len(z) - 1 and inside[hi + 1]:
        hi += 1
    return cont[lo : hi + 1]


def fold_share(cont, frame, hpx, px):
    """Share of ``cont``'s points near the apex that turn back (``outer_layer.turned_back_share``)."""
    return turned_back_share(cont, frame, hpx, px)


def unfolded_start(flat, noise, cont, level, apex_hint, frame, hpx, px):
    """(start contour, the folded first contour or None, entries for the edge model): ``cont`` (the
    contour at ``level``, already clipped to 1.3 x the profile height + 8 px) where it does not fold,
    else the first unfolded contour of the levels of the module doc (item 2)."""
    share = fold_share(cont, frame, hpx, px)
    info = {"level": float(level), "fold_share": share, "start_level": float(level)}
    if share <= FOLD_SHARE:
        return cont, None, info
    smoothed_noise = 4.0 * noise / (2.0 * np.sqrt(np.pi) * SMOOTH_PX)
    levels = []
    if 1.0 - max(smoothed_noise, OUTER_LEVEL) > level + 1e-9:
        levels.append(1.0 - max(smoothed_noise, OUTER_LEVEL))
    levels += list(level - np.arange(LEVEL_STEP, LOWEST_STEP + 1e-9, LEVEL_STEP))
    for lv in levels:
        try:
            c = clip_height(initial_contour(flat, lv, apex_hint, smooth=SMOOTH_PX), frame, 1.3 * hpx + 8)
        except _Fail:
            continue
        s = fold_share(c, frame, hpx, px) if _both_flanks(c, frame, hpx) else 1.0
        if s <= UNFOLDED_SHARE:
            info.update(start_level=float(lv), start_fold_share=s)
            return c, cont, info
    info["note"] = "no level gave an unfolded start"
    return cont, None, info


def _both_flanks(cont, frame, hpx, min_points=3):
    """True where ``cont`` has at least ``min_points`` on each flank at the heights ``fold_share`` judges
    (a flank with fewer is not judged there, so its share would read 0)."""
    if len(cont) < 10:
        return False
    x, z = frame.to_tip(np.asarray(cont, float))
    low = z <= 2 * Z_RAMP * hpx
    return bool(((x < 0) & low).sum() >= min_points and ((x >= 0) & low).sum() >= min_points)


def _radius_at(z, x_edge, z_edge, side):
    """The edge's radius on flank ``side`` (-1 / +1) at heights ``z`` (px), by interpolation in height."""
    m = np.where(x_edge < 0, -1, 1) == side
    if m.sum() < 2:
        return np.full(np.shape(z), np.inf)
    o = np.argsort(z_edge[m], kind="stable")
    return np.interp(z, z_edge[m][o], np.abs(x_edge[m][o]))


def dim_zone(folded, pts, frame, hpx):
    """Median signed distance (px, + outward) of the folded contour's points from the edge ``pts``
    (window px), over the heights the fold was judged on (``fold_share``)."""
    from scipy.spatial import cKDTree

    xb, zb = frame.to_tip(np.asarray(folded, float))
    xe, ze = frame.to_tip(np.asarray(pts, float))
    sel = zb <= 2 * Z_RAMP * hpx
    if sel.sum() < 5 or len(pts) < 5:
        return 0.0
    xb, zb = xb[sel], zb[sel]
    d, _ = cKDTree(np.c_[xe, ze]).query(np.c_[xb, zb])
    radius = np.where(xb < 0, _radius_at(zb, xe, ze, -1), _radius_at(zb, xe, ze, 1))
    outside = (zb < ze.min()) | (np.abs(xb) > radius)
    return float(np.median(np.where(outside, d, -d)))
