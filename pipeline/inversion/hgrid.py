"""The adhesion-range grid of the inversion: the Monte-Carlo subset of it and interpolation in ln h."""

from __future__ import annotations

import numpy as np


def mc_grid_index(H: int, points: int):
    """Indices of the (ln-uniform) subset of the h grid used for the MC samples (ends kept)."""
    if points is None or points >= H:
        return np.arange(H)
    points = max(int(points), 3)
    return np.unique(np.round(np.linspace(0, H - 1, points)).astype(int))


def interp_loglog(x_from, y, x_to, log_y=True):
    """Linear interpolation of y (last axis) in ln x (and ln y); NaN propagates to neighbours."""
    y = np.asarray(y, float)
    if x_from.size == x_to.size and np.allclose(x_from, x_to, rtol=0, atol=0):
        return y.copy()
    lx, lt = np.log(x_from), np.log(x_to)
    k = np.clip(np.searchsorted(lx, lt) - 1, 0, lx.size - 2)
    t = (lt - lx[k]) / (lx[k + 1] - lx[k])
    if log_y:
        with np.errstate(divide="ignore", invalid="ignore"):
            ly = np.where(y > 0, np.log(np.where(y > 0, y, 1.0)), np.nan)
        return np.exp(ly[..., k] * (1 - t) + ly[..., k + 1] * t)
    return y[..., k] * (1 - t) + y[..., k + 1] * t
