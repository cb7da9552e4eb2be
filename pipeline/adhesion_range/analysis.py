"""One traction law of a tip: reference, per-interval crossings and the global estimate."""

from __future__ import annotations

import numpy as np

from pipeline.adhesion_range.crossings import interval_crossing
from pipeline.adhesion_range.curves import LawCurves
from pipeline.adhesion_range.global_fit import global_estimate
from pipeline.adhesion_range.inconsistency import INCONSISTENCY_MODELS
from pipeline.adhesion_range.reference import reference_at, reference_curve


def analyse_law(inv: dict, law: str, inconsistency: str = "random_effects") -> dict:
    """Reference, crossings and global estimate for one traction law (pure function of the
    inversion ``inv``, ``load_inversion``).  ``inconsistency``: how intervals that disagree
    beyond their uncertainties widen the interval of h and W_A (``random_effects``, the default,
    or ``birge``; ``pipeline.adhesion_range.inconsistency``).

    Returns {law, reference (None without a usable one), intervals: {name: crossing}, global,
    notes}; ``status`` ``no_reference`` where no reference interval has a finite W_A."""
    if inconsistency not in INCONSISTENCY_MODELS:
        raise ValueError(f"inconsistency {inconsistency!r} not in {INCONSISTENCY_MODELS}")
    h = inv["h"]
    order = inv["order"]
    ivs = inv["intervals"]
    refs = [nm for nm in order if ivs[nm]["reference"]]
    res = {"law": law, "intervals": {}, "notes": []}
    if not refs:
        raise ValueError("no reference interval (config reference_intervals) in the inversion file")
    curves = LawCurves(inv, law)
    reference, ref_c, ref_s = reference_curve(curves, refs, ivs, h, res["notes"])
    res["reference"] = reference
    if reference is None:
        res["status"] = "no_reference"
        for nm in order:
            res["intervals"][nm] = {
                "status": "reference" if nm in refs else "unusable",
                "crossings": [],
                "note": "no usable reference",
            }
        return res
    for nm in order:
        yc, ys = curves(nm)
        res["intervals"][nm] = interval_crossing(ivs[nm], yc, ys, ref_c, ref_s, h)
    res["global"] = global_estimate(curves, order, res["intervals"], h, inconsistency)
    g_h = res["global"]["h"]
    at_h = g_h if np.isfinite(g_h) else float(np.exp(np.median(np.log(h))))
    reference["at_global_h"] = (at_h, *reference_at(reference, h, at_h))
    del reference["ln_samples"]  # (S, H): not kept past the law's analysis
    return res
