"""Stage 5: the adhesion range h where the worn intervals' W_A(h) meet the reference.

Paper Sec. 4.1 (Fig. 3b/d) and Sec. 4.3 (Table 1): W_A is assumed constant over the
wear test and is taken from the paraboloidal (n ~ 2) reference interval(s), whose
W_A(h) is nearly independent of h.  For a worn interval (n > 2), W_A(h) depends
strongly on h; h is where the two curves meet.

Per traction law this stage computes

* the reference curve W_ref(h): inverse-variance weighted mean of ln W_A(h) of the
  reference intervals (weights from the Monte-Carlo variance at each h), per MC sample;
  its value and its variation over the grid (max relative change over h >= 0.3 nm);
* per worn interval the roots of D(h) = ln W(h) - ln W_ref(h) on the grid, refined by
  linear interpolation in ln h; the same per MC sample (the root nearest the central
  one) gives percentile confidence intervals.  Explicit status, never a made-up number:
  ``ok``, ``no_crossing`` (side: the curves approach each other ``below``/``above`` the
  grid), ``multiple_crossings`` (all roots listed), ``n_too_close_to_2`` (n - 2 <
  3 sigma_n or |dD/d ln h| < MIN_SLOPE: the curve cannot constrain h),
  ``reference``, ``unusable`` (invalid fit, n far below 2, no finite W_A);
* a global estimate: at every h the common W_A is the generalised-least-squares mean of
  ln W_A(h) of the reference and usable worn intervals with the covariance Sigma(h)
  estimated from the MC samples (this keeps the shared calibration/E* errors from
  counting as inconsistency), chi2(h) its residual; h = argmin chi2 refined by a
  parabola in ln h; W_A = GLS mean there.  The CI comes from repeating the minimisation
  for every MC sample (percentiles of the per-sample estimates).  Where the intervals disagree
  more than their uncertainties allow (chi2_min/dof > 1), the spread of the per-sample
  estimates is scaled by the Birge ratio sqrt(chi2_min/dof) and the note says so and by how
  much (``_widen_if_inconsistent``); with one worn interval it says that agreement cannot be
  tested.

Range conventions: L-J in the z0 = h/0.974 convention (the h reported is the
Dugdale-equivalent h; z0 is given too); Tri2 h is the Dugdale-equivalent h (separation
of the peak stress); its full range 2h is reported separately (the paper's Table 1
uses 2h for Tri2).
"""
from __future__ import annotations

import logging
import time
from pathlib import Path

import h5py
import numpy as np

from pipeline.h5io import atomic_h5, create_group, read_attr_json, read_dataset, write_dataset
from pipeline.inversion import CONVENTIONS, LJ_Z0_OVER_H, load_inversion

log = logging.getLogger(__name__)

MIN_SLOPE = 0.05          # |d ln(W/W_ref) / d ln h| below this cannot constrain h
N_SIGMA_NEAR_2 = 3.0      # n - 2 < 3 sigma_n: too close to a paraboloid
H_FLATNESS_MIN = 0.3e-9   # the paper's check: W_ref(h) nearly constant for h >= 0.3 nm
CI_PCTS = (2.5, 16.0, 50.0, 84.0, 97.5)
MIN_SAMPLES_FOR_COV = 20
STATUSES = ("ok", "no_crossing", "multiple_crossings", "n_too_close_to_2", "reference", "unusable")


# ------------------------------------------------------------------- small helpers
def _crossings(x, d):
    """Roots of d(x) from sign changes on the grid, linear interpolation in x.

    ``d`` may be (H,) or (S, H).  Returns a list (1-D input) of root x values.
    """
    d = np.asarray(d, float)
    fin = np.isfinite(d)
    roots = []
    for j in range(d.size - 1):
        if not (fin[j] and fin[j + 1]):
            continue
        a, b = d[j], d[j + 1]
        if a == 0.0:
            roots.append(x[j])
        elif a * b < 0:
            roots.append(x[j] + a * (x[j + 1] - x[j]) / (a - b))
    if fin[-1] and d[-1] == 0.0:
        roots.append(x[-1])
    return roots


def _sample_crossings(x, D, target):
    """Per-sample root nearest to ``target`` (x units), vectorised.

    Returns (root, side): root NaN when the sample has none; side -1 when the curves
    approach each other below the grid, +1 above, 0 if a root exists or undetermined.
    """
    S, H = D.shape
    a, b = D[:, :-1], D[:, 1:]
    ok = np.isfinite(a) & np.isfinite(b)
    sc = ok & ((a * b < 0) | (a == 0))
    with np.errstate(divide="ignore", invalid="ignore"):
        xr = np.where(sc, x[:-1] + a * (x[1:] - x[:-1]) / np.where(a - b == 0, 1.0, a - b), np.nan)
    dist = np.where(sc, np.abs(xr - target), np.inf)
    has = sc.any(axis=1)
    j = np.argmin(dist, axis=1)
    root = np.where(has, xr[np.arange(S), j], np.nan)
    # side of a missing root: end where |D| is smaller
    absd = np.abs(np.where(np.isfinite(D), D, np.nan))
    lo = _first_finite(absd)
    hi = _first_finite(absd[:, ::-1])
    side = np.where(has, 0, np.where(lo < hi, -1, np.where(hi < lo, 1, 0)))
    return root, side


def _first_finite(a):
    fin = np.isfinite(a)
    idx = np.argmax(fin, axis=1)
    v = a[np.arange(a.shape[0]), idx]
    return np.where(fin.any(axis=1), v, np.inf)


