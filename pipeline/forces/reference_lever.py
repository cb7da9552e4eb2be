"""Spring constant by the reference-cantilever method (Tortonese & Kirk 1997).

    k = k_ref_eff (S_hard / S_ref - 1) cos^p(theta),  S = 1/InvOLS (V/m)
      = k_ref_eff (InvOLS_ref / InvOLS_hard - 1) cos^p(theta)
    k_ref_eff = k_ref (L / (L - dL))^3        (loaded dL before the reference lever's end)

InvOLS_hard: test lever pressed on a hard surface; InvOLS_ref: pressed on the end of
the reference lever.  Tilt: sources differ -- ``tilt_correction='cos'`` (p = 1,
Tortonese & Kirk; Gibson et al.) or ``'cos2'`` (p = 2, e.g. Hutter 2005 for the
tilted-lever stiffness), ``'none'`` (p = 0).
"""

from __future__ import annotations

import numpy as np

TILT_POWER = {"none": 0, "cos": 1, "cos2": 2}


def reference_lever_k(k_ref, invols_hard, invols_ref, *, length=None, offset=0.0, tilt=0.0, tilt_correction="cos"):
    """k (N/m) of the test lever; invols in m/V, length/offset in m, tilt in rad."""
    if tilt_correction not in TILT_POWER:
        raise ValueError(f"tilt_correction must be one of {sorted(TILT_POWER)}, got {tilt_correction!r}")
    k_eff = k_ref
    if length is not None and offset:
        if not 0 <= offset < length:
            raise ValueError(f"reference lever offset {offset:g} m must lie in [0, length={length:g} m)")
        k_eff = k_ref * (length / (length - offset)) ** 3
    ratio = invols_ref / invols_hard
    if not ratio > 1:
        raise ValueError(
            f"InvOLS on the reference lever ({invols_ref:.4g} m/V) must "
            f"exceed the hard-surface InvOLS ({invols_hard:.4g} m/V)"
        )
    return float(k_eff * (ratio - 1.0) * np.cos(tilt) ** TILT_POWER[tilt_correction])
