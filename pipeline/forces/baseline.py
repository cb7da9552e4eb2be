"""Straight-line fits (baseline offset + tilt, contact slopes)."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np


@dataclass
class Line:
    """y = offset + slope * x; ``rms`` of the residuals of the points kept, ``n`` points kept,
    ``u_slope`` standard error of the slope."""

    offset: float
    slope: float
    rms: float
    n: int
    u_slope: float

    def __call__(self, x):
        return self.offset + self.slope * np.asarray(x)


def _lsq(x, y):
    xm, ym = x.mean(), y.mean()
    dx = x - xm
    sxx = float(np.dot(dx, dx))
    slope = float(np.dot(dx, y - ym)) / sxx if sxx > 0 else 0.0
    return ym - slope * xm, slope, sxx


def fit_line(x, y, clip: float = 3.0) -> Line:
    """Least-squares line with one ``clip``-sigma rejection pass (spikes); needs >= 3 points."""
    x, y = np.asarray(x, float), np.asarray(y, float)
    a, b, _ = _lsq(x, y)
    r = y - (a + b * x)
    s = float(np.sqrt(np.mean(r * r)))
    keep = np.abs(r) <= clip * s if s > 0 else np.ones(x.size, bool)
    if 3 <= keep.sum() < x.size:
        x, y = x[keep], y[keep]
        a, b, _ = _lsq(x, y)
        r = y - (a + b * x)
    _, _, sxx = _lsq(x, y)
    dof = max(x.size - 2, 1)
    rms = float(np.sqrt(np.dot(r, r) / dof))
    u_slope = rms / np.sqrt(sxx) if sxx > 0 else np.inf
    return Line(float(a), float(b), rms, int(x.size), float(u_slope))