def censored_percentiles(values, side, pcts, lo_edge, hi_edge):
    """Percentiles of per-sample estimates with censoring at the grid edges.

    Samples with no estimate inside the grid count as -inf (side -1) or +inf (+1);
    samples with neither are dropped.  A percentile that falls on a censored sample is
    NaN (the interval is open on that side).
    """
    v = np.asarray(values, float).copy()
    v[np.isnan(v) & (side < 0)] = -np.inf
    v[np.isnan(v) & (side > 0)] = np.inf
    v = v[~np.isnan(v)]
    if v.size == 0:
        return np.full(len(pcts), np.nan)
    v.sort()
    out = []
    for p in pcts:
        k = int(np.clip(np.ceil(p / 100.0 * v.size) - 1, 0, v.size - 1))  # inverted-CDF
        out.append(v[k] if np.isfinite(v[k]) else np.nan)
    return np.array(out)


def sample_covariances(Y):
    """Per-h covariance (H, I, I) of Y (S, H, I) over the samples with all I finite at that h
    (vectorised; NaN where fewer than max(MIN_SAMPLES_FOR_COV, I + 2) samples are)."""
    S, H, I = Y.shape
    ok = np.all(np.isfinite(Y), axis=2)  # (S, H)
    n = ok.sum(axis=0)
    Yz = np.where(ok[..., None], Y, 0.0)
    with np.errstate(divide="ignore", invalid="ignore"):
        mean = Yz.sum(axis=0) / n[:, None]
        D = np.where(ok[..., None], Yz - mean[None], 0.0)
        Dh = np.moveaxis(D, 0, 1)  # (H, S, I): one batched matrix product per h
        C = np.matmul(np.swapaxes(Dh, 1, 2), Dh) / (n - 1)[:, None, None]
    C[n < max(MIN_SAMPLES_FOR_COV, I + 2)] = np.nan
    return C


def precision(C, ridge=1e-10, tau2=0.0):
    """Inverse of C (H, I, I) with a small ridge and ``tau2`` added to every interval's variance
    (a between-interval random effect); NaN where C is."""
    H, I, _ = C.shape
    P = np.full(C.shape, np.nan)
    good = np.all(np.isfinite(C), axis=(1, 2))
    if not good.any():
        return P
    Cg = C[good]
    tr = np.trace(Cg, axis1=1, axis2=2)
    Cg = Cg + np.eye(I)[None] * (ridge + 1e-9 * tr / I + tau2)[:, None, None]
    try:
        P[good] = np.linalg.inv(Cg)
    except np.linalg.LinAlgError:
        P[good] = np.linalg.pinv(Cg)
    return P


def _cov_inverse(Y, ridge=1e-10, tau2=0.0):
    """Per-h inverse covariance of Y (S, H, I) over samples with all I finite, with ``tau2``
    added to every interval's variance (a between-interval random effect)."""
    return precision(sample_covariances(Y), ridge, tau2)


def gls_chi2(Y, P):
    """Common-mean GLS at every h: Y (..., H, I), P (H, I, I) -> (mean, chi2) (..., H)."""
    fin = np.isfinite(Y)
    Yz = np.where(fin, Y, 0.0)
    # a[..., h, i] = sum_j P[h, i, j] Y[..., h, j], as one batched matrix product per h
    Pz = np.nan_to_num(P)
    if Yz.ndim == 2:
        a = np.einsum("hij,hj->hi", Pz, Yz)
    else:
        lead = Yz.shape[:-2]
        Yh = np.moveaxis(Yz.reshape(-1, *Yz.shape[-2:]), 1, 0)  # (H, N, I)
        a = np.moveaxis(np.matmul(Yh, np.swapaxes(Pz, 1, 2)), 0, 1).reshape(*lead, *Yz.shape[-2:])
    one_p_one = np.nansum(P, axis=(1, 2))
    with np.errstate(divide="ignore", invalid="ignore"):
        mean = a.sum(axis=-1) / one_p_one
        chi2 = (Yz * a).sum(axis=-1) - mean**2 * one_p_one
    bad = ~np.all(fin, axis=-1) | ~np.isfinite(one_p_one) | (one_p_one <= 0)
    mean = np.where(bad, np.nan, mean)
    chi2 = np.where(bad, np.inf, np.maximum(chi2, 0.0))
    return mean, chi2


def _argmin_refined(x, chi2, mean):
    """argmin over the last axis with a parabola in x; returns (x*, mean(x*), chi2*, edge).

    ``edge`` is -1/+1 if the discrete minimum is the first/last grid point, 0 inside.
    """
    chi2 = np.atleast_2d(chi2)
    mean = np.atleast_2d(mean)
    n, H = chi2.shape
    fin = np.isfinite(chi2)
    c = np.where(fin, chi2, np.inf)
    j = np.argmin(c, axis=1)
    any_fin = fin.any(axis=1)
    r = np.arange(n)
    edge = np.where(j == 0, -1, np.where(j == H - 1, 1, 0))
    jm = np.clip(j, 1, H - 2)
    x0, x1, x2 = x[jm - 1], x[jm], x[jm + 1]
    y0, y1, y2 = c[r, jm - 1], c[r, jm], c[r, jm + 1]
    with np.errstate(divide="ignore", invalid="ignore", over="ignore"):
        d1 = (y1 - y0) / (x1 - x0)
        d2 = (y2 - y1) / (x2 - x1)
        curv = (d2 - d1) / (x2 - x0)
        xs = 0.5 * (x0 + x1) - d1 / (2.0 * curv)
    good = (edge == 0) & np.isfinite(xs) & (curv > 0) & np.isfinite(y0) & np.isfinite(y2)
    xstar = np.where(good, np.clip(xs, x0, x2), x[j])
    xstar = np.where(any_fin, xstar, np.nan)
    with np.errstate(invalid="ignore", over="ignore"):
        chi_star = np.where(good, y0 + d1 * (xstar - x0) + curv * (xstar - x0) * (xstar - x1), c[r, j])
    k = np.clip(np.searchsorted(x, np.where(np.isfinite(xstar), xstar, x[0])) - 1, 0, H - 2)
    t = np.clip((np.where(np.isfinite(xstar), xstar, x[0]) - x[k]) / (x[k + 1] - x[k]), 0.0, 1.0)
    mstar = mean[r, k] * (1.0 - t) + mean[r, k + 1] * t
    mstar = np.where(np.isfinite(mstar), mstar, mean[r, j])
    mstar = np.where(any_fin, mstar, np.nan)
    edge = np.where(any_fin, edge, 0)
    return xstar, mstar, np.where(any_fin, chi_star, np.nan), edge


