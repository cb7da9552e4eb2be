"""The reference W_A(h): the paraboloidal interval(s) whose W_A hardly depends on h.

W_ref(h) is the inverse-variance weighted mean of ln W_A(h) of the reference intervals (weights
from the Monte-Carlo variance at each h), per MC sample too; its variation over the grid (the
paper's check that it is nearly constant for h >= 0.3 nm) is reported.
"""

from __future__ import annotations

import numpy as np

from pipeline.adhesion_range.curves import CI_PCTS, ROW_CHUNK, LawCurves, nanvar_cols, row_starts, wmean_ln
from pipeline.inversion.montecarlo import sample_percentiles

H_FLATNESS_MIN = 0.3e-9  # the paper's check: W_ref(h) nearly constant for h >= 0.3 nm


def reference_curve(curves: LawCurves, refs: list, ivs: dict, h, notes: list):
    """(reference, ln W_ref central, ln W_ref samples) of the reference intervals ``refs``, or
    (None, None, None) when none has a finite W_A (each such one noted in ``notes``).

    ``reference``: intervals, W_ref (central, J/m^2), W_ref_pcts (CI_PCTS of the samples),
    ln_samples, max_rel_change ((max - min)/median over h >= flatness_h_min), flatness_h_min."""
    yc_list, ys_list, var_list = [], [], []
    for nm in refs:
        yc, ys = curves(nm)
        if not np.any(np.isfinite(yc)):
            notes.append(f"reference {nm} has no finite W_A (n flag {ivs[nm]['n_flag']})")
            continue
        yc_list.append(yc)
        ys_list.append(ys)
        var_list.append(nanvar_cols(ys))
    if not yc_list:
        return None, None, None
    ref_c = wmean_ln(yc_list, var_list)
    ref_s = np.empty(ys_list[0].shape)
    for a in row_starts(ref_s):  # the weighted mean sample by sample: only ROW_CHUNK rows of temporaries
        rows = [ys[a : a + ROW_CHUNK] for ys in ys_list]
        ref_s[a : a + ROW_CHUNK] = wmean_ln(rows, [v[None, :] * np.ones_like(rows[0]) for v in var_list])
    Wc = np.exp(ref_c)
    sel = h >= H_FLATNESS_MIN - 1e-15
    if not np.any(sel):
        sel = np.ones_like(h, bool)
    wsel = Wc[sel][np.isfinite(Wc[sel])]
    flat = float((wsel.max() - wsel.min()) / np.median(wsel)) if wsel.size else np.nan
    reference = {
        "intervals": list(refs),
        "W_ref": Wc,
        "W_ref_pcts": sample_percentiles(np.exp(ref_s), CI_PCTS),
        "ln_samples": ref_s,
        "max_rel_change": flat,
        "flatness_h_min": float(h[sel][0]),
    }
    return reference, ref_c, ref_s


def reference_at(reference: dict, h_grid, h_value):
    """Reference W_A and its percentiles at h (interpolated in ln h)."""
    x = np.log(h_grid)
    xv = np.log(h_value)
    w = float(np.exp(np.interp(xv, x, np.log(reference["W_ref"]))))
    k = int(np.clip(np.searchsorted(x, xv) - 1, 0, x.size - 2))
    t = float(np.clip((xv - x[k]) / (x[k + 1] - x[k]), 0.0, 1.0))
    ls = reference["ln_samples"]
    s = np.exp(ls[:, k] * (1.0 - t) + ls[:, k + 1] * t)
    s = s[np.isfinite(s)]
    pc = np.percentile(s, CI_PCTS) if s.size else np.full(len(CI_PCTS), np.nan)
    return w, pc
