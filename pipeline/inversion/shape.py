"""Which tip shape an interval is inverted with.

Power index below 2
-------------------
The mechanics is defined for n in [2, 20].  A paraboloidal tip may fit to n slightly
below 2.  Policy (``n_policy`` attribute in the output):

* central n >= 2: used as is;
* 2 - max(3 sigma_n, N_BELOW_2_TOL) <= n < 2: n is clipped to 2 (flag
  ``n_clipped_to_2``); Q is re-expressed keeping the fit's R (Q = R at n = 2, since
  Q = S^(n-2) R^(n-1) (Eq. 2) with R = (Q S^(2-n))^(1/(n-1)) from the fit);
* n further below 2: the interval is unusable (flag ``n_below_2``), its W_A is NaN
  and stage 5 reports it with an explicit status, no number;
* Monte-Carlo draws with n < 2 are clipped the same way (each draw keeps its own R);
  draws with n > 20, non-finite inputs or a Q that no float holds (|ln Q| > ln of the largest
  double, ~709.8; only a draw from a shape the image barely constrains gets there) give NaN and
  are counted in ``valid_fraction``.

A reference interval whose n is consistent with 2 is inverted as the paraboloid of its n = 2 fit
(:func:`shape_for_inversion`); a fit that stage 2 flagged as untrustworthy is not used.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

N_MIN, N_MAX = 2.0, 20.0
N_BELOW_2_TOL = 0.05  # minimum tolerance for clipping a central n < 2 to 2
LN_Q_MAX = float(np.log(np.finfo(float).max))  # |ln Q| beyond this: Q overflows to inf or 0
N_POLICY = (
    "central n >= 2 used as is; 2 - max(3 sigma_n, 0.05) <= n < 2 clipped to 2 keeping R "
    "(flag n_clipped_to_2); lower n: interval unusable (flag n_below_2, W_A NaN); MC draws "
    "with n < 2 clipped keeping their R; draws with n > 20 give NaN"
)
# A reference whose n is within this many sigma of 2 is used as the paraboloid it is meant to be.
REFERENCE_N_SIGMA = 2.0
# sigma_n above which the image hardly constrains the shape (said in the notes).
SHAPE_POORLY_DEFINED_SIGMA_N = 0.2
# Stage-2 fit flags that make an interval unusable (its fit is not a trustworthy tip shape).
UNUSABLE_FIT_FLAGS = frozenset(
    {
        "n_below_1.5",
        "not_converged",
        "n_at_bound",
        "residual_above_pixel",
        "few_points",
        "edge_turns_back",
        "edge_is_core",
        "edge_not_fitted",
    }
)
USABLE_N_FLAGS = ("ok", "n_clipped_to_2")


def shape_for_inversion(fit: dict, reference: bool):
    """(fit used, shape model, note) for one interval.

    A reference interval is the unworn, paraboloidal tip of the method (the paper's n = 2
    interval).  Where its fitted n is consistent with 2 (within REFERENCE_N_SIGMA sigma_n), it
    is used as a paraboloid with R from the paraboloid fit of the same profile (n held at 2,
    ``pipeline.fits.stage.run_fit``, group ``fit_n2``), instead of clipping a free-n fit: with n free, R is
    tied to an uncertain n (a fit of n = 1.70 +- 0.45 clipped to 2 kept an R 12 % off).  A worn
    interval whose n is below 2 but within the clipping tolerance is treated the same way.
    A reference that is not consistent with 2 keeps its power-law fit and the note says the
    method's assumption does not hold.  Without a paraboloid fit (older files) nothing changes."""
    n, u = fit["n"], fit["u_n"]
    para = fit.get("paraboloid")
    consistent = np.isfinite(n) and abs(n - 2.0) <= REFERENCE_N_SIGMA * max(u, 0.0)
    below_tol = np.isfinite(n) and N_MIN - max(3.0 * u, N_BELOW_2_TOL) <= n < N_MIN
    usable_para = para is not None and not (set(para["flags"]) & UNUSABLE_FIT_FLAGS)
    vague = (
        f" The image hardly constrains the shape (sigma_n = {u:.2f}): W_A rests on the paraboloid assumption."
        if u > SHAPE_POORLY_DEFINED_SIGMA_N
        else ""
    )
    if usable_para and ((reference and consistent) or below_tol):
        u_r = para["R"] * float(np.sqrt(max(para["cov_n_lnQ"][1, 1], 0.0)))
        note = (
            f"fitted n = {n:.3f} +- {u:.3f} is consistent with a paraboloid: used as one, R = {para['R'] * 1e9:.3g} "
            f"+- {u_r * 1e9:.2g} nm from the n = 2 fit of the same profile.{vague}"
        )
        return {**fit, **para, "S": fit["S"]}, "paraboloid (n = 2 fit)", note
    if reference and np.isfinite(n) and not consistent:
        return (
            fit,
            "power law",
            (
                f"reference interval fitted n = {n:.3f} +- {u:.3f}, {abs(n - 2.0) / max(u, 1e-12):.1f} sigma "
                "from a paraboloid: the method's reference assumption does not hold; used with its fitted shape"
            ),
        )
    return fit, "power law", ""


