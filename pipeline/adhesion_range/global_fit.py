"""The global h and W_A that make all intervals most consistent.

At every h the common W_A is the generalised-least-squares mean of ln W_A(h) of the reference
and usable worn intervals with the covariance Sigma(h) estimated from the MC samples (this keeps
the shared calibration/E* errors from counting as inconsistency), chi2(h) its residual;
h = argmin chi2 refined by a parabola in ln h; W_A = GLS mean there.  The CI comes from
repeating the minimisation for every MC sample (percentiles of the per-sample estimates).
Where the intervals disagree more than their uncertainties allow, ``inconsistency`` widens it.
"""

from __future__ import annotations

import numpy as np

from pipeline.adhesion_range.curves import CI_PCTS, LawCurves, censored_percentiles
from pipeline.adhesion_range.gls import argmin_refined, gls_chi2, precision, sample_covariances, sample_minima
from pipeline.adhesion_range.inconsistency import random_effects_if_inconsistent, widen_if_inconsistent

USED_STATUSES = ("reference", "ok", "multiple_crossings", "n_too_close_to_2")
CONSTRAINING_STATUSES = ("ok", "multiple_crossings")


def global_estimate(curves: LawCurves, order: list, intervals: dict, h, inconsistency: str) -> dict:
    """The global h and W_A of one law from the intervals whose status lets them take part
    (``intervals``: per interval the result of ``crossings.interval_crossing``): status ``ok``,
    ``at_grid_edge`` (chi2 smallest at an end of the grid: no estimate) or ``no_h_constraint``
    (no worn interval constrains h), with chi2(h), the GLS W_A(h), the per-sample estimates and
    their percentiles, widened by ``inconsistency`` ("random_effects" or "birge")."""
    x = np.log(h)
    used = [nm for nm in order if intervals[nm]["status"] in USED_STATUSES]
    used = [nm for nm in used if np.any(np.isfinite(curves(nm)[0]))]
    constraining = [nm for nm in used if intervals[nm]["status"] in CONSTRAINING_STATUSES]
    g = {
        "intervals_used": used,
        "h": np.nan,
        "W_A": np.nan,
        "h_pcts": np.full(len(CI_PCTS), np.nan),
        "W_pcts": np.full(len(CI_PCTS), np.nan),
        "chi2_min": np.nan,
        "dof": max(len(used) - 2, 0),
        "chi2": np.full(h.shape, np.nan),
        "W_common": np.full(h.shape, np.nan),
        "note": "",
    }
    excluded = [nm for nm in order if nm not in used]
    if excluded:
        g["note"] = "excluded: " + ", ".join(f"{nm} ({intervals[nm]['status']})" for nm in excluded) + ". "
    if not constraining:
        g["status"] = "no_h_constraint"
        g["note"] += "no worn interval constrains h; W_A from the reference only"
        return g
    Yc = np.stack([curves(nm)[0] for nm in used], axis=-1)  # (H, I)
    Ys = curves.stacked_samples(used)  # (S, H, I)
    C = sample_covariances(Ys)
    P = precision(C)
    mc, chic = gls_chi2(Yc, P)
    g["chi2"] = np.where(np.isfinite(chic), chic, np.nan)
    g["W_common"] = np.exp(mc)
    xs, ms, chis, edge = argmin_refined(x, chic[None, :], mc[None, :])
    xss, mss, edge_s = sample_minima(x, Ys, P)
    g["h_samples"] = np.exp(xss)
    g["W_samples"] = np.exp(mss)
    g["chi2_min"] = float(chis[0])
    g["edge_fraction"] = float(np.mean(edge_s != 0))
    xss_c = np.where(edge_s != 0, np.nan, xss)
    g["h_pcts"] = np.exp(censored_percentiles(xss_c, edge_s, CI_PCTS))
    g["W_pcts"] = np.exp(censored_percentiles(mss, np.zeros_like(edge_s), CI_PCTS))
    if edge[0] != 0 or not np.isfinite(xs[0]):
        g["status"] = "at_grid_edge"
        g["note"] += f"chi2(h) is smallest at the {'lower' if edge[0] < 0 else 'upper'} end of the h grid: no estimate"
        return g
    g["status"] = "ok"
    g["h"] = float(np.exp(xs[0]))
    g["W_A"] = float(np.exp(ms[0]))
    if inconsistency == "birge":
        widen_if_inconsistent(g, xs[0], ms[0], xss_c, mss, edge_s, x)
    else:
        random_effects_if_inconsistent(g, x, Yc, Ys, C)
    return g
