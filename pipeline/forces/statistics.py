"""Per-interval pull-off statistics with outlier flagging.

Rule (Iglewicz & Hoaglin 1993): modified z-score M_i = 0.6745 (x_i - median) / MAD
over the accepted curves; |M_i| > threshold (default 3.5) flags an outlier.  With
fewer than 3 curves or MAD = 0 nothing is flagged.  Outliers stay in the file; the
mean, standard deviation (ddof = 1; NaN for a single curve) and standard error are
over the accepted, non-outlier curves.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np


@dataclass
class IntervalStats:
    mean: float
    std: float
    sem: float
    median: float
    n_used: int
    modified_z: np.ndarray
    outlier: np.ndarray


def modified_z_scores(x) -> np.ndarray:
    """0.6745 (x - median) / MAD; zeros when MAD = 0 or fewer than 3 values."""
    x = np.asarray(x, float)
    if x.size < 3:
        return np.zeros_like(x)
    med = np.median(x)
    mad = np.median(np.abs(x - med))
    return 0.6745 * (x - med) / mad if mad > 0 else np.zeros_like(x)


def interval_stats(values, accepted, threshold: float = 3.5) -> IntervalStats:
    """Statistics of ``values`` over ``accepted`` curves (bool mask, same length)."""
    values, accepted = np.asarray(values, float), np.asarray(accepted, bool)
    mz = np.full(values.size, np.nan)
    mz[accepted] = modified_z_scores(values[accepted])
    outlier = accepted & (np.abs(np.nan_to_num(mz)) > threshold)
    used = values[accepted & ~outlier]
    n = used.size
    if n == 0:
        raise ValueError("no accepted curves")
    std = float(used.std(ddof=1)) if n > 1 else float("nan")
    sem = std / np.sqrt(n) if n > 1 else float("nan")
    return IntervalStats(float(used.mean()), std, float(sem), float(np.median(used)), int(n), mz, outlier)
