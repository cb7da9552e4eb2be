"""The seeded Monte-Carlo draws of the inversion.

* the pull-off force of the interval: the mean of the accepted curves is sampled from its
  sampling distribution (Student t with n_curves - 1 degrees of freedom around F_p_mean with
  the standard error of the mean; Gaussian when fewer than 3 curves), truncated to F_p > 0;
* the calibration: k systematic, one draw per sample shared by all intervals of the tip; the
  InvOLS of each interval its own draw (the chip is remounted), or the tip's draw where stage 3
  says one InvOLS serves the tip (F_p scales as k * InvOLS);
* the power-law fit (n, ln Q): bivariate normal with the fit covariance, per interval, clipped
  by the n policy (``pipeline.inversion.shape``);
* E*: systematic, one draw per sample shared by all intervals.

The streams: ``SeedSequence([seed, crc32(tip)])`` spawns one child for the shared draws, one per
interval for its own draws and one per interval for its InvOLS, so a tip's result does not
depend on the other tips or on the order of the laws.
"""

from __future__ import annotations

import warnings
import zlib

import numpy as np

from pipeline.inversion.shape import N_MIN, clip_samples


def truncnormal(rng, mean, sd, size):
    """Normal draws truncated to > 0 (resampling); sd <= 0 gives the mean."""
    if not (sd > 0):
        return np.full(size, float(mean))
    x = rng.normal(mean, sd, size)
    for _ in range(100):
        bad = x <= 0
        if not np.any(bad):
            break
        x[bad] = rng.normal(mean, sd, int(bad.sum()))
    return np.where(x > 0, x, np.nan)


def draw_mean(rng, mean, sem, n_curves, size):
    """Sampling distribution of the mean pull-off force, truncated to > 0."""
    if not (np.isfinite(sem) and sem > 0):
        return np.full(size, float(mean))
    dof = n_curves - 1
    draw = (lambda k: mean + sem * rng.standard_t(dof, k)) if dof >= 2 else (lambda k: rng.normal(mean, sem, k))
    x = draw(size)
    for _ in range(100):
        bad = x <= 0
        if not np.any(bad):
            break
        x[bad] = draw(int(bad.sum()))
    return np.where(x > 0, x, np.nan)


def seed_streams(seed: int, tip: str, n_intervals: int):
    """(shared, per-interval, per-interval InvOLS) seed sequences of a tip (module doc)."""
    children = np.random.SeedSequence([int(seed), zlib.crc32(tip.encode())]).spawn(1 + 2 * n_intervals)
    return children[0], children[1 : 1 + n_intervals], children[1 + n_intervals :]


def draw_systematic(ss, cal, E_star, u_E_star, size):
    """Shared draws: calibration factor (k InvOLS)/(k0 InvOLS0) and E*."""
    rng = np.random.default_rng(ss)
    k, u_k, inv, u_inv = cal["k"], cal["u_k"], cal["invols"], cal["u_invols"]
    u_k, u_inv = np.nan_to_num(u_k), np.nan_to_num(u_inv)
    fk = truncnormal(rng, 1.0, u_k / k, size) if np.isfinite(k) and k > 0 else np.ones(size)
    fi = truncnormal(rng, 1.0, u_inv / inv, size) if np.isfinite(inv) and inv > 0 else np.ones(size)
    u_rel = cal.get("u_cal_rel", np.nan)
    if np.isfinite(u_rel):
        # stage 3 gives the relative uncertainty of k * InvOLS with their correlation: use it for
        # the product (the individual factors are kept for the record only)
        cf = truncnormal(rng, 1.0, float(u_rel), size)
    else:
        cf = fk * fi
    u_e = 0.0 if u_E_star is None or not np.isfinite(u_E_star) else float(u_E_star)
    es = truncnormal(rng, E_star, u_e, size)
    return {"k_factor": fk, "invols_factor": fi, "cal_factor": cf, "E_star": es}


def interval_calibration_factor(ss, sysd, forces, size):
    """(k InvOLS)/(k0 InvOLS0) of one interval per MC sample: k drawn once per tip (shared), the
    interval's own InvOLS drawn on its own; a tip-level InvOLS shares the tip's draw (with its
    correlation to a reference-lever k)."""
    if forces["invols_shared"]:
        return sysd["cal_factor"]
    inv, u_inv = forces["invols"], np.nan_to_num(forces["u_invols"])
    fi = (
        truncnormal(np.random.default_rng(ss), 1.0, u_inv / inv, size)
        if np.isfinite(inv) and inv > 0
        else np.ones(size)
    )
    return sysd["k_factor"] * fi


def draw_interval(ss, fit, forces, size):
    """One interval's draws: its mean F_p (before calibration) and (n, ln Q) from the fit
    covariance, clipped by the n policy (``n_raw`` before, ``n_clipped`` where it acted)."""
    rng = np.random.default_rng(ss)
    fp = draw_mean(rng, forces["F_p_mean"], forces["F_p_sem"], forces["n_curves"], size)
    cov = np.asarray(fit["cov_n_lnQ"], float)
    mean = np.array([fit["n"], fit["ln_Q"]])
    if np.all(cov == 0) or not np.all(np.isfinite(cov)):
        nl = np.tile(mean, (size, 1))
    else:
        nl = rng.multivariate_normal(mean, cov, size, method="eigh")
    n_raw = nl[:, 0]
    n, ln_q = clip_samples(n_raw, nl[:, 1], fit["S"])
    return {"F_p_mean": fp, "n_raw": n_raw, "n": n, "ln_Q": ln_q, "n_clipped": n_raw < N_MIN}


PERCENTILES = (16.0, 50.0, 84.0)  # of the W_A(h) samples, stored per law in the inversion file


def sample_percentiles(samples, pcts):
    """Percentiles ``pcts`` over the Monte-Carlo samples (axis 0) of their finite values; NaN
    where a column has none."""
    samples = np.asarray(samples, float)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", RuntimeWarning)  # a column without a finite sample: NaN
        return np.nanpercentile(np.where(np.isfinite(samples), samples, np.nan), pcts, axis=0)