def _wmean_ln(Y_list, var_list):
    """Inverse-variance weighted mean of ln W curves (weights per h, shared by samples)."""
    Y = np.stack(Y_list, axis=-1)
    V = np.stack(var_list, axis=-1)
    with np.errstate(divide="ignore", invalid="ignore"):
        w = np.where(np.isfinite(V) & (V > 0), 1.0 / V, 0.0)
    if np.all(w.sum(axis=-1) == 0):
        w = np.ones_like(V)
    w = np.where(w.sum(axis=-1, keepdims=True) > 0, w, 1.0)
    w = w / w.sum(axis=-1, keepdims=True)
    return np.sum(Y * w, axis=-1)


def _ln(x):
    x = np.asarray(x, float)
    out = np.full(x.shape, np.nan)
    ok = np.isfinite(x) & (x > 0)
    out[ok] = np.log(x[ok])
    return out


# --------------------------------------------------------------------- the analysis
INCONSISTENCY_MODELS = ("random_effects", "birge")


def analyse_law(inv: dict, law: str, inconsistency: str = "random_effects") -> dict:
    """Reference, crossings and global estimate for one traction law (pure function).
    ``inconsistency``: how intervals that disagree beyond their uncertainties widen the
    interval of h and W_A (``random_effects``, the default, or ``birge``; module doc)."""
    h = inv["h"]
    x = np.log(h)
    order = inv["order"]
    ivs = inv["intervals"]
    refs = [nm for nm in order if ivs[nm]["reference"]]
    res = {"law": law, "intervals": {}, "notes": []}
    if not refs:
        raise ValueError("no reference interval (config reference_intervals) in the inversion file")

    cache = {}

    def curves(nm):
        if nm not in cache:
            d = ivs[nm]["laws"][law]
            cache[nm] = (_ln(d["W_A"]), _ln(d["W_A_samples"]))
        return cache[nm]

    # ---- reference
    yc_list, ys_list, var_list = [], [], []
    for nm in refs:
        yc, ys = curves(nm)
        if not np.any(np.isfinite(yc)):
            res["notes"].append(f"reference {nm} has no finite W_A (n flag {ivs[nm]['n_flag']})")
            continue
        yc_list.append(yc)
        ys_list.append(ys)
        var_list.append(_nanvar_cols(ys))
    if not yc_list:
        res["status"] = "no_reference"
        res["reference"] = None
        for nm in order:
            res["intervals"][nm] = {"status": "reference" if nm in refs else "unusable", "crossings": [], "note": "no usable reference"}
        return res
    ref_c = _wmean_ln(yc_list, var_list)
    ref_s = _wmean_ln(ys_list, [v[None, :] * np.ones_like(ys_list[0]) for v in var_list])
    Wc = np.exp(ref_c)
    sel = h >= H_FLATNESS_MIN - 1e-15
    if not np.any(sel):
        sel = np.ones_like(h, bool)
    wsel = Wc[sel][np.isfinite(Wc[sel])]
    flat = float((wsel.max() - wsel.min()) / np.median(wsel)) if wsel.size else np.nan
    res["reference"] = {
        "intervals": [nm for nm in refs],
        "W_ref": Wc,
        "W_ref_pcts": _nanpercentile_cols(np.exp(ref_s), CI_PCTS),
        "ln_samples": ref_s,
        "max_rel_change": flat,
        "flatness_h_min": float(h[sel][0]),
    }

    # ---- per interval crossings
    for nm in order:
        d = ivs[nm]
        info = {"crossings": [], "h": np.nan, "h_pcts": np.full(len(CI_PCTS), np.nan), "side": "",
                "slope": np.nan, "crossing_fraction": np.nan, "note": ""}
        res["intervals"][nm] = info
        if d["reference"]:
            info["status"] = "reference"
            continue
        yc, ys = curves(nm)
        if d["n_flag"] not in ("ok", "n_clipped_to_2") or not np.any(np.isfinite(yc)):
            info["status"] = "unusable"
            info["note"] = f"n flag {d['n_flag']}; no finite W_A(h)"
            continue
        Dc = yc - ref_c
        Ds = ys - ref_s
        roots = _crossings(x, Dc)
        info["crossings"] = [float(np.exp(r)) for r in roots]
        slope = np.gradient(Dc, x)
        if len(roots) >= 1:
            sl = np.interp(roots[0], x, slope)
        else:
            sl = np.nanmedian(np.abs(slope)) if np.any(np.isfinite(slope)) else np.nan
        info["slope"] = float(abs(sl))
        n_used, u_n = float(d["n_used"]), float(d["u_n"])
        if (n_used - 2.0) < N_SIGMA_NEAR_2 * u_n or not (abs(sl) >= MIN_SLOPE):
            info["status"] = "n_too_close_to_2"
            info["note"] = (f"n = {d['n']:.3f} +/- {u_n:.3f}, |d ln(W/W_ref)/d ln h| = {abs(sl):.3f}: "
                            f"W_A(h) too flat to constrain h (need n - 2 >= {N_SIGMA_NEAR_2:g} sigma_n and slope >= {MIN_SLOPE})")
            continue
        if len(roots) == 0:
            info["status"] = "no_crossing"
            absd = np.abs(Dc)
            lo, hi = _first_finite(absd[None, :])[0], _first_finite(absd[None, ::-1])[0]
            info["side"] = "below" if lo < hi else "above"
            edge = h[0] if lo < hi else h[-1]
            rel = "above" if np.nanmedian(Dc) > 0 else "below"
            info["note"] = (f"W_A(h) stays {rel} the reference on the whole grid; the curves approach each other "
                            f"{info['side']} the grid (h {'<' if lo < hi else '>'} {edge * 1e9:.3g} nm)")
            continue
        target = roots[0] if len(roots) == 1 else float(np.median(roots))
        root_s, side_s = _sample_crossings(x, Ds, target)
        info["crossing_fraction"] = float(np.mean(np.isfinite(root_s)))
        info["h_samples"] = np.exp(root_s)
        info["h_pcts"] = np.exp(censored_percentiles(root_s, side_s, CI_PCTS, x[0], x[-1]))
        if len(roots) > 1:
            info["status"] = "multiple_crossings"
            info["note"] = "W_A(h) meets the reference at h = " + ", ".join(f"{r * 1e9:.3g}" for r in np.exp(roots)) + " nm"
            continue
        info["status"] = "ok"
        info["h"] = float(np.exp(roots[0]))

    # ---- global estimate
    used = [nm for nm in order if res["intervals"][nm]["status"] in ("reference", "ok", "multiple_crossings", "n_too_close_to_2")]
    used = [nm for nm in used if np.any(np.isfinite(curves(nm)[0]))]
    constraining = [nm for nm in used if res["intervals"][nm]["status"] in ("ok", "multiple_crossings")]
    g = {"intervals_used": used, "h": np.nan, "W_A": np.nan, "h_pcts": np.full(len(CI_PCTS), np.nan),
         "W_pcts": np.full(len(CI_PCTS), np.nan), "chi2_min": np.nan, "dof": max(len(used) - 2, 0),
         "chi2": np.full(h.shape, np.nan), "W_common": np.full(h.shape, np.nan), "note": ""}
    res["global"] = g
    excluded = [nm for nm in order if nm not in used]
    if excluded:
        g["note"] = "excluded: " + ", ".join(f"{nm} ({res['intervals'][nm]['status']})" for nm in excluded) + ". "
    if not constraining:
        g["status"] = "no_h_constraint"
        g["note"] += "no worn interval constrains h; W_A from the reference only"
        return res
    Yc = np.stack([curves(nm)[0] for nm in used], axis=-1)   # (H, I)
    Ys = np.stack([curves(nm)[1] for nm in used], axis=-1)   # (S, H, I)
    P = _cov_inverse(Ys)
    mc, chic = gls_chi2(Yc, P)
    g["chi2"] = np.where(np.isfinite(chic), chic, np.nan)
    g["W_common"] = np.exp(mc)
    xs, ms, chis, edge = _argmin_refined(x, chic[None, :], mc[None, :])
    ms_s, chi_s = gls_chi2(Ys, P)
    xss, mss, _, edge_s = _argmin_refined(x, chi_s, ms_s)
    g["h_samples"] = np.exp(xss)
    g["W_samples"] = np.exp(mss)
    g["chi2_min"] = float(chis[0])
    g["edge_fraction"] = float(np.mean(edge_s != 0))
    xss_c = np.where(edge_s != 0, np.nan, xss)
    g["h_pcts"] = np.exp(censored_percentiles(xss_c, edge_s, CI_PCTS, x[0], x[-1]))
    g["W_pcts"] = np.exp(censored_percentiles(mss, np.zeros_like(edge_s), CI_PCTS, -np.inf, np.inf))
    if edge[0] != 0 or not np.isfinite(xs[0]):
        g["status"] = "at_grid_edge"
        g["note"] += f"chi2(h) is smallest at the {'lower' if edge[0] < 0 else 'upper'} end of the h grid: no estimate"
        return res
    g["status"] = "ok"
    g["h"] = float(np.exp(xs[0]))
    g["W_A"] = float(np.exp(ms[0]))
    if inconsistency == "birge":
        _widen_if_inconsistent(g, xs[0], ms[0], xss_c, mss, edge_s, x)
    else:
        _random_effects_if_inconsistent(g, x, Yc, Ys)
    return res


