"""Where an edge turns back: the radius of a worn tip grows with height above the apex, so a point
with a point of its flank lower and further out is an undercut (contamination, a notch) or a failed
edge, never the power law. The rule of stage 2's screening (``pipeline.fits.screening``), also used by
stage 1 before it moves an edge out to a faint layer (``pipeline.tem.outer_layer``)."""

from __future__ import annotations

import numpy as np

# a point turns back where a point of its flank at least this much lower lies this much further
# out (m, or TURN_BACK_PX pixels if more): a flat face's edge wanders by +-0.3 nm at 0.5 nm pixels
TURN_BACK_TOL = 0.4e-9
TURN_BACK_PX = 1.5
TURN_BACK_MAX = 0.25  # share of the window's points where the edge turns back that makes it unusable


def turned_back(r, z, side, win, tol=TURN_BACK_TOL):
    """Points (in the window) with a point of the same flank at least ``tol`` lower and ``tol``
    further out: the radius of a worn tip grows with height, an edge that turns back is an
    undercut (contamination, a notch) or a failed edge, never the power law."""
    out = np.zeros(r.size, bool)
    for s_ in (-1, 1):
        i = np.nonzero(win & (side == s_))[0]
        if i.size < 3:
            continue
        o = i[np.argsort(z[i], kind="stable")]
        zz, rr = z[o], r[o]
        # largest radius among the points at least tol lower
        j = np.searchsorted(zz, zz - tol, side="right")
        runmax = np.concatenate([[-np.inf], np.maximum.accumulate(rr)])[j]
        out[o] = rr < runmax - tol
    return out