def clip_n(n, ln_q, s, sigma_n=0.0):
    """Apply the n < 2 policy to a central (scalar) estimate.

    Returns (n_used, ln_Q_used, flag) with flag in {"ok", "n_clipped_to_2", "n_below_2"}.
    """
    if not np.isfinite(n) or not np.isfinite(ln_q):
        return np.nan, np.nan, "invalid_fit"
    if n > N_MAX:
        return np.nan, np.nan, "n_above_20"
    if n >= N_MIN:
        return float(n), float(ln_q), "ok"
    tol = max(3.0 * float(sigma_n), N_BELOW_2_TOL)
    if n >= N_MIN - tol:
        n_arr, lq_arr = clip_samples(np.array([n]), np.array([ln_q]), s)
        return float(n_arr[0]), float(lq_arr[0]), "n_clipped_to_2"
    return np.nan, np.nan, "n_below_2"


def clip_samples(n, ln_q, s):
    """Clip draws with n < 2 to n = 2 keeping R: ln Q(2) = ln R = (ln Q - (n-2) ln S)/(n-1).
    NaN where n > 20, n <= 1.5, or Q = exp(ln Q) is not a finite positive double."""
    n = np.array(n, dtype=float)
    ln_q = np.array(ln_q, dtype=float)
    low = n < N_MIN
    too_low = ~(n > 1.5)  # far from a paraboloid (or NaN): no meaningful R to keep
    with np.errstate(divide="ignore", invalid="ignore"):
        ln_r = (ln_q[low] - (n[low] - 2.0) * np.log(s)) / (n[low] - 1.0)
    ln_q[low] = ln_r
    n[low] = N_MIN
    bad = ~(n <= N_MAX) | ~(np.abs(ln_q) < LN_Q_MAX) | too_low
    n[bad] = np.nan
    ln_q[bad] = np.nan
    return n, ln_q


@dataclass
class IntervalShape:
    """The shape one interval is inverted with: the fit used (``shape_for_inversion``), the
    central (n, ln Q, Q) after the n policy (NaN: not usable), its flag and the unusable
    stage-2 flags of the fit."""

    fit: dict
    model: str
    note: str
    n: float
    ln_Q: float
    Q: float
    n_flag: str
    bad_fit_flags: list

    @property
    def usable(self) -> bool:
        return self.n_flag in USABLE_N_FLAGS


def interval_shape(fit: dict, reference: bool) -> IntervalShape:
    """The n policy and the stage-2 flags applied to one interval's fit (a fit flagged in stage 2
    is not used, never silently: flag ``fit_flagged``)."""
    used, model, note = shape_for_inversion(fit, reference)
    n_c, lnq_c, n_flag = clip_n(used["n"], used["ln_Q"], used["S"], used["u_n"])
    bad_fit = sorted(set(used["flags"]) & UNUSABLE_FIT_FLAGS)
    if bad_fit and n_flag in USABLE_N_FLAGS:
        n_c, lnq_c, n_flag = np.nan, np.nan, "fit_flagged"
    q_c = float(np.exp(lnq_c)) if np.isfinite(lnq_c) else np.nan
    return IntervalShape(used, model, note, n_c, lnq_c, q_c, n_flag, bad_fit)
