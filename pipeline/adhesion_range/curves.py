"""ln W_A(h) curves of the intervals and percentiles of per-sample estimates."""

from __future__ import annotations

import numpy as np

from pipeline.inversion.io import samples_on_h_grid

CI_PCTS = (2.5, 16.0, 50.0, 84.0, 97.5)
ROW_CHUNK = 1024  # Monte-Carlo samples per chunk of per-sample work (temporaries stay in the CPU's cache)


def row_starts(samples, chunk=ROW_CHUNK):
    """First row of every chunk of ``chunk`` Monte-Carlo samples (axis 0) of ``samples``."""
    return range(0, max(len(samples), 1), chunk)


def ln_positive(x):
    """ln x where x is finite and > 0, NaN elsewhere."""
    x = np.asarray(x, float)
    out = np.full(x.shape, np.nan)
    ok = np.isfinite(x) & (x > 0)
    out[ok] = np.log(x[ok])
    return out


class LawCurves:
    """ln W_A(h) of every interval for one law of an inversion (``load_inversion``): central
    (H,) and Monte-Carlo samples (S, H) on the full h grid, computed once per interval."""

    def __init__(self, inv: dict, law: str):
        self._inv = inv
        self._law = law
        self._cache = {}

    def __call__(self, nm: str):
        if self._cache.get(nm, (None, None))[1] is None:  # not yet, or released by stacked_samples
            d = self._inv["intervals"][nm]["laws"][self._law]
            self._cache[nm] = (ln_positive(d["W_A"]), self._ln_samples(d["W_A_samples"]))
        return self._cache[nm]

    def stacked_samples(self, names):
        """The sampled ln W_A(h) of the intervals ``names`` as one array (S, H, I); each interval's
        own copy is released as it is moved in (only the central curves stay cached), so that the
        samples are held once."""
        out = None
        for i, nm in enumerate(names):
            yc, ys = self(nm)
            if out is None:
                out = np.empty((*ys.shape, len(names)))
            out[..., i] = ys
            self._cache[nm] = (yc, None)
        return out

    def _ln_samples(self, samples):
        """ln W_A of the samples on the full h grid, ``ROW_CHUNK`` samples at a time."""
        out = np.empty((len(samples), self._inv["h"].size))
        for a in row_starts(samples):
            out[a : a + ROW_CHUNK] = ln_positive(samples_on_h_grid(self._inv, samples[a : a + ROW_CHUNK]))
        return out


def nanvar_cols(y):
    """Variance (ddof 1) of every column over its finite values (NaN with fewer than 2)."""
    fin = np.isfinite(y)
    cnt = fin.sum(axis=0)
    yz = np.where(fin, y, 0.0)
    with np.errstate(divide="ignore", invalid="ignore"):
        m = yz.sum(axis=0) / cnt
        v = (np.where(fin, (y - m) ** 2, 0.0)).sum(axis=0) / (cnt - 1)
    return np.where(cnt > 1, v, np.nan)


def wmean_ln(Y_list, var_list):
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


def first_finite(a):
    """The first finite value of every row (inf where a row has none)."""
    fin = np.isfinite(a)
    idx = np.argmax(fin, axis=1)
    v = a[np.arange(a.shape[0]), idx]
    return np.where(fin.any(axis=1), v, np.inf)


def censored_percentiles(values, side, pcts):
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