def _min_chi2(x, Yc, P):
    mc, chic = gls_chi2(Yc, P)
    xs, ms, chis, edge = _argmin_refined(x, chic[None, :], mc[None, :])
    return float(chis[0]), float(xs[0]), float(ms[0]), int(edge[0])


def between_interval_variance(x, Yc, C, dof, iters=60):
    """Paule-Mandel tau^2 (in (ln W_A)^2): the variance that, added to every interval's (per-h
    covariance ``C`` of the Monte Carlo), brings the global fit's chi^2_min down to its degrees of
    freedom (0 where it is already at or below)."""
    chi0 = _min_chi2(x, Yc, precision(C))[0]
    if dof <= 0 or not np.isfinite(chi0) or chi0 <= dof:
        return 0.0
    lo, hi = -14.0, 0.0  # ln tau^2: tau from 0.1 % to 100 % of W_A
    if _min_chi2(x, Yc, precision(C, tau2=np.exp(hi)))[0] > dof:
        return float(np.exp(hi))
    for _ in range(iters):
        mid = 0.5 * (lo + hi)
        if _min_chi2(x, Yc, precision(C, tau2=np.exp(mid)))[0] > dof:
            lo = mid
        else:
            hi = mid
        if hi - lo < 1e-3:
            break
    return float(np.exp(hi))


