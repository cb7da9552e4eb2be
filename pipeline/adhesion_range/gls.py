"""Generalised least squares of a common ln W_A over the intervals at every h, with the
per-h covariance of the Monte-Carlo samples, and the minimum of its chi^2 over h."""

from __future__ import annotations

import numpy as np

from pipeline.adhesion_range.curves import ROW_CHUNK

MIN_SAMPLES_FOR_COV = 20
SAMPLE_CHUNK = 8192  # Monte-Carlo samples per chunk of the covariance sums (memory ~ chunk x H x I)


def sample_covariances(Y, chunk=None):
    """Per-h covariance (H, I, I) of Y (S, H, I) over the samples with all I finite at that h
    (vectorised; NaN where fewer than max(MIN_SAMPLES_FOR_COV, I + 2) samples are).

    The samples are summed ``chunk`` (default ``SAMPLE_CHUNK``) at a time, in two passes (mean,
    then the centred products), so that the memory does not grow with the Monte Carlo."""
    S, H, I = Y.shape
    chunk = SAMPLE_CHUNK if chunk is None else int(chunk)
    ok = np.all(np.isfinite(Y), axis=2)  # (S, H)
    n = ok.sum(axis=0)

    def chunks():  # (samples with the non-finite rows zeroed, their finite mask), chunk by chunk
        for a in range(0, S, chunk):
            yield np.where(ok[a : a + chunk, :, None], Y[a : a + chunk], 0.0), ok[a : a + chunk]

    with np.errstate(divide="ignore", invalid="ignore"):
        mean = sum(Yz.sum(axis=0) for Yz, _ in chunks()) / n[:, None]
    C = sum(_centred_products(Yz, okc, mean) for Yz, okc in chunks())
    with np.errstate(divide="ignore", invalid="ignore"):
        C = C / (n - 1)[:, None, None]
    C[n < max(MIN_SAMPLES_FOR_COV, I + 2)] = np.nan
    return C


def _centred_products(Yz, ok, mean):
    """Sum over samples of (y - mean)(y - mean)^T per h, (H, I, I)."""
    with np.errstate(invalid="ignore"):
        D = np.where(ok[..., None], Yz - mean[None], 0.0)
    Dh = np.moveaxis(D, 0, 1)  # (H, S, I): one batched matrix product per h
    return np.matmul(np.swapaxes(Dh, 1, 2), Dh)


def precision(C, ridge=1e-10, tau2=0.0):
    """Inverse of C (H, I, I) with a small ridge and ``tau2`` added to every interval's variance
    (a between-interval random effect); NaN where C is."""
    _, I, _ = C.shape
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


def cov_inverse(Y, ridge=1e-10, tau2=0.0):
    """Per-h inverse covariance of Y (S, H, I) over samples with all I finite, with ``tau2``
    added to every interval's variance (a between-interval random effect)."""
    return precision(sample_covariances(Y), ridge, tau2)


def gls_chi2(Y, P, chunk=None):
    """Common-mean GLS at every h: Y (..., H, I), P (H, I, I) -> (mean, chi2) (..., H).

    Samples (Y of shape (S, H, I)) are taken ``chunk`` (default ``SAMPLE_CHUNK``) at a time."""
    chunk = SAMPLE_CHUNK if chunk is None else int(chunk)
    if Y.ndim == 3 and Y.shape[0] > chunk:
        parts = [_gls_chi2(Y[a : a + chunk], P) for a in range(0, Y.shape[0], chunk)]
        return np.concatenate([m for m, _ in parts]), np.concatenate([c for _, c in parts])
    return _gls_chi2(Y, P)


def sample_minima(x, Ys, P, offsets=None, chunk=None):
    """Per-sample global estimate: the GLS chi^2(h) of every Monte-Carlo sample of Ys (S, H, I)
    (plus ``offsets``, broadcastable to it: the random-effects draws) minimised over x = ln h by
    :func:`argmin_refined`, ``chunk`` (default ``ROW_CHUNK``) samples at a time, so that only the
    per-sample results (S,) are kept: (ln h*, ln W*, edge), each (S,)."""
    chunk = ROW_CHUNK if chunk is None else int(chunk)
    S = Ys.shape[0]
    parts = []
    for a in range(0, S, chunk if S > chunk else max(S, 1)):
        Y = Ys[a : a + chunk] if offsets is None else Ys[a : a + chunk] + offsets[a : a + chunk]
        ms, chi = _gls_chi2(Y, P)
        xs, mstar, _, edge = argmin_refined(x, chi, ms)
        parts.append((xs, mstar, edge))
    return tuple(np.concatenate([p[k] for p in parts]) for k in range(3))


def _gls_chi2(Y, P):
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


def argmin_refined(x, chi2, mean):
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


def min_chi2(x, Yc, P):
    """(chi2_min, ln h*, ln W*, edge) of the central curves Yc (H, I) with precision P."""
    mc, chic = gls_chi2(Yc, P)
    xs, ms, chis, edge = argmin_refined(x, chic[None, :], mc[None, :])
    return float(chis[0]), float(xs[0]), float(ms[0]), int(edge[0])
