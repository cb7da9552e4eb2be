"""Loops of an offset curve, cut off: the silhouette fit's edge is its reference meridian moved along
the reference's normals (``silhouette_model._Problem.curve``), and a move inward by more than the
reference's radius of curvature folds the curve into a loop (the "swallowtail" of parallel curves).

Where that happens the curve runs backwards for a stretch (its step against the reference's own
direction is negative) and crosses itself on either side of it.  The body the curve bounds is the
body without the loop (an erosion, or a dilation where a concave stretch moves out), so the loop's
points are collapsed onto the crossing point.  A body rendered from the looped curve had a spike at
the apex, and a reference made from it (``_Problem.rebase``) had a loop of its own whose normals turn
through 360 degrees: on one interval of the end-to-end study (``bench_wear_test_wave``, tip 1035 i1,
uncoated, 1.3 um overfocus, 0.41 nm px) the single-layer fit pulled a sharp start contour 3-4 px in at
the apex, the reference took the loop, and the edge reported there was a 2 nm pigtail below the apex:
n 1.05 at its bound against 2.75, interval lost.

A curve that nowhere runs backwards is returned as it is (the same arrays: no number changes).
"""

from __future__ import annotations

import numpy as np

REACH = 160  # curve steps searched for the crossing on either side of a backward stretch (40 px at 0.25 px) ...
COARSE = 4  # ... then, where none is found there, every COARSE-th point over COARSE x as far (sharp tips)


def trimmed_loops(x, z, nx, nz):
    """(x, z) of the offset curve with every loop collapsed onto its crossing point (module doc).

    ``x``, ``z``: the curve (tip frame, px, left -> apex -> right); ``nx``, ``nz``: the unit normals
    of the reference it was moved along (the reference's direction is (-nz, nx)).  Each backward run
    is cut at its own outermost crossing (a run inside a loop already cut is skipped): two loops
    apart, as at the two corners of a flat worn apex, are two cuts."""
    dx, dz = np.diff(x), np.diff(z)
    back = dx * -nz[:-1] + dz * nx[:-1] < 0
    if not back.any():
        return x, z
    x, z = x.copy(), z.copy()
    done = -1  # the last point collapsed so far
    for a, b in _runs(back):
        if b <= done:
            continue
        hit = _crossing(x, z, max(a, done), b)
        if hit is not None:
            i, j, px, pz = hit
            x[i + 1 : j + 1] = px
            z[i + 1 : j + 1] = pz
            done = j
    return x, z


def _runs(back):
    """(first, last) segment index of each run of backward steps."""
    idx = np.nonzero(back)[0]
    cut = np.nonzero(np.diff(idx) > 1)[0]
    return list(zip(idx[np.r_[0, cut + 1]], idx[np.r_[cut, idx.size - 1]]))


def _crossing(x, z, a, b):
    """(i, j, x, z): the outermost crossing of segment i <= a with segment j >= b (``_outermost``),
    searched ``REACH`` steps out; where there is none, on the curve's every ``COARSE``-th point
    ``COARSE`` x as far (on a sharp tip moved in far the crossing lies ~(|d| - R) / tan(half-angle)
    along the flanks) and refined on the segments around it; or None."""
    i = np.arange(max(0, a - REACH), a + 1)
    j = np.arange(b, min(x.size - 1, b + 1 + REACH))
    hit = _outermost(x, z, i, j)
    if hit is not None:
        return hit
    xc, zc = x[::COARSE], z[::COARSE]
    ac, bc = a // COARSE, -(-(b + 1) // COARSE)
    ic = np.arange(max(0, ac - REACH), ac)
    jc = np.arange(bc, min(xc.size - 1, bc + REACH))
    coarse = _outermost(xc, zc, ic, jc)
    if coarse is None:
        return None
    ci, cj = coarse[0] * COARSE, coarse[1] * COARSE
    fine = _outermost(
        x, z, np.arange(max(0, ci - COARSE), ci + 2 * COARSE), np.arange(cj - COARSE, min(x.size - 1, cj + 2 * COARSE))
    )
    return fine if fine is not None else (ci, cj, coarse[2], coarse[3])


def _outermost(x, z, i, j):
    """(i, j, x, z) of the crossing of a segment of ``i`` with a later one of ``j`` (two apart at least)
    that encloses the most points, or None where none cross."""
    if i.size == 0 or j.size == 0:
        return None
    p = np.column_stack([x[i], z[i]])[:, None, :]
    r = np.column_stack([x[i + 1] - x[i], z[i + 1] - z[i]])[:, None, :]
    q = np.column_stack([x[j], z[j]])[None, :, :]
    s = np.column_stack([x[j + 1] - x[j], z[j + 1] - z[j]])[None, :, :]
    den = r[..., 0] * s[..., 1] - r[..., 1] * s[..., 0]
    qp = q - p
    with np.errstate(divide="ignore", invalid="ignore"):
        t = (qp[..., 0] * s[..., 1] - qp[..., 1] * s[..., 0]) / den
        u = (qp[..., 0] * r[..., 1] - qp[..., 1] * r[..., 0]) / den
    ok = (den != 0) & (t >= 0) & (t <= 1) & (u >= 0) & (u <= 1) & (j[None, :] - i[:, None] >= 2)
    if not ok.any():
        return None
    ii, jj = np.nonzero(ok)
    k = int(np.argmax(j[jj] - i[ii]))
    m, n = ii[k], jj[k]
    tk = t[m, n]
    return int(i[m]), int(j[n]), float(x[i[m]] + tk * r[m, 0, 0]), float(z[i[m]] + tk * r[m, 0, 1])