def _random_effects_if_inconsistent(g, x, Yc, Ys):
    """Where the intervals disagree more than their uncertainties allow (chi^2_min > dof), a
    between-interval random effect: every interval's ln W_A(h) is given an extra, independent
    offset of variance tau^2 (Paule-Mandel: chi^2_min = dof with it; DerSimonian & Laird 1986,
    Paule & Mandel 1982), constant over h -- an InvOLS not remeasured after a remount, a force
    bias, a contaminated reference, each moving one interval's whole W_A(h) curve.  The global h
    and W_A are re-estimated with it (an interval whose own uncertainty is small no longer
    outweighs the rest: a wrong reference cannot pin W_A alone) and the Monte Carlo draws the
    offsets too, so the intervals widen by what the disagreement needs.  Unlike a Birge scaling,
    which keeps the relative weights, this lets the consistent majority decide the estimate."""
    from scipy.special import chdtrc

    if g["dof"] <= 0:
        g["birge_ratio"] = np.nan
        g["tau"] = np.nan
        g["note"] += ("one worn interval: whether the intervals agree cannot be tested, the interval of h rests on "
                      "the stated uncertainties alone. ")
        return
    g["p_value"] = float(chdtrc(g["dof"], g["chi2_min"]))
    g["birge_ratio"] = birge_ratio(g["chi2_min"], g["dof"])
    C = sample_covariances(Ys)
    tau2 = between_interval_variance(x, Yc, C, g["dof"])
    g["tau"] = float(np.sqrt(tau2))
    if tau2 <= 0.0:
        return
    P = precision(C, tau2=tau2)
    chi, xs, ms, edge = _min_chi2(x, Yc, P)
    S, _, I = Ys.shape
    # the random offsets of the Monte Carlo: seeded by the data's size (deterministic per file)
    eps = np.sqrt(tau2) * np.random.default_rng([S, I, 0x7A0]).standard_normal((S, 1, I))
    ms_s, chi_s = gls_chi2(Ys + eps, P)
    xss, mss, _, edge_s = _argmin_refined(x, chi_s, ms_s)
    xss_c = np.where(edge_s != 0, np.nan, xss)
    g["h_pcts_unscaled"], g["W_pcts_unscaled"] = g["h_pcts"], g["W_pcts"]
    g["h_unscaled"], g["W_A_unscaled"] = g["h"], g["W_A"]
    if edge == 0 and np.isfinite(xs):
        g["h"], g["W_A"] = float(np.exp(xs)), float(np.exp(ms))
    g["h_samples"], g["W_samples"] = np.exp(xss), np.exp(mss)
    g["h_pcts"] = np.exp(censored_percentiles(xss_c, edge_s, CI_PCTS, x[0], x[-1]))
    g["W_pcts"] = np.exp(censored_percentiles(mss, np.zeros_like(edge_s), CI_PCTS, -np.inf, np.inf))
    widen = lambda p, p0: float(np.log(p[-1] / p[0]) / np.log(p0[-1] / p0[0]))  # noqa: E731
    g["ci_widening_h"] = widen(g["h_pcts"], g["h_pcts_unscaled"]) if np.all(np.isfinite(g["h_pcts"][[0, -1]])) else np.inf
    g["ci_widening_W"] = widen(g["W_pcts"], g["W_pcts_unscaled"])
    verdict = "mutually inconsistent" if g["p_value"] < 0.05 else "scattered a little more than their uncertainties allow"
    g["note"] += (f"intervals {verdict} (chi2 = {g['chi2_min']:.3g} for {g['dof']} dof, p = {g['p_value']:.2g}): a "
                  f"between-interval scatter of {100 * g['tau']:.1f} % in W_A was added to every interval (random effects), "
                  f"which moved h from {g['h_unscaled'] * 1e9:.3g} to {g['h'] * 1e9:.3g} nm and widened the 95 % interval of h "
                  f"by {g['ci_widening_h']:.2f}x and of W_A by {g['ci_widening_W']:.2f}x. ")


def birge_ratio(chi2_min: float, dof: int) -> float:
    """sqrt(chi2/dof) when it exceeds 1, else 1 (NaN without degrees of freedom)."""
    if dof <= 0 or not np.isfinite(chi2_min):
        return np.nan
    return float(max(1.0, np.sqrt(max(chi2_min, 0.0) / dof)))


