"""Screening of the profile before the fit (package doc, "Screening"): runs that stand out of one
flank only (points where the edge turns back: ``pipeline.tem.turn_back``, shared with stage 1)."""

from __future__ import annotations

import numpy as np

from pipeline.fits.power_law import _model, _r_h

RUN_SIGMA = 4.0  # contamination: a run of residuals this many robust SD outwards ...
RUN_MIN = 0.15e-9  # ... and at least this far (m) ...
RUN_POINTS = 4  # ... over at least this many consecutive points of one flank


def _where(r, z, side, mask):
    """Words for where ``mask`` lies: flank(s) and height range (nm)."""
    parts = []
    for s_, name in ((-1, "left"), (1, "right")):
        m = mask & (side == s_)
        if m.any():
            parts.append(f"{name} flank, z {z[m].min() * 1e9:.1f}-{z[m].max() * 1e9:.1f} nm")
    return "; ".join(parts)


def _one_flank_runs(fit, r, z, side, use, r_scale):
    """Runs of points of one flank that stand outwards of the flank-wise fit (module doc) while
    the other flank at the same heights does not: contamination stuck to one flank."""
    f, fp = _model(
        np.r_[fit.n, np.log(_r_h(fit) / r_scale), fit.z0 / r_scale, fit.axis_offset / r_scale, fit.flank_asymmetry],
        r / r_scale,
        fit.fit_height / r_scale,
        side,
    )
    e = (z / r_scale - f) / np.sqrt(1.0 + fp**2) * r_scale  # m, < 0 outwards
    if use.sum() < 10:
        return np.zeros(r.size, bool)
    s = 1.4826 * float(np.median(np.abs(e[use] - np.median(e[use])))) + 1e-15
    out = use & (e < -max(RUN_SIGMA * s, RUN_MIN))
    runs = np.zeros(r.size, bool)
    for s_ in (-1, 1):
        i = np.nonzero(use & (side == s_))[0]
        o = i[np.argsort(z[i], kind="stable")]
        flagged = out[o]
        k = 0
        while k < o.size:
            if not flagged[k]:
                k += 1
                continue
            j = k
            while j < o.size and flagged[j]:
                j += 1
            if j - k >= RUN_POINTS:
                z1, z2 = z[o[k]], z[o[j - 1]]
                other = use & (side == -s_) & (z >= z1) & (z <= z2)
                if not other.any() or np.median(e[other]) > -2.0 * s:
                    # with its flanks: where the run's residuals return through zero
                    a, b = k, j
                    while a > 0 and e[o[a - 1]] < 0:
                        a -= 1
                    while b < o.size and e[o[b]] < 0:
                        b += 1
                    runs[o[a:b]] = True
            k = j
    return runs
