"""Where each worn interval's W_A(h) meets the reference.

The roots of D(h) = ln W(h) - ln W_ref(h) on the grid, refined by linear interpolation in
ln h; the same per MC sample (the root nearest the central one) gives percentile confidence
intervals.  Explicit status, never a made-up number: ``ok``, ``no_crossing`` (side: the curves
approach each other ``below``/``above`` the grid), ``multiple_crossings`` (all roots listed),
``n_too_close_to_2`` (n - 2 < 3 sigma_n or |dD/d ln h| < MIN_SLOPE: the curve cannot constrain
h), ``reference``, ``unusable`` (invalid fit, n far below 2, no finite W_A).
"""

from __future__ import annotations

import numpy as np

from pipeline.adhesion_range.curves import CI_PCTS, ROW_CHUNK, censored_percentiles, first_finite, row_starts
from pipeline.inversion.shape import USABLE_N_FLAGS

MIN_SLOPE = 0.05  # |d ln(W/W_ref) / d ln h| below this cannot constrain h
N_SIGMA_NEAR_2 = 3.0  # n - 2 < 3 sigma_n: too close to a paraboloid
STATUSES = ("ok", "no_crossing", "multiple_crossings", "n_too_close_to_2", "reference", "unusable")


def crossings(x, d):
    """Roots of d(x) (1-D) from sign changes on the grid, linear interpolation in x; a list."""
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


def sample_crossings(x, D, target):
    """Per-sample root of D (S, H) nearest to ``target`` (x units), vectorised.

    Returns (root, side): root NaN when the sample has none; side -1 when the curves
    approach each other below the grid, +1 above, 0 if a root exists or undetermined.
    """
    n_samples = D.shape[0]
    a, b = D[:, :-1], D[:, 1:]
    ok = np.isfinite(a) & np.isfinite(b)
    sc = ok & ((a * b < 0) | (a == 0))
    with np.errstate(divide="ignore", invalid="ignore"):
        xr = np.where(sc, x[:-1] + a * (x[1:] - x[:-1]) / np.where(a - b == 0, 1.0, a - b), np.nan)
    dist = np.where(sc, np.abs(xr - target), np.inf)
    has = sc.any(axis=1)
    j = np.argmin(dist, axis=1)
    root = np.where(has, xr[np.arange(n_samples), j], np.nan)
    # side of a missing root: end where |D| is smaller
    absd = np.abs(np.where(np.isfinite(D), D, np.nan))
    lo = first_finite(absd)
    hi = first_finite(absd[:, ::-1])
    side = np.where(has, 0, np.where(lo < hi, -1, np.where(hi < lo, 1, 0)))
    return root, side


def interval_crossing(d: dict, yc, ys, ref_c, ref_s, h) -> dict:
    """Status and crossing of one interval (``d``: its entry of ``load_inversion``; yc, ys its
    central (H,) and sampled (S, H) ln W_A; ref_c, ref_s the reference's; h the grid, m)."""
    x = np.log(h)
    info = {
        "crossings": [],
        "h": np.nan,
        "h_pcts": np.full(len(CI_PCTS), np.nan),
        "side": "",
        "slope": np.nan,
        "crossing_fraction": np.nan,
        "note": "",
    }
    if d["reference"]:
        return {**info, "status": "reference"}
    if d["n_flag"] not in USABLE_N_FLAGS or not np.any(np.isfinite(yc)):
        return {**info, "status": "unusable", "note": f"n flag {d['n_flag']}; no finite W_A(h)"}
    Dc = yc - ref_c
    roots = crossings(x, Dc)
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
        info["note"] = (
            f"n = {d['n']:.3f} +/- {u_n:.3f}, |d ln(W/W_ref)/d ln h| = {abs(sl):.3f}: "
            f"W_A(h) too flat to constrain h (need n - 2 >= {N_SIGMA_NEAR_2:g} sigma_n and slope >= {MIN_SLOPE})"
        )
        return info
    if len(roots) == 0:
        return {**info, **_no_crossing(Dc, h)}
    target = roots[0] if len(roots) == 1 else float(np.median(roots))
    parts = [sample_crossings(x, ys[a : a + ROW_CHUNK] - ref_s[a : a + ROW_CHUNK], target) for a in row_starts(ys)]
    root_s, side_s = (np.concatenate([p[k] for p in parts]) for k in (0, 1))
    info["crossing_fraction"] = float(np.mean(np.isfinite(root_s)))
    info["h_samples"] = np.exp(root_s)
    info["h_pcts"] = np.exp(censored_percentiles(root_s, side_s, CI_PCTS))
    if len(roots) > 1:
        info["status"] = "multiple_crossings"
        info["note"] = "W_A(h) meets the reference at h = " + ", ".join(f"{r * 1e9:.3g}" for r in np.exp(roots)) + " nm"
        return info
    info["status"] = "ok"
    info["h"] = float(np.exp(roots[0]))
    return info


def _no_crossing(Dc, h) -> dict:
    """Status, side and note of a curve that stays on one side of the reference on the grid."""
    absd = np.abs(Dc)
    lo, hi = first_finite(absd[None, :])[0], first_finite(absd[None, ::-1])[0]
    side = "below" if lo < hi else "above"
    edge = h[0] if lo < hi else h[-1]
    rel = "above" if np.nanmedian(Dc) > 0 else "below"
    return {
        "status": "no_crossing",
        "side": side,
        "note": (
            f"W_A(h) stays {rel} the reference on the whole grid; the curves approach each other "
            f"{side} the grid (h {'<' if lo < hi else '>'} {edge * 1e9:.3g} nm)"
        ),
    }