def _widen_if_inconsistent(g, x0, m0, xss, mss, edge_s, x):
    """Scale the spread of the per-sample global h and W_A by the Birge ratio (module doc).

    The GLS chi^2 of the intervals about the common W_A(h) at the estimate, with dof = number
    of intervals - 2 (h and W_A fitted), says whether they agree within the uncertainties the
    Monte Carlo carries.  When chi^2/dof > 1 they disagree more than those allow (an InvOLS not
    remeasured after a remount, a biased reference, a shape error), by an amount the data show
    but whose cause they do not: every interval's uncertainty is scaled by S = sqrt(chi^2/dof)
    (Birge 1932; the Particle Data Group's scale factor), which scales the spread of the
    per-sample estimates about the central one by S.  A multiplicative scale (rather than an
    added between-interval variance) keeps the relative weights the data support and needs no
    further parameter, which 1-4 degrees of freedom cannot estimate; it never narrows (S >= 1)."""
    if g["dof"] <= 0:
        g["birge_ratio"] = np.nan
        g["note"] += ("one worn interval: whether the intervals agree cannot be tested, the interval of h rests on "
                      "the stated uncertainties alone. ")
        return
    from scipy.special import chdtrc

    g["p_value"] = float(chdtrc(g["dof"], g["chi2_min"]))
    S = birge_ratio(g["chi2_min"], g["dof"])
    g["birge_ratio"] = S
    if S <= 1.0:
        return
    xw = x0 + S * (xss - x0)
    mw = m0 + S * (mss - m0)
    # a widened sample beyond the grid is open (censored) on that side
    side = np.where(np.isfinite(xw) & (xw < x[0]), -1, np.where(np.isfinite(xw) & (xw > x[-1]), 1, edge_s))
    xw = np.where((xw < x[0]) | (xw > x[-1]), np.nan, xw)
    g["h_pcts_unscaled"] = g["h_pcts"]
    g["W_pcts_unscaled"] = g["W_pcts"]
    g["h_pcts"] = np.exp(censored_percentiles(xw, side, CI_PCTS, x[0], x[-1]))
    g["W_pcts"] = np.exp(censored_percentiles(mw, np.zeros_like(edge_s), CI_PCTS, -np.inf, np.inf))
    verdict = "mutually inconsistent" if g["p_value"] < 0.05 else "scattered a little more than their uncertainties allow"
    g["note"] += (f"intervals {verdict} (chi2 = {g['chi2_min']:.3g} for {g['dof']} dof, p = {g['p_value']:.2g}): "
                  f"the confidence intervals of h and W_A are widened by the Birge ratio sqrt(chi2/dof) = {S:.2f}. ")


def _nanvar_cols(y):
    fin = np.isfinite(y)
    cnt = fin.sum(axis=0)
    yz = np.where(fin, y, 0.0)
    with np.errstate(divide="ignore", invalid="ignore"):
        m = yz.sum(axis=0) / cnt
        v = (np.where(fin, (y - m) ** 2, 0.0)).sum(axis=0) / (cnt - 1)
    return np.where(cnt > 1, v, np.nan)


def _nanpercentile_cols(x, pcts):
    out = np.full((len(pcts), x.shape[1]), np.nan)
    fin = np.isfinite(x)
    if np.all(fin):
        return np.percentile(x, pcts, axis=0)
    for j in np.flatnonzero(fin.any(axis=0)):
        out[:, j] = np.percentile(x[fin[:, j], j], pcts)
    return out


def reference_at(res: dict, h_grid, h_value):
    """Reference W_A and its percentiles at h (interpolated in ln h)."""
    ref = res["reference"]
    x = np.log(h_grid)
    xv = np.log(h_value)
    w = float(np.exp(np.interp(xv, x, np.log(ref["W_ref"]))))
    k = int(np.clip(np.searchsorted(x, xv) - 1, 0, x.size - 2))
    t = float(np.clip((xv - x[k]) / (x[k + 1] - x[k]), 0.0, 1.0))
    ls = ref["ln_samples"]
    s = np.exp(ls[:, k] * (1.0 - t) + ls[:, k + 1] * t)
    s = s[np.isfinite(s)]
    pc = np.percentile(s, CI_PCTS) if s.size else np.full(len(CI_PCTS), np.nan)
    return w, pc


# ------------------------------------------------------------------------ the stage
def run_adhesion_range(inversion_h5, out_h5, report_csv=None, fig_dir=None, *, tip: str = "",
                       w_of_h_png=None, adhesion_map_png=None, inconsistency: str = "random_effects"):
    """Stage 5: reference W_A, per-interval crossings, global h and W_A per traction law.

    Writes ``out_h5``; if given, the per-tip report CSV (pipeline.reports) and the
    figures ``fig_dir/W_A_vs_h.png`` and ``fig_dir/adhesion_map.png`` (or the explicit
    paths ``w_of_h_png`` / ``adhesion_map_png``).  Returns {law: analysis dict}.
    """
    t0 = time.perf_counter()
    inv = load_inversion(inversion_h5)
    tip = tip or inv.get("tip") or ""
    h = inv["h"]
    results = {law: analyse_law(inv, law, inconsistency) for law in inv["laws"]}
    for law, res in results.items():
        g = res.get("global", {})
        for nm, info in res["intervals"].items():
            log.info("%s %s %s: %s%s%s", tip, law, nm, info["status"],
                     f", crosses the reference at h = {info['h'] * 1e9:.3g} nm" if np.isfinite(info.get("h", np.nan)) else "",
                     f" ({info['note']})" if info.get("note") else "")
        if g.get("status") == "ok":
            hp, wp = g["h_pcts"], g["W_pcts"]
            log.info("%s %s: h = %.3g nm [%.3g, %.3g], W_A = %.4g mJ/m^2 [%.4g, %.4g] (95 %% Monte Carlo percentiles; "
                     "chi2 %.3g for %d dof; %s)", tip, law, g["h"] * 1e9, hp[0] * 1e9, hp[-1] * 1e9, g["W_A"] * 1e3,
                     wp[0] * 1e3, wp[-1] * 1e3, g["chi2_min"], g["dof"], g.get("note", "").strip() or "consistent")
        else:
            log.info("%s %s: %s %s", tip, law, g.get("status", res.get("status", "")), g.get("note", ""))
    write_range_h5(out_h5, inv, results, tip=tip, source=str(inversion_h5))
    if report_csv is not None:
        from pipeline.reports import write_tip_report

        write_tip_report(out_h5, report_csv, tip=tip)
    if fig_dir is not None:
        w_of_h_png = w_of_h_png or Path(fig_dir) / "W_A_vs_h.png"
        adhesion_map_png = adhesion_map_png or Path(fig_dir) / "adhesion_map.png"
    if w_of_h_png is not None or adhesion_map_png is not None:
        from pipeline import figures_adhesion as fa

        if w_of_h_png is not None:
            fa.plot_w_of_h(out_h5, w_of_h_png, tip=tip)
        if adhesion_map_png is not None:
            fa.plot_adhesion_map(out_h5, adhesion_map_png, tip=tip)
    log.info("adhesion range for %s done in %.2f s (h grid %d points)", tip, time.perf_counter() - t0, h.size)
    return results


