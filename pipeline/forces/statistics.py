"""Per-interval pull-off statistics with outlier flagging.

Default rule: the generalized ESD test (Rosner 1983) at significance ``alpha``
(config default 0.01) over the accepted curves, testing for up to floor(n/3)
outliers; it assumes normal scatter and is calibrated for small samples (at n = 8
a clean interval is flagged with probability ~2 % at alpha = 0.01, ~7 % at 0.05).
A curve is dropped only on strong evidence, so genuine scatter stays in the
standard error.  Alternative rule "modified_z"
(Iglewicz & Hoaglin 1993): |0.6745 (x - median) / MAD| > threshold.  The MAD rule
is kept as a diagnostic but is not the default: with the 5-10 curves of an
interval the MAD is itself so noisy that genuine 3 % scatter gets flagged and the
standard error is then underestimated.  With fewer than 3 curves nothing is
flagged.  Outliers stay in the file; the mean, standard deviation (ddof = 1; NaN
for a single curve) and standard error are over the accepted, non-outlier curves.

Mean: with each curve's own uncertainty u_i, a random-effects weighted mean
(DerSimonian & Laird 1986): the between-curve variance tau^2 (genuine pull-off scatter,
which usually dominates) is estimated from the curves, and each curve is weighted by
1 / (u_i^2 + tau^2).  Curves of ordinary quality then weigh alike (the plain mean when the
u_i are equal), while a curve whose reading is far less certain (a jittered jump-off, a
noisy contact line) cannot move the mean much.  Its standard error is the modified
Knapp-Hartung one (Knapp & Hartung 2003; Roever et al. 2015): sqrt(max(1, q) / sum w),
q = sum w (x - mean)^2 / (n - 1), which is std / sqrt(n) for equal u_i and never below what
the curves' own uncertainties allow.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.special import stdtrit  # Student t quantile (scipy.stats costs ~0.5 s of start-up)


@dataclass
class IntervalStats:
    mean: float
    std: float
    sem: float
    median: float
    n_used: int
    modified_z: np.ndarray
    outlier: np.ndarray
    weight: np.ndarray  # relative weight of each curve in the mean (0: not used; sums to 1)
    tau: float = float("nan")  # between-curve scatter (random-effects SD; NaN without u)


def modified_z_scores(x) -> np.ndarray:
    """0.6745 (x - median) / MAD; zeros when MAD = 0 or fewer than 3 values."""
    x = np.asarray(x, float)
    if x.size < 3:
        return np.zeros_like(x)
    med = np.median(x)
    mad = np.median(np.abs(x - med))
    return 0.6745 * (x - med) / mad if mad > 0 else np.zeros_like(x)


def generalized_esd(x, alpha: float = 0.05, max_outliers: int | None = None) -> np.ndarray:
    """Boolean mask of outliers by Rosner's (1983) generalized ESD test.

    R_i = max |x - mean| / sd over the values left after removing the i-1 most
    extreme; lambda_i = (n-i) t_{p, n-i-1} / sqrt((n-i-1 + t^2)(n-i+1)) with
    p = 1 - alpha / (2 (n-i+1)); the number of outliers is the largest i with
    R_i > lambda_i.
    """
    x = np.asarray(x, float)
    n = x.size
    out = np.zeros(n, bool)
    r = n // 3 if max_outliers is None else max_outliers
    if n < 3 or r < 1:
        return out
    idx = np.arange(n)
    removed, n_out = [], 0
    keep = np.ones(n, bool)
    for i in range(1, r + 1):
        v = x[keep]
        sd = v.std(ddof=1)
        if not sd > 0:
            break
        dev = np.abs(v - v.mean()) / sd
        j = int(np.argmax(dev))
        m = n - i + 1  # values in this step
        t = stdtrit(m - 2, 1.0 - alpha / (2.0 * m))
        lam = (m - 1) * t / np.sqrt((m - 2 + t**2) * m)
        removed.append(idx[keep][j])
        if dev[j] > lam:
            n_out = i
        keep[idx[keep][j]] = False
    out[removed[:n_out]] = True
    return out


def random_effects_mean(x, u):
    """(mean, sem, tau, weights) of values ``x`` with 1-sigma uncertainties ``u`` (module doc).

    Non-finite or non-positive u are replaced by the median of the others (by 1 if none)."""
    x, u = np.asarray(x, float), np.asarray(u, float)
    ok = np.isfinite(u) & (u > 0)
    u = np.where(ok, u, np.median(u[ok]) if ok.any() else 1.0)
    n = x.size
    w = 1.0 / u**2
    if n < 2:
        return float(x.mean()), float("nan"), float("nan"), np.ones(n)
    m = float(np.sum(w * x) / w.sum())
    q_dl = float(np.sum(w * (x - m) ** 2))
    tau2 = max(0.0, (q_dl - (n - 1)) / (w.sum() - np.sum(w**2) / w.sum()))
    w = 1.0 / (u**2 + tau2)
    m = float(np.sum(w * x) / w.sum())
    q = float(np.sum(w * (x - m) ** 2)) / (n - 1)
    return m, float(np.sqrt(max(q, 1.0) / w.sum())), float(np.sqrt(tau2)), w / w.sum()


def interval_stats(
    values, accepted, threshold: float = 3.5, rule: str = "esd", alpha: float = 0.01, u=None
) -> IntervalStats:
    """Statistics of ``values`` over ``accepted`` curves (bool mask, same length).

    ``rule`` "esd" (generalized ESD at ``alpha``) or "modified_z" (|M| > ``threshold``);
    the modified z-score is returned in either case as a diagnostic.  ``u``: each curve's
    1-sigma uncertainty: the mean and its standard error are then the random-effects ones
    (module doc); without it, the plain mean and std / sqrt(n).
    """
    values, accepted = np.asarray(values, float), np.asarray(accepted, bool)
    mz = np.full(values.size, np.nan)
    mz[accepted] = modified_z_scores(values[accepted])
    outlier = np.zeros(values.size, bool)
    if rule == "esd":
        outlier[accepted] = generalized_esd(values[accepted], alpha)
    elif rule == "modified_z":
        outlier = accepted & (np.abs(np.nan_to_num(mz)) > threshold)
    else:
        raise ValueError(f"unknown outlier rule {rule!r} (esd or modified_z)")
    used_mask = accepted & ~outlier
    used = values[used_mask]
    n = used.size
    if n == 0:
        raise ValueError("no accepted curves")
    std = float(used.std(ddof=1)) if n > 1 else float("nan")
    weight = np.zeros(values.size)
    if u is None:
        mean, sem, tau = float(used.mean()), (std / np.sqrt(n) if n > 1 else float("nan")), float("nan")
        weight[used_mask] = 1.0 / n
    else:
        mean, sem, tau, weight[used_mask] = random_effects_mean(used, np.asarray(u, float)[used_mask])
    return IntervalStats(mean, std, float(sem), float(np.median(used)), int(n), mz, outlier, weight, tau)
