"""Intervals that disagree more than their uncertainties allow (chi^2_min of the global fit above
its degrees of freedom): how the interval of h and W_A is widened, and the note that says so.

``random_effects`` (the default): a between-interval scatter tau added to every interval, the
Paule-Mandel value that brings chi^2_min down to the degrees of freedom, drawn in the Monte
Carlo; ``birge``: the spread of the per-sample estimates scaled by sqrt(chi^2/dof).  With one
worn interval (dof 0) agreement cannot be tested, and the note says that.
"""

from __future__ import annotations

import numpy as np
from scipy.special import chdtrc, ndtri

from pipeline.adhesion_range.curves import CI_PCTS, censored_percentiles
from pipeline.adhesion_range.gls import min_chi2, precision, sample_minima

INCONSISTENCY_MODELS = ("random_effects", "birge")
UNTESTABLE = (
    "one worn interval: whether the intervals agree cannot be tested, the interval of h rests on "
    "the stated uncertainties alone. "
)


def birge_ratio(chi2_min: float, dof: int) -> float:
    """sqrt(chi2/dof) when it exceeds 1, else 1 (NaN without degrees of freedom)."""
    if dof <= 0 or not np.isfinite(chi2_min):
        return np.nan
    return float(max(1.0, np.sqrt(max(chi2_min, 0.0) / dof)))


def between_interval_variance(x, Yc, C, dof, iters=60):
    """Paule-Mandel tau^2 (in (ln W_A)^2): the variance that, added to every interval's (per-h
    covariance ``C`` of the Monte Carlo), brings the global fit's chi^2_min down to its degrees of
    freedom (0 where it is already at or below)."""
    chi0 = min_chi2(x, Yc, precision(C))[0]
    if dof <= 0 or not np.isfinite(chi0) or chi0 <= dof:
        return 0.0
    lo, hi = -14.0, 0.0  # ln tau^2: tau from 0.1 % to 100 % of W_A
    if min_chi2(x, Yc, precision(C, tau2=np.exp(hi)))[0] > dof:
        return float(np.exp(hi))
    for _ in range(iters):
        mid = 0.5 * (lo + hi)
        if min_chi2(x, Yc, precision(C, tau2=np.exp(mid)))[0] > dof:
            lo = mid
        else:
            hi = mid
        if hi - lo < 1e-3:
            break
    return float(np.exp(hi))


def _verdict(g: dict) -> str:
    verdict = (
        "mutually inconsistent" if g["p_value"] < 0.05 else "scattered a little more than their uncertainties allow"
    )
    return f"intervals {verdict} (chi2 = {g['chi2_min']:.3g} for {g['dof']} dof, p = {g['p_value']:.2g})"


def _percentiles(g: dict, xs, ms, side) -> None:
    """The global estimate's percentiles from per-sample ln h (``xs``, NaN where censored on
    ``side``) and ln W (``ms``); the previous ones kept as ``*_pcts_unscaled``."""
    g["h_pcts_unscaled"], g["W_pcts_unscaled"] = g["h_pcts"], g["W_pcts"]
    g["h_pcts"] = np.exp(censored_percentiles(xs, side, CI_PCTS))
    g["W_pcts"] = np.exp(censored_percentiles(ms, np.zeros_like(side), CI_PCTS))


def random_effects_if_inconsistent(g, x, Yc, Ys, C):
    """Where the intervals disagree more than their uncertainties allow (chi^2_min > dof), a
    between-interval random effect: every interval's ln W_A(h) is given an extra, independent
    offset of variance tau^2 (Paule-Mandel: chi^2_min = dof with it; DerSimonian & Laird 1986,
    Paule & Mandel 1982), constant over h -- an InvOLS not remeasured after a remount, a force
    bias, a contaminated reference, each moving one interval's whole W_A(h) curve.  The global h
    and W_A are re-estimated with it (an interval whose own uncertainty is small no longer
    outweighs the rest: a wrong reference cannot pin W_A alone) and the Monte Carlo draws the
    offsets too, so the intervals widen by what the disagreement needs.  Unlike a Birge scaling,
    which keeps the relative weights, this lets the consistent majority decide the estimate.

    ``g``: the global estimate (``global_fit``), updated in place; Yc (H, I) and Ys (S, H, I)
    the central and sampled ln W_A of the intervals used, C their per-h sample covariance."""
    if g["dof"] <= 0:
        g["birge_ratio"] = np.nan
        g["tau"] = np.nan
        g["note"] += UNTESTABLE
        return
    g["p_value"] = float(chdtrc(g["dof"], g["chi2_min"]))
    g["birge_ratio"] = birge_ratio(g["chi2_min"], g["dof"])
    tau2 = between_interval_variance(x, Yc, C, g["dof"])
    g["tau"] = float(np.sqrt(tau2))
    if tau2 <= 0.0:
        return
    P = precision(C, tau2=tau2)
    _, xs, ms, edge = min_chi2(x, Yc, P)
    n_samples, _, n_intervals = Ys.shape
    # the random offsets of the Monte Carlo: seeded by the data's size (deterministic per file)
    eps = np.sqrt(tau2) * np.random.default_rng([n_samples, n_intervals, 0x7A0]).standard_normal(
        (n_samples, 1, n_intervals)
    )
    xss, mss, edge_s = sample_minima(x, Ys, P, offsets=eps)
    g["h_unscaled"], g["W_A_unscaled"] = g["h"], g["W_A"]
    if edge == 0 and np.isfinite(xs):
        g["h"], g["W_A"] = float(np.exp(xs)), float(np.exp(ms))
    g["h_samples"], g["W_samples"] = np.exp(xss), np.exp(mss)
    _percentiles(g, np.where(edge_s != 0, np.nan, xss), mss, edge_s)

    jk = leave_one_out_spread(x, Yc, C, tau2, float(np.log(g["h"])))
    g["h_jackknife_rel_sd"] = jk
    if np.isfinite(jk):
        _cover_jackknife(g, x, jk)

    def widening(p, p0):
        return float(np.log(p[-1] / p[0]) / np.log(p0[-1] / p0[0]))

    g["ci_widening_h"] = (
        widening(g["h_pcts"], g["h_pcts_unscaled"]) if np.all(np.isfinite(g["h_pcts"][[0, -1]])) else np.inf
    )
    g["ci_widening_W"] = widening(g["W_pcts"], g["W_pcts_unscaled"])
    g["note"] += (
        f"{_verdict(g)}: a between-interval scatter of {100 * g['tau']:.1f} % in W_A was added to every interval "
        f"(random effects), which moved h from {g['h_unscaled'] * 1e9:.3g} to {g['h'] * 1e9:.3g} nm and widened the "
        + (
            f"95 % interval of h by {g['ci_widening_h']:.2f}x"
            if np.isfinite(g["ci_widening_h"])
            else "95 % interval of h until it reaches the end of the h grid (open)"
        )
        + f" and of W_A by {g['ci_widening_W']:.2f}x"
        + (
            f" (h's interval holds ln h +- {JACKKNIFE_Z * jk:.2f}, {JACKKNIFE_Z:g} x the jackknife spread of the "
            "estimates without any one interval: the disagreement may be one interval's). "
            if np.isfinite(jk)
            else ". "
        )
    )