def write_range_h5(out_h5, inv, results, *, tip="", source=""):
    h = inv["h"]
    with atomic_h5(out_h5, stage="adhesion_range", tip=tip, source=source, laws=list(results),
                   interval_order=inv["order"], conventions=CONVENTIONS, solver_mode=inv["solver_mode"],
                   mc_samples=int(inv["mc_samples"]), E_star=float(inv["E_star"]),
                   ci_percentiles=list(CI_PCTS), min_slope=MIN_SLOPE, n_sigma_near_2=N_SIGMA_NEAR_2,
                   lj_z0_over_h=LJ_Z0_OVER_H) as f:
        write_dataset(f, "h_grid", h, "m", "adhesion range grid")
        write_dataset(f, "ci_percentiles", np.array(CI_PCTS), "1", "percentiles stored in *_pcts datasets")
        gi = create_group(f, "intervals")
        for nm in inv["order"]:
            d = inv["intervals"][nm]
            g = create_group(gi, nm, scans=d["scans"], reference=d["reference"], n_flag=d["n_flag"])
            for key, unit in (("n", "1"), ("u_n", "1"), ("n_used", "1"), ("ln_Q_used", "1"), ("Q", "m^(n-1)"), ("R", "m"), ("S", "1"),
                              ("F_p_mean", "N"), ("F_p_sem", "N"), ("F_p_std", "N"), ("n_curves", "1"),
                              ("invols", "m/V"), ("u_invols", "m/V"), ("invols_method", "1"), ("invols_contact", "m/V"),
                              ("u_invols_contact", "m/V"), ("invols_check", "1")):
                if key in d:  # the InvOLS keys: inversion files written since InvOLS is per interval
                    write_dataset(g, key, d[key], unit)
            dl = d["laws"].get("dugdale")
            if dl is not None:
                write_dataset(g, "Lambda", dl["Lambda"], "1", "Lambda(h) at the central Dugdale W_A(h)")
                write_dataset(g, "Lambda_boundary", dl["Lambda_boundary"], "1", "Eq. 13")
                write_dataset(g, "rigid_valid", dl["rigid_valid"], "1", "Lambda < Lambda_b(n)")
                write_dataset(g, "model_used", dl["model_used"], "1", "Dugdale model per h")
                if "maugis_lambda" in dl:
                    write_dataset(g, "maugis_lambda", dl["maugis_lambda"], "1", "Maugis parameter at the central W_A(h)")
            for law, dlaw in d["laws"].items():  # which model made the other laws' W_A(h)
                if law != "dugdale" and "model_used" in dlaw:
                    write_dataset(g, f"model_used_{law}", dlaw["model_used"], "1", f"{law} model per h (rigid or elastic)")
        gl_all = create_group(f, "laws")
        for law, res in results.items():
            gl = create_group(gl_all, law, convention=CONVENTIONS[law])
            if res.get("reference") is not None:
                ref = res["reference"]
                gr = create_group(gl, "reference", intervals=ref["intervals"])
                write_dataset(gr, "W_ref", ref["W_ref"], "J/m^2", "reference W_A(h) (central)")
                write_dataset(gr, "W_ref_pcts", ref["W_ref_pcts"], "J/m^2", "percentiles (ci_percentiles) of W_ref(h)")
                write_dataset(gr, "max_rel_change", ref["max_rel_change"], "1",
                              "(max - min)/median of W_ref(h) over h >= flatness_h_min")
                write_dataset(gr, "flatness_h_min", ref["flatness_h_min"], "m", "lower end of the flatness check")
            gint = create_group(gl, "intervals")
            for nm in inv["order"]:
                info = res["intervals"][nm]
                g = create_group(gint, nm, status=info["status"], note=info.get("note", ""), side=info.get("side", ""))
                write_dataset(g, "h_cross", info.get("h", np.nan), "m", "crossing with the reference (NaN unless status ok)")
                write_dataset(g, "crossings", np.asarray(info.get("crossings", []), float), "m", "all roots on the central curves")
                write_dataset(g, "h_pcts", info.get("h_pcts", np.full(len(CI_PCTS), np.nan)), "m",
                              "percentiles of the per-sample crossings (NaN: open, censored at the grid edge)")
                write_dataset(g, "slope", info.get("slope", np.nan), "1", "|d ln(W/W_ref)/d ln h| at the crossing")
                write_dataset(g, "crossing_fraction", info.get("crossing_fraction", np.nan), "1",
                              "fraction of MC samples with a crossing inside the grid")
                if "h_samples" in info:
                    write_dataset(g, "h_samples", info["h_samples"], "m", "per-sample crossing (NaN: none in grid)")
                dl = inv["intervals"][nm]["laws"][law]
                write_dataset(g, "W_A", dl["W_A"], "J/m^2", "central W_A(h) (copied from the inversion)")
                write_dataset(g, "W_A_p16", dl["W_A_p16"], "J/m^2", "16th percentile of the MC W_A(h)")
                write_dataset(g, "W_A_p84", dl["W_A_p84"], "J/m^2", "84th percentile of the MC W_A(h)")
            gg = res.get("global")
            if gg is not None:
                g = create_group(gl, "global", status=gg.get("status", ""), note=gg.get("note", ""),
                                 intervals_used=gg["intervals_used"])
                write_dataset(g, "h", gg["h"], "m", "global h (argmin chi2)")
                write_dataset(g, "W_A", gg["W_A"], "J/m^2", "common W_A at the global h")
                write_dataset(g, "h_pcts", gg["h_pcts"], "m", "percentiles of per-sample global h (NaN: open at grid edge)")
                write_dataset(g, "W_pcts", gg["W_pcts"], "J/m^2", "percentiles of per-sample common W_A")
                write_dataset(g, "chi2", gg["chi2"], "1", "chi2(h) of the GLS common mean")
                write_dataset(g, "W_common", gg["W_common"], "J/m^2", "GLS common W_A(h)")
                write_dataset(g, "chi2_min", gg["chi2_min"], "1")
                write_dataset(g, "dof", gg["dof"], "1", "number of intervals used - 2")
                write_dataset(g, "p_value", gg.get("p_value", np.nan), "1", "chi2 survival probability")
                write_dataset(g, "birge_ratio", gg.get("birge_ratio", np.nan), "1",
                              "max(1, sqrt(chi2_min/dof)) (NaN: dof 0); the CIs are scaled by it only with inconsistency: birge")
                write_dataset(g, "tau", gg.get("tau", np.nan), "1",
                              "between-interval scatter of ln W_A added to every interval (random effects; 0: consistent)")
                for key, desc in (("ci_widening_h", "ratio of the widths of the 95 % interval of h with and without tau"),
                                  ("ci_widening_W", "the same for W_A")):
                    write_dataset(g, key, gg.get(key, 1.0), "1", desc)
                if "h_pcts_unscaled" in gg:
                    write_dataset(g, "h_pcts_unscaled", gg["h_pcts_unscaled"], "m", "h percentiles before the widening")
                    write_dataset(g, "W_pcts_unscaled", gg["W_pcts_unscaled"], "J/m^2", "W_A percentiles before the widening")
                if "h_unscaled" in gg:
                    write_dataset(g, "h_unscaled", gg["h_unscaled"], "m", "global h without the between-interval scatter")
                    write_dataset(g, "W_A_unscaled", gg["W_A_unscaled"], "J/m^2", "global W_A without it")
                if "h_samples" in gg:
                    write_dataset(g, "h_samples", gg["h_samples"], "m", "per-sample global h")
                    write_dataset(g, "W_samples", gg["W_samples"], "J/m^2", "per-sample common W_A")
                    write_dataset(g, "edge_fraction", gg["edge_fraction"], "1", "fraction of samples with the minimum at a grid end")
                if res.get("reference") is not None:
                    hv = gg["h"] if np.isfinite(gg["h"]) else float(np.exp(np.median(np.log(h))))
                    w, pc = reference_at(res, h, hv)
                    write_dataset(g, "W_ref_at_h", w, "J/m^2", "reference W_A at the global h (grid median if none)")
                    write_dataset(g, "W_ref_at_h_pcts", pc, "J/m^2", "percentiles of the reference W_A there")
                    write_dataset(g, "W_ref_h", hv, "m", "h at which W_ref_at_h is evaluated")


def load_range(path) -> dict:
    """Read a stage-5 file into nested dicts (for reports and figures)."""
    out = {"laws": {}, "intervals": {}}
    with h5py.File(path, "r") as f:
        out["tip"] = str(read_attr_json(f, "tip"))
        out["h"] = f["h_grid"][()]
        out["order"] = list(read_attr_json(f, "interval_order"))
        out["solver_mode"] = str(read_attr_json(f, "solver_mode"))
        laws = read_attr_json(f, "laws")
        out["law_order"] = [laws] if isinstance(laws, str) else list(laws)
        for nm in out["order"]:
            g = f["intervals"][nm]
            d = {k: read_dataset(g, k)[0] for k in g}
            d.update(scans=int(g.attrs["scans"]), reference=bool(g.attrs["reference"]), n_flag=str(read_attr_json(g, "n_flag")))
            out["intervals"][nm] = d
        for law in out["law_order"]:
            gl = f["laws"][law]
            L = {"convention": str(read_attr_json(gl, "convention")), "intervals": {}}
            if "reference" in gl:
                L["reference"] = {k: read_dataset(gl["reference"], k)[0] for k in gl["reference"]}
                L["reference"]["intervals"] = read_attr_json(gl["reference"], "intervals")
            for nm in out["order"]:
                g = gl["intervals"][nm]
                d = {k: read_dataset(g, k)[0] for k in g}
                d.update(status=str(read_attr_json(g, "status")), note=str(read_attr_json(g, "note")),
                         side=str(read_attr_json(g, "side")))
                L["intervals"][nm] = d
            if "global" in gl:
                g = gl["global"]
                G = {k: read_dataset(g, k)[0] for k in g}
                G.update(status=str(read_attr_json(g, "status")), note=str(read_attr_json(g, "note")),
                         intervals_used=read_attr_json(g, "intervals_used"))
                if isinstance(G["intervals_used"], str):
                    G["intervals_used"] = [G["intervals_used"]] if G["intervals_used"] else []
                L["global"] = G
            out["laws"][law] = L
    return out