JACKKNIFE_Z = 1.96  # the 95 % interval of h holds ln h +- this x the jackknife SD (normal)


def leave_one_out_spread(x, Yc, C, tau2, x0):
    """Jackknife SD of ln h over the global fits that leave one interval out (Tukey; with the same
    between-interval variance tau^2), NaN with fewer than 3 intervals.  Random effects spread a
    disagreement over every interval; when one interval is wrong (a reference whose pull-off is
    10 % off) its share is far larger than tau, and how far h moves without it is the honest
    measure: on wrong-reference wear tests the 95 % interval of h held the truth in 25 % of tips
    with random effects alone (benchmarks/bench_calibration_coverage.py).  A fit without an
    interval whose minimum is at an end of the grid counts at that end."""
    n = Yc.shape[1]
    if n < 3:
        return np.nan
    xs_l = []
    for i in range(n):
        keep = [j for j in range(n) if j != i]
        _, xs, _, edge = min_chi2(x, Yc[:, keep], precision(C[:, keep][:, :, keep], tau2=tau2))
        xs_l.append(x[0] if edge < 0 else x[-1] if edge > 0 else xs)
    xs_l = np.asarray(xs_l, float)
    if not np.all(np.isfinite(xs_l)):
        return np.nan
    return float(np.sqrt((n - 1) / n * np.sum((xs_l - xs_l.mean()) ** 2)))


def _cover_jackknife(g, x, jk):
    """Widen every percentile of h away from the median to hold ln h + z x ``jk`` (z its normal
    quantile: +-1.96 for the 95 % interval, +-1 for the 68 % one); beyond the h grid a bound is
    open (NaN)."""
    x0 = np.log(g["h"])
    p = np.array(g["h_pcts"], float)
    for k, pct in enumerate(CI_PCTS):
        z = float(ndtri(pct / 100.0))
        if z == 0.0 or not np.isfinite(p[k]):
            continue
        b = x0 + z * jk
        if b < x[0] or b > x[-1]:
            p[k] = np.nan
        else:
            p[k] = min(p[k], np.exp(b)) if z < 0 else max(p[k], np.exp(b))
    g["h_pcts"] = p


def widen_if_inconsistent(g, x0, m0, xss, mss, edge_s, x):
    """Scale the spread of the per-sample global h and W_A by the Birge ratio.

    The GLS chi^2 of the intervals about the common W_A(h) at the estimate, with dof = number
    of intervals - 2 (h and W_A fitted), says whether they agree within the uncertainties the
    Monte Carlo carries.  When chi^2/dof > 1 they disagree more than those allow (an InvOLS not
    remeasured after a remount, a biased reference, a shape error), by an amount the data show
    but whose cause they do not: every interval's uncertainty is scaled by B = sqrt(chi^2/dof)
    (Birge 1932; the Particle Data Group's scale factor), which scales the spread of the
    per-sample estimates about the central one (x0 = ln h, m0 = ln W_A) by B.  A multiplicative
    scale (rather than an added between-interval variance) keeps the relative weights the data
    support and needs no further parameter, which 1-4 degrees of freedom cannot estimate; it
    never narrows (B >= 1)."""
    if g["dof"] <= 0:
        g["birge_ratio"] = np.nan
        g["note"] += UNTESTABLE
        return
    g["p_value"] = float(chdtrc(g["dof"], g["chi2_min"]))
    B = birge_ratio(g["chi2_min"], g["dof"])
    g["birge_ratio"] = B
    if B <= 1.0:
        return
    xw = x0 + B * (xss - x0)
    mw = m0 + B * (mss - m0)
    # a widened sample beyond the grid is open (censored) on that side
    side = np.where(np.isfinite(xw) & (xw < x[0]), -1, np.where(np.isfinite(xw) & (xw > x[-1]), 1, edge_s))
    xw = np.where((xw < x[0]) | (xw > x[-1]), np.nan, xw)
    _percentiles(g, xw, mw, side)
    g["note"] += (
        f"{_verdict(g)}: the confidence intervals of h and W_A "
        f"are widened by the Birge ratio sqrt(chi2/dof) = {B:.2f}. "
    )
