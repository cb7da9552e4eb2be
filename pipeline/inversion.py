"""Stage 4: invert measured pull-off forces into W_A(h) for every wear interval.

For each interval of a tip and each traction law the work of adhesion is computed on
an h grid (paper Sec. 4.1, Fig. 3b/d): W_A(h) = work_of_adhesion(F_p, n, Q, E*, h).
The central curve uses the best estimates; a seeded Monte-Carlo propagates

* the pull-off force of the interval: the mean of the accepted curves is sampled
  from its sampling distribution (Student t with n_curves - 1 degrees of freedom
  around F_p_mean with the standard error of the mean; Gaussian when fewer than 3
  curves), truncated to F_p > 0;
* the calibration (spring constant k and InvOLS): systematic, one draw per sample
  shared by all intervals of the tip (F_p scales as k * InvOLS);
* the power-law fit (n, ln Q): bivariate normal with the fit covariance, per interval;
* E*: systematic, one draw per sample shared by all intervals.

Power index below 2
-------------------
The mechanics is defined for n in [2, 20].  A paraboloidal tip may fit to n slightly
below 2.  Policy (``n_policy`` attribute in the output):

* central n >= 2: used as is;
* 2 - max(3 sigma_n, N_BELOW_2_TOL) <= n < 2: n is clipped to 2 (flag
  ``n_clipped_to_2``); Q is re-expressed keeping the fit's R (Q = R at n = 2, since
  Q = S^(n-2) R^(n-1) with R = (Q S^(2-n))^(1/(n-1)) from the fit);
* n further below 2: the interval is unusable (flag ``n_below_2``), its W_A is NaN
  and stage 5 reports it with an explicit status, no number;
* Monte-Carlo draws with n < 2 are clipped the same way (each draw keeps its own R);
  draws with n > 20 or non-finite inputs give NaN and are counted in
  ``valid_fraction``.

Solver modes apply to every law: "rigid" (closed forms), "mdn" (always the full elastic
model: M-D-n for Dugdale, the elastic solver of pipeline.mechanics.elastic_contact for L-J,
Tri1, Tri2) and "auto" (rigid where Lambda < Lambda_b(n), the 5 % boundary of the law:
Eq. 13 for Dugdale, pipeline.mechanics.rigid_boundary for the others; else the full model).
Every law's group records which model made each W_A (model_used; the internal keys mdn_used /
mdn_fraction mean "full model" for every law).  The L-J law is tied to Dugdale by z0 = h / 0.974
(equal peak stress and W_A): its h column is the Dugdale-equivalent h.  For Tri2, h is
the separation of the peak stress; the full range is 2h.
"""
from __future__ import annotations

import logging
import time
import zlib
from pathlib import Path

import h5py
import numpy as np

from pipeline.h5io import atomic_h5, create_group, read_attr_json, read_dataset, write_dataset

log = logging.getLogger(__name__)

LAWS = ("dugdale", "lj", "tri1", "tri2")
SOLVER_MODES = ("auto", "mdn", "rigid")
N_MIN, N_MAX = 2.0, 20.0
N_BELOW_2_TOL = 0.05          # minimum tolerance for clipping a central n < 2 to 2
N_NEAR_2_FOR_MAUGIS = 0.25    # Maugis parameter reported for intervals with n < 2.25
PERCENTILES = (16.0, 50.0, 84.0)
LJ_Z0_OVER_H = 1.0 / 0.974
CONVENTIONS = {
    "dugdale": "h = range of the constant Dugdale stress sigma_0 = W_A/h",
    "lj": "Dugdale-equivalent h with L-J 3-9 equilibrium gap z0 = h/0.974 (equal peak stress and W_A)",
    "tri1": "h = range (stress zero beyond h), peak 2 sigma_0 at h/2",
    "tri2": "h = separation of the peak stress sigma_0 (Dugdale-equivalent h); full range is 2h",
}
N_POLICY = (
    "central n >= 2 used as is; 2 - max(3 sigma_n, 0.05) <= n < 2 clipped to 2 keeping R "
    "(flag n_clipped_to_2); lower n: interval unusable (flag n_below_2, W_A NaN); MC draws "
    "with n < 2 clipped keeping their R; draws with n > 20 give NaN"
)


# --------------------------------------------------------------------------- inputs
def _group(f, names):
    for name in names:
        if name in f:
            return f[name]
    raise KeyError(f"{f.file.filename}: none of the groups {names} found")


def _get(g, name, default=None, *, required=False):
    if name in g:
        value, _ = read_dataset(g, name)
        return value
    if name in g.attrs:
        return g.attrs[name]
    if required:
        raise KeyError(f"{g.file.filename}:{g.name}: missing {name!r}")
    return default


def load_fit(path) -> dict:
    """Read the stage-2 power-law fit of one interval (SI).

    Returns n, u_n, ln_Q, Q (m^(n-1)), R (m), S, cov_n_lnQ (2x2), rms_residual (m), flags.
    All knowledge of the fit file layout lives here.
    """
    with h5py.File(path, "r") as f:
        para = None
        if "fit_n2" in f and not f["fit_n2"].attrs.get("failed", False):
            gp = f["fit_n2"]
            cp = np.asarray(gp["cov_n_lnQ"][()], float).reshape(2, 2)
            fl = [x.decode() if isinstance(x, bytes) else str(x) for x in np.atleast_1d(gp["flags"][()])]
            para = {"n": 2.0, "u_n": 0.0, "ln_Q": float(gp["ln_Q"][()]), "Q": float(gp["Q"][()]), "R": float(gp["R"][()]),
                    "cov_n_lnQ": cp, "rms_residual": float(gp["rms_residual"][()]), "flags": [x for x in fl if x]}
        g = _group(f, ["fit"])
        n = float(_get(g, "n", required=True))
        ln_q = _get(g, "ln_Q")
        q = _get(g, "Q")
        if ln_q is None:
            if q is None:
                raise KeyError(f"{path}: fit has neither ln_Q nor Q")
            ln_q = np.log(float(q))
        ln_q = float(ln_q)
        q = float(q) if q is not None else float(np.exp(ln_q))
        s = float(_get(g, "S", 1.0))
        r = _get(g, "R")
        r = float(r) if r is not None else float(np.exp((ln_q - (n - 2.0) * np.log(s)) / (n - 1.0)))
        cov = _get(g, "cov_n_lnQ")
        cov = np.zeros((2, 2)) if cov is None else np.asarray(cov, dtype=float).reshape(2, 2)
        flags = _get(g, "flags", [])
        if isinstance(flags, (str, bytes)):
            flags = [flags.decode() if isinstance(flags, bytes) else flags]
        flags = [str(x) for x in np.atleast_1d(flags) if str(x)]
        rms = _get(g, "rms_residual", np.nan)
    return {
        "n": n,
        "u_n": float(np.sqrt(max(cov[0, 0], 0.0))),
        "ln_Q": ln_q,
        "Q": q,
        "R": r,
        "S": s,
        "cov_n_lnQ": cov,
        "rms_residual": float(rms),
        "flags": flags,
        "paraboloid": para,
    }


# A reference whose n is within this many sigma of 2 is used as the paraboloid it is meant to be.
REFERENCE_N_SIGMA = 2.0
# sigma_n above which the image hardly constrains the shape (said in the notes).
SHAPE_POORLY_DEFINED_SIGMA_N = 0.2


def shape_for_inversion(fit: dict, reference: bool):
    """(fit used, shape model, note) for one interval.

    A reference interval is the unworn, paraboloidal tip of the method (the paper's n = 2
    interval).  Where its fitted n is consistent with 2 (within REFERENCE_N_SIGMA sigma_n), it
    is used as a paraboloid with R from the paraboloid fit of the same profile (n held at 2,
    ``fits.run_fit`` group ``fit_n2``), instead of clipping a free-n fit: with n free, R is
    tied to an uncertain n (a fit of n = 1.70 +- 0.45 clipped to 2 kept an R 12 % off).  A worn
    interval whose n is below 2 but within the clipping tolerance is treated the same way.
    A reference that is not consistent with 2 keeps its power-law fit and the note says the
    method's assumption does not hold.  Without a paraboloid fit (older files) nothing changes."""
    n, u = fit["n"], fit["u_n"]
    para = fit.get("paraboloid")
    consistent = np.isfinite(n) and abs(n - 2.0) <= REFERENCE_N_SIGMA * max(u, 0.0)
    below_tol = np.isfinite(n) and N_MIN - max(3.0 * u, N_BELOW_2_TOL) <= n < N_MIN
    usable_para = para is not None and not (set(para["flags"]) & UNUSABLE_FIT_FLAGS)
    vague = f" The image hardly constrains the shape (sigma_n = {u:.2f}): W_A rests on the paraboloid assumption." \
        if u > SHAPE_POORLY_DEFINED_SIGMA_N else ""
    if usable_para and ((reference and consistent) or below_tol):
        u_r = para["R"] * float(np.sqrt(max(para["cov_n_lnQ"][1, 1], 0.0)))
        note = (f"fitted n = {n:.3f} +- {u:.3f} is consistent with a paraboloid: used as one, R = {para['R'] * 1e9:.3g} "
                f"+- {u_r * 1e9:.2g} nm from the n = 2 fit of the same profile.{vague}")
        return {**fit, **para, "S": fit["S"]}, "paraboloid (n = 2 fit)", note
    if reference and np.isfinite(n) and not consistent:
        return fit, "power law", (f"reference interval fitted n = {n:.3f} +- {u:.3f}, {abs(n - 2.0) / max(u, 1e-12):.1f} sigma "
                                  "from a paraboloid: the method's reference assumption does not hold; used with its fitted shape")
    return fit, "power law", ""


def load_forces(path) -> dict:
    """Read the stage-3 pull-off forces of one interval (SI).

    Returns F_p_mean, F_p_std, F_p_sem, n_curves (N), F_p_curves, accepted (per curve, may be
    empty) and the calibration k, u_k (N/m), invols, u_invols (m/V).
    All knowledge of the forces file layout lives here.
    """
    with h5py.File(path, "r") as f:
        g = _group(f, ["interval"])
        fp_mean = float(_get(g, "F_p_mean", required=True))
        n_curves = int(_get(g, "n_curves_used", _get(g, "n_curves", 0)))
        fp_std = _get(g, "F_p_std")
        fp_sem = _get(g, "F_p_sem")
        gc = f["curves"] if "curves" in f else g          # per-curve data (stage 3: group "curves")
        fp_curves = np.atleast_1d(np.asarray(_get(gc, "F_p", np.array([])), dtype=float))
        accepted = _get(gc, "used", _get(gc, "accepted", None))
        if accepted is None:
            outlier = _get(gc, "outlier", None)
            accepted = (~np.asarray(outlier, dtype=bool)) if outlier is not None else np.ones(fp_curves.shape, bool)
        accepted = np.atleast_1d(np.asarray(accepted, dtype=bool))
        u_cal_rel = _get(g, "u_F_p_calibration_rel", None)
        if fp_std is None and fp_curves.size > 1:
            fp_std = float(np.std(fp_curves[accepted], ddof=1))
        fp_std = float(fp_std) if fp_std is not None else np.nan
        if fp_sem is None:
            fp_sem = fp_std / np.sqrt(n_curves) if n_curves > 0 else np.nan
        cal = f["calibration"] if "calibration" in f else {}
        k = float(_get(cal, "k", np.nan)) if cal else np.nan
        u_k = float(_get(cal, "u_k", 0.0)) if cal else 0.0
        invols = float(_get(cal, "invols", np.nan)) if cal else np.nan
        u_invols = float(_get(cal, "u_invols", 0.0)) if cal else 0.0
        if u_cal_rel is None and cal:
            u_cal_rel = _get(cal, "u_factor_rel", None)
        # files written before InvOLS was per interval: one value for the whole tip
        shared = bool(_get(cal, "invols_shared", True)) if cal else True
        inv_method = str(_get(cal, "invols_method", "")) if cal else ""
        contact_range = np.asarray(_get(cal, "contact_fit_deflection", np.full(2, np.nan)), float) if cal else np.full(2, np.nan)
        contact_segment = str(_get(cal, "contact_segment", "approach")) if cal else "approach"
        inv_check = str(_get(cal, "invols_check", "")) if cal else ""
        inv_contact = float(_get(cal, "invols_contact", np.nan)) if cal else np.nan
        u_inv_contact = float(_get(cal, "u_invols_contact", np.nan)) if cal else np.nan
        warnings = list(read_attr_json(f, "warnings")) if "warnings" in f.attrs else []
    return {
        "F_p_mean": fp_mean,
        "F_p_std": fp_std,
        "F_p_sem": float(fp_sem),
        "n_curves": n_curves,
        "F_p_curves": fp_curves,
        "accepted": accepted,
        "k": k,
        "u_k": u_k,
        "invols": invols,
        "u_invols": u_invols,
        # relative 1-sigma of k * InvOLS (correlations included) if stage 3 gives it, else NaN
        "u_cal_rel": float(u_cal_rel) if u_cal_rel is not None else np.nan,
        "invols_shared": shared,
        "invols_method": inv_method,
        "contact_fit_deflection": contact_range,
        "contact_segment": contact_segment,
        "invols_check": inv_check,
        "invols_contact": inv_contact,
        "u_invols_contact": u_inv_contact,
        "warnings": warnings,
    }


# ----------------------------------------------------------------------- mechanics
def _mechanics(mech=None):
    if mech is not None:
        return mech
    import pipeline.mechanics as m  # noqa: PLC0415  (lands in parallel; imported lazily)

    return m


def lambda_boundary(n, mech=None):
    """Eq. 13 (from the mechanics module; closed form used if it is missing)."""
    m = _mechanics(mech)
    if hasattr(m, "lambda_boundary"):
        return m.lambda_boundary(n)
    n = np.asarray(n, dtype=float)
    return -0.002194 * n**2 + 0.067185 * n + 0.022056


# Stage-2 fit flags that make an interval unusable (its fit is not a trustworthy tip shape).
UNUSABLE_FIT_FLAGS = frozenset({"n_below_1.5", "not_converged", "n_at_bound", "residual_above_pixel", "few_points"})


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
        n_arr, lq_arr = _clip_samples(np.array([n]), np.array([ln_q]), s)
        return float(n_arr[0]), float(lq_arr[0]), "n_clipped_to_2"
    return np.nan, np.nan, "n_below_2"


def _clip_samples(n, ln_q, s):
    """Clip draws with n < 2 to n = 2 keeping R: ln Q(2) = ln R = (ln Q - (n-2) ln S)/(n-1)."""
    n = np.array(n, dtype=float)
    ln_q = np.array(ln_q, dtype=float)
    low = n < N_MIN
    too_low = ~(n > 1.5)  # far from a paraboloid (or NaN): no meaningful R to keep
    with np.errstate(divide="ignore", invalid="ignore"):
        ln_r = (ln_q[low] - (n[low] - 2.0) * np.log(s)) / (n[low] - 1.0)
    ln_q[low] = ln_r
    n[low] = N_MIN
    bad = ~(n <= N_MAX) | ~np.isfinite(ln_q) | too_low
    n[bad] = np.nan
    ln_q[bad] = np.nan
    return n, ln_q


def solve_w(F, n, q, e_star, h, law, mode, mech=None, exact=False):
    """W_A for broadcastable inputs; NaN where the inputs are out of the model's domain.

    ``mode`` is the solver mode ("mdn" = the law's full elastic model, "rigid", "auto").
    Out-of-domain inputs (the mechanics raises ValueError) are isolated row by row and
    element by element so that a single bad Monte-Carlo draw never stops the run.
    """
    m = _mechanics(mech)
    model = "elastic" if (mode == "mdn" and law != "dugdale") else mode
    F, n, q, e_star, h = np.broadcast_arrays(*(np.asarray(x, dtype=float) for x in (F, n, q, e_star, h)))
    out = np.full(F.shape, np.nan)
    ok = np.isfinite(F) & np.isfinite(n) & np.isfinite(q) & np.isfinite(e_star) & np.isfinite(h) & (F > 0)
    if not np.any(ok):
        return out

    def call(sel):
        return np.asarray(
            m.work_of_adhesion(F[sel], n[sel], q[sel], e_star[sel], h[sel], potential=law, model=model, exact=exact),
            dtype=float,
        )

    try:
        out[ok] = call(ok)
        return out
    except ValueError:
        pass
    # slow path: split into chunks, then single elements
    idx = np.flatnonzero(ok.ravel())
    flat = out.ravel()
    for chunk in np.array_split(idx, max(1, idx.size // 64)):
        sel = np.zeros(F.size, bool)
        sel[chunk] = True
        sel = sel.reshape(F.shape)
        try:
            flat[chunk] = call(sel)
        except ValueError:
            for i in chunk:
                one = np.zeros(F.size, bool)
                one[i] = True
                try:
                    flat[i] = call(one.reshape(F.shape))[0]
                except ValueError:
                    flat[i] = np.nan
    return flat.reshape(F.shape)


def regime(W, n, q, e_star, h, mech=None):
    """Lambda (Eq. 8 corrected) and the rigid-valid mask Lambda < Lambda_b(n) (Eq. 13)."""
    m = _mechanics(mech)
    W, n, q, e_star, h = np.broadcast_arrays(*(np.asarray(x, dtype=float) for x in (W, n, q, e_star, h)))
    lam = np.full(W.shape, np.nan)
    ok = np.isfinite(W) & (W > 0) & np.isfinite(n) & np.isfinite(q)
    if np.any(ok):
        lam[ok] = m.transition_parameter(n[ok], q[ok], e_star[ok], W[ok], h[ok])
    lam_b = np.full(W.shape, np.nan)
    if np.any(ok):
        lam_b[ok] = lambda_boundary(n[ok], m)
    valid = np.zeros(W.shape, bool)
    valid[ok] = lam[ok] < lam_b[ok]
    return lam, lam_b, valid


def _model_used(F, n, q, e_star, h, mode, mech=None, exact=False, law="dugdale"):
    """Which model a call in ``mode`` uses for ``law``: True where the full elastic model
    (M-D-n for Dugdale, the elastic solver for the other laws).

    In auto mode the mechanics decides with Lambda evaluated at the rigid W_A (the
    M-D-n correction is below 5 % where rigid is valid): reproduced here for the record.
    """
    shape = np.broadcast_shapes(*(np.shape(x) for x in (F, n, q, e_star, h)))
    if mode == "mdn":
        return np.ones(shape, bool)
    if mode == "rigid":
        return np.zeros(shape, bool)
    m = _mechanics(mech)
    F, n, q, e_star, h = np.broadcast_arrays(*(np.asarray(x, dtype=float) for x in (F, n, q, e_star, h)))
    ok = np.isfinite(F) & (F > 0) & np.isfinite(n) & np.isfinite(q) & np.isfinite(e_star)
    out = np.zeros(F.shape, bool)
    if not np.any(ok):
        return out
    if hasattr(m, "model_used"):
        out[ok] = ~np.asarray(m.model_used(n[ok], q[ok], e_star[ok], h[ok], F_p=F[ok], potential=law), dtype=bool)
        return out
    w_r = solve_w(F, n, q, e_star, h, law, "rigid", mech, exact)
    _, _, valid = regime(w_r, n, q, e_star, h, mech)
    return ~valid & np.isfinite(w_r)


# ------------------------------------------------------------------ Monte-Carlo draws
def _truncnormal(rng, mean, sd, size):
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


def _draw_mean(rng, mean, sem, n_curves, size):
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


def _seed_sequence(seed: int, tip: str):
    return np.random.SeedSequence([int(seed), zlib.crc32(tip.encode())])


def draw_systematic(ss, cal, E_star, u_E_star, size):
    """Shared draws: calibration factor (k InvOLS)/(k0 InvOLS0) and E*."""
    rng = np.random.default_rng(ss)
    k, u_k, inv, u_inv = cal["k"], cal["u_k"], cal["invols"], cal["u_invols"]
    u_k, u_inv = np.nan_to_num(u_k), np.nan_to_num(u_inv)
    fk = _truncnormal(rng, 1.0, u_k / k, size) if np.isfinite(k) and k > 0 else np.ones(size)
    fi = _truncnormal(rng, 1.0, u_inv / inv, size) if np.isfinite(inv) and inv > 0 else np.ones(size)
    u_rel = cal.get("u_cal_rel", np.nan)
    if np.isfinite(u_rel):
        # stage 3 gives the relative uncertainty of k * InvOLS with their correlation: use it for
        # the product (the individual factors are kept for the record only)
        cf = _truncnormal(rng, 1.0, float(u_rel), size)
    else:
        cf = fk * fi
    u_e = 0.0 if u_E_star is None or not np.isfinite(u_E_star) else float(u_E_star)
    es = _truncnormal(rng, E_star, u_e, size)
    return {"k_factor": fk, "invols_factor": fi, "cal_factor": cf, "E_star": es}


def interval_calibration_factor(ss, sysd, forces, size):
    """(k InvOLS)/(k0 InvOLS0) of one interval per MC sample: k drawn once per tip (shared), the
    interval's own InvOLS drawn on its own; a tip-level InvOLS shares the tip's draw (with its
    correlation to a reference-lever k)."""
    if forces["invols_shared"]:
        return sysd["cal_factor"]
    inv, u_inv = forces["invols"], np.nan_to_num(forces["u_invols"])
    fi = _truncnormal(np.random.default_rng(ss), 1.0, u_inv / inv, size) if np.isfinite(inv) and inv > 0 else np.ones(size)
    return sysd["k_factor"] * fi


def implausible_forces(F_p: dict, factor: float = 10.0) -> list:
    """Words for intervals whose mean pull-off is more than ``factor`` times above or below the
    median of the tip's other intervals: a wear test changes F_p by a few times at most (a blunter
    tip), so such a step is a unit or calibration mistake (a deflection written in nm read as V)."""
    notes = []
    for nm, F in F_p.items():
        others = [v for k, v in F_p.items() if k != nm and np.isfinite(v) and v > 0]
        if not others or not (np.isfinite(F) and F > 0):
            continue
        ratio = F / float(np.median(others))
        if ratio > factor or ratio < 1.0 / factor:
            notes.append(f"interval {nm}: its mean pull-off {F * 1e9:.4g} nN is {ratio:.3g} x the median of the tip's other "
                         f"intervals ({np.median(others) * 1e9:.4g} nN): check its deflection unit and calibration "
                         "(force_curves.deflection_unit, the InvOLS source)")
    return notes


def correct_contact_compliance(forces: dict, n: float, Q: float, E_star: float):
    """Forces of an interval whose InvOLS came from its own contact slopes, corrected for the
    tip's finite contact stiffness (``pipeline.forces.contact_compliance``): F_p, its SEM and
    InvOLS divided by c, half of c - 1 added (relative) to the InvOLS uncertainty.  Returns
    (forces, c); c = 1 (forces unchanged) for other InvOLS sources or an unknown shape."""
    from pipeline.forces.contact_compliance import contact_compliance_factor

    if forces.get("invols_method") != "contact" or forces.get("invols_shared", True):
        return forces, 1.0
    F_adh = forces["F_p_mean"]  # DMT: the adhesion outside the contact adds to the load on either segment
    c = contact_compliance_factor(forces["k"], forces.get("contact_fit_deflection", (np.nan, np.nan)), F_adh, n, Q, E_star)
    if c == 1.0:
        return forces, 1.0
    inv = forces["invols"] / c
    u_inv = float(np.hypot(np.nan_to_num(forces["u_invols"]) / c, 0.5 * (c - 1.0) * inv))
    out = {**forces, "F_p_mean": forces["F_p_mean"] / c, "F_p_sem": forces["F_p_sem"] / c, "F_p_std": forces["F_p_std"] / c,
           "F_p_curves": np.asarray(forces["F_p_curves"]) / c, "invols": inv, "u_invols": u_inv,
           "contact_compliance_factor": c}
    return out, c


def draw_interval(ss, fit, forces, size):
    rng = np.random.default_rng(ss)
    fp = _draw_mean(rng, forces["F_p_mean"], forces["F_p_sem"], forces["n_curves"], size)
    cov = np.asarray(fit["cov_n_lnQ"], float)
    mean = np.array([fit["n"], fit["ln_Q"]])
    if np.all(cov == 0) or not np.all(np.isfinite(cov)):
        nl = np.tile(mean, (size, 1))
    else:
        nl = rng.multivariate_normal(mean, cov, size, method="eigh")
    n_raw = nl[:, 0]
    n, ln_q = _clip_samples(n_raw, nl[:, 1], fit["S"])
    return {"F_p_mean": fp, "n_raw": n_raw, "n": n, "ln_Q": ln_q, "n_clipped": n_raw < N_MIN}


# ------------------------------------------------------------------------ the stage
def run_inversion(
    fit_h5s: dict,
    forces_h5s: dict,
    out_h5,
    *,
    intervals: list,
    E_star: float,
    u_E_star: float,
    h_grid,
    laws=LAWS,
    solver_mode: str = "auto",
    mc_samples: int = 1000,
    seed: int = 0,
    tip: str = "",
    exact: bool = False,
    mc_h_points: int = 64,
    mechanics=None,
):
    """Stage 4: W_A(h) per interval and traction law, with Monte-Carlo samples.

    ``fit_h5s``/``forces_h5s`` map interval name -> stage-2/stage-3 HDF5 file;
    ``intervals`` is the config list of dicts (name, scans, reference); ``E_star``,
    ``u_E_star`` in Pa; ``h_grid`` in m. Writes ``out_h5`` (layout: see module README in
    the report) and returns a small summary dict.
    """
    t0 = time.perf_counter()
    mech = _mechanics(mechanics)
    laws = [str(x).lower() for x in laws]
    for law in laws:
        if law not in LAWS:
            raise ValueError(f"unknown traction law {law!r}; expected one of {LAWS}")
    if solver_mode not in SOLVER_MODES:
        raise ValueError(f"solver_mode {solver_mode!r} not in {SOLVER_MODES}")
    h = np.sort(np.asarray(h_grid, dtype=float).ravel())
    if h.size < 3 or np.any(h <= 0):
        raise ValueError("h_grid needs at least 3 positive values (m)")
    S = int(mc_samples)
    if S < 10:
        raise ValueError("mc_samples must be >= 10")
    mc_idx = mc_grid_index(h.size, mc_h_points)
    hm = h[mc_idx]
    names = [str(iv["name"]) for iv in intervals]
    for nm in names:
        if nm not in fit_h5s or nm not in forces_h5s:
            raise KeyError(f"interval {nm!r} has no fit or forces file")

    fits = {nm: load_fit(fit_h5s[nm]) for nm in names}
    forces = {nm: load_forces(forces_h5s[nm]) for nm in names}

    # k is one per tip: take the first interval's, check the others agree; InvOLS is each
    # interval's own (the chip is remounted) unless stage 3 says it is shared by the tip
    cal = forces[names[0]]
    cal_notes = []
    keys = ("k",) if not all(forces[nm]["invols_shared"] for nm in names) else ("k", "invols")
    for nm in names[1:]:
        for key in keys:
            a, b = cal[key], forces[nm][key]
            if np.isfinite(a) and np.isfinite(b) and not np.isclose(a, b, rtol=1e-9):
                cal_notes.append(f"{key} of {nm} ({b:g}) differs from {names[0]} ({a:g}); using {names[0]}'s")
    for note in cal_notes:
        log.warning(note)

    fp_notes = implausible_forces({nm: forces[nm]["F_p_mean"] for nm in names})
    for note in fp_notes:
        log.warning(note)
    ss = _seed_sequence(seed, tip)
    children = ss.spawn(1 + 2 * len(names))  # systematic, per-interval draws, per-interval InvOLS
    sysd = draw_systematic(children[0], cal, float(E_star), float(u_E_star), S)

    results = {}
    refs = {str(iv["name"]): bool(iv.get("reference", False)) for iv in intervals}
    for i, nm in enumerate(names):
        fo = forces[nm]
        fit, shape_model, shape_note = shape_for_inversion(fits[nm], refs[nm])
        n_c, lnq_c, n_flag = clip_n(fit["n"], fit["ln_Q"], fit["S"], fit["u_n"])
        bad_fit = sorted(set(fit["flags"]) & UNUSABLE_FIT_FLAGS)
        if bad_fit and n_flag in ("ok", "n_clipped_to_2"):
            n_c, lnq_c, n_flag = np.nan, np.nan, "fit_flagged"  # flagged in stage 2: not silently used
        q_c = float(np.exp(lnq_c)) if np.isfinite(lnq_c) else np.nan
        fo, compliance = correct_contact_compliance(fo, n_c, q_c, float(E_star))
        forces[nm] = fo
        dr = draw_interval(children[1 + i], fit, fo, S)
        dr["cal_factor"] = interval_calibration_factor(children[1 + len(names) + i], sysd, fo, S)
        if n_flag not in ("ok", "n_clipped_to_2"):
            dr["n"][:] = np.nan
        F_s = (dr["F_p_mean"] * dr["cal_factor"])[:, None]
        n_s = dr["n"][:, None]
        q_s = np.exp(dr["ln_Q"])[:, None]
        e_s = sysd["E_star"][:, None]
        notes = list(fo["warnings"]) + ([shape_note] if shape_note else []) + [x for x in fp_notes if x.startswith(f"interval {nm}:")]
        if compliance > 1.001:
            notes.append(f"InvOLS from the contact slopes corrected for the tip's contact stiffness (Sneddon, DMT load): "
                         f"F_p divided by {compliance:.4f}, half the correction added to its uncertainty")
        if not (np.isfinite(fo["F_p_sem"]) and fo["F_p_sem"] > 0):
            notes.append("no statistical uncertainty of F_p (fewer than 2 curves): only calibration/fit/E* propagated")
        if n_flag == "n_clipped_to_2":
            notes.append(f"fitted n = {fit['n']:.4f} < 2 clipped to 2 keeping R")
        if n_flag == "fit_flagged":
            notes.append(f"power-law fit flagged {', '.join(bad_fit)}: interval not used (check its profile figure)")
        if np.any(dr["n_clipped"]):
            notes.append(f"{np.mean(dr['n_clipped']):.0%} of MC draws had n < 2 and were clipped to 2 keeping R")
        log.info("%s %s: n = %.3f +- %.3f (%s), F_p = %.4g nN%s; %s", tip, nm, fit["n"], fit["u_n"], n_flag, fo["F_p_mean"] * 1e9,
                 f" (contact compliance {compliance:.4f} applied)" if compliance > 1 else "", "; ".join(notes) or "no notes")
        res = {"n_used": n_c, "ln_Q_used": lnq_c, "n_flag": n_flag, "draws": dr, "laws": {}, "notes": notes,
               "shape_model": shape_model}
        for law in laws:
            w_c = solve_w(fo["F_p_mean"], n_c, q_c, E_star, h, law, solver_mode, mech, exact)
            w_s = solve_w(F_s, n_s, q_s, e_s, hm[None, :], law, solver_mode, mech, exact)
            lr = {"W_A": w_c, "samples": w_s}
            lr["mdn_used"] = _model_used(fo["F_p_mean"], n_c, q_c, E_star, h, solver_mode, mech, exact, law)
            if solver_mode == "auto":
                used_s = _model_used(F_s, n_s, q_s, e_s, hm[None, :], "auto", mech, exact, law)
                fin = np.isfinite(w_s)
                cnt = fin.sum(axis=0)
                frac = (used_s & fin).sum(axis=0) / np.maximum(cnt, 1)
                lr["mdn_fraction"] = np.interp(np.log(h), np.log(hm), np.where(cnt > 0, frac, np.nan))
            else:
                lr["mdn_fraction"] = np.full(h.shape, 1.0 if solver_mode == "mdn" else 0.0)
            if law == "dugdale":
                lam, lam_b, valid = regime(w_c, n_c, q_c, E_star, h, mech)
                lr.update(Lambda=lam, Lambda_boundary=lam_b, rigid_valid=valid)
                if np.isfinite(n_c) and n_c < N_MIN + N_NEAR_2_FOR_MAUGIS and hasattr(mech, "maugis_parameter"):
                    lr["maugis"] = np.asarray(mech.maugis_parameter(fit["R"], E_star, w_c, h), dtype=float)
            res["laws"][law] = lr
        results[nm] = res

    with atomic_h5(
        out_h5,
        stage="inversion",
        tip=tip,
        solver_mode=solver_mode,
        laws=list(laws),
        mc_samples=S,
        mc_h_points=int(hm.size),
        seed=int(seed),
        E_star=float(E_star),
        u_E_star=float(u_E_star or 0.0),
        exact=bool(exact),
        interval_order=names,
        fp_sampling="Student t (dof = n_curves - 1; normal if < 3 curves) around F_p_mean with F_p_sem, truncated > 0",
        systematic="k and E* drawn once per sample, shared by all intervals; InvOLS per interval (its own draw) "
                   "unless stage 3 marks it shared by the tip",
        n_policy=N_POLICY,
        conventions=CONVENTIONS,
        calibration_notes=cal_notes,
    ) as f:
        write_dataset(f, "h_grid", h, "m", "adhesion range grid")
        write_dataset(f, "h_grid_mc", hm, "m", "subset of h_grid on which the MC samples are evaluated")
        write_dataset(f, "h_grid_mc_index", mc_idx, "1", "indices of h_grid_mc in h_grid")
        g = create_group(f, "systematic")
        write_dataset(g, "cal_factor", sysd["cal_factor"], "1", "(k InvOLS)/(k0 InvOLS0) per MC sample (shared)",
                      source="u_F_p_calibration_rel of stage 3" if np.isfinite(cal.get("u_cal_rel", np.nan)) else "k and InvOLS independent")
        write_dataset(g, "k_factor", sysd["k_factor"], "1", "k/k0 per MC sample (shared)")
        write_dataset(g, "invols_factor", sysd["invols_factor"], "1", "InvOLS/InvOLS0 per MC sample (shared)")
        write_dataset(g, "E_star", sysd["E_star"], "Pa", "E* per MC sample (shared)")
        write_dataset(g, "k", cal["k"], "N/m", "spring constant")
        write_dataset(g, "u_k", cal["u_k"], "N/m", "1-sigma uncertainty of k")
        write_dataset(g, "invols", cal["invols"], "m/V", "deflection sensitivity")
        write_dataset(g, "u_invols", cal["u_invols"], "m/V", "1-sigma uncertainty of InvOLS")
        gi = create_group(f, "intervals")
        for iv in intervals:
            nm = str(iv["name"])
            fit, fo, res = fits[nm], forces[nm], results[nm]
            g = create_group(
                gi, nm, scans=int(iv.get("scans", -1)), reference=bool(iv.get("reference", False)),
                n_flag=res["n_flag"], fit_flags=fit["flags"], notes=res["notes"], shape_model=res["shape_model"],
            )
            write_dataset(g, "n", fit["n"], "1", "fitted power index")
            write_dataset(g, "u_n", fit["u_n"], "1", "1-sigma of n")
            write_dataset(g, "ln_Q", fit["ln_Q"], "1", "ln of Q in SI (Q in m^(n-1))")
            write_dataset(g, "Q", fit["Q"], "m^(n-1)", "Q = S^(n-2) R^(n-1)")
            write_dataset(g, "R", fit["R"], "m", "R of Eq. 2")
            write_dataset(g, "S", fit["S"], "1", "S of Eq. 2")
            write_dataset(g, "cov_n_lnQ", fit["cov_n_lnQ"], "1", "covariance of (n, ln Q)")
            write_dataset(g, "n_used", res["n_used"], "1", "n used after the n<2 policy")
            write_dataset(g, "ln_Q_used", res["ln_Q_used"], "1", "ln Q used after the n<2 policy")
            write_dataset(g, "F_p_mean", fo["F_p_mean"], "N", "mean pull-off force")
            write_dataset(g, "F_p_sem", fo["F_p_sem"], "N", "standard error of the mean")
            write_dataset(g, "F_p_std", fo["F_p_std"], "N", "standard deviation of the curves")
            write_dataset(g, "n_curves", fo["n_curves"], "1", "curves used")
            write_dataset(g, "invols", fo["invols"], "m/V", "InvOLS used for this interval")
            write_dataset(g, "u_invols", fo["u_invols"], "m/V", "its 1-sigma uncertainty")
            write_dataset(g, "invols_method", fo["invols_method"], "1", "where it came from (stage 3)")
            write_dataset(g, "invols_shared", fo["invols_shared"], "1", "one InvOLS for the whole tip")
            write_dataset(g, "invols_contact", fo["invols_contact"], "m/V", "InvOLS from the interval's own contact slopes")
            write_dataset(g, "u_invols_contact", fo["u_invols_contact"], "m/V", "its uncertainty")
            write_dataset(g, "invols_check", fo["invols_check"], "1", "'' or what disagrees with the contact slope")
            write_dataset(g, "contact_compliance_factor", fo.get("contact_compliance_factor", 1.0), "1",
                          "contact-slope InvOLS and F_p divided by this (the tip's finite contact stiffness; 1: not applied)")
            gs = create_group(g, "draws")
            dr = res["draws"]
            write_dataset(gs, "F_p_mean", dr["F_p_mean"], "N", "sampled mean F_p (before the calibration factor)")
            write_dataset(gs, "cal_factor", dr["cal_factor"], "1", "(k InvOLS)/(k0 InvOLS0) of this interval per sample")
            write_dataset(gs, "n", dr["n"], "1", "sampled n after clipping (NaN: invalid draw)")
            write_dataset(gs, "n_raw", dr["n_raw"], "1", "sampled n before clipping")
            write_dataset(gs, "ln_Q", dr["ln_Q"], "1", "sampled ln Q after clipping")
            write_dataset(gs, "n_clipped", dr["n_clipped"], "1", "draw had n < 2 and was clipped")
            for law, lr in res["laws"].items():
                gl = create_group(g, law, convention=CONVENTIONS[law], model=solver_mode)
                w_s = lr["samples"]
                write_dataset(gl, "W_A", lr["W_A"], "J/m^2", "W_A(h) from the best estimates")
                write_dataset(gl, "W_A_samples", w_s.astype(np.float32), "J/m^2",
                              "Monte-Carlo samples of W_A on h_grid_mc, shape (sample, h_mc); "
                              "interpolate linearly in (ln h, ln W_A) for the full grid")
                valid_frac = interp_loglog(hm, np.isfinite(w_s).mean(axis=0), h, log_y=False)
                pct = _nanpercentile_cols(w_s, PERCENTILES)
                for p, row in zip(PERCENTILES, pct):
                    write_dataset(gl, f"W_A_p{int(p)}", interp_loglog(hm, row, h), "J/m^2",
                                  f"{p:g}th percentile of the MC samples (on h_grid)")
                write_dataset(gl, "valid_fraction", valid_frac, "1", "fraction of MC samples with a finite W_A")
                full = "mdn" if law == "dugdale" else "elastic"
                used = np.where(lr["mdn_used"], full, "rigid").astype(object)
                write_dataset(gl, "model_used", used, "1", "model used for the central W_A per h (rigid, mdn or elastic)")
                write_dataset(gl, f"{full}_fraction", lr["mdn_fraction"], "1",
                              f"fraction of MC samples solved with the full model ({full})")
                if law == "dugdale":
                    write_dataset(gl, "Lambda", lr["Lambda"], "1", "transition parameter at the central W_A(h)")
                    write_dataset(gl, "Lambda_boundary", lr["Lambda_boundary"], "1", "Eq. 13 boundary at n_used")
                    write_dataset(gl, "rigid_valid", lr["rigid_valid"], "1", "Lambda < Lambda_b(n)")
                    if "maugis" in lr:
                        write_dataset(gl, "maugis_lambda", lr["maugis"], "1", "Maugis parameter (n ~ 2)")
    dt = time.perf_counter() - t0
    return {"seconds": dt, "intervals": names, "laws": laws}


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


def _nanpercentile_cols(x, pcts):
    """Percentiles over axis 0 ignoring NaN, without warnings for all-NaN columns."""
    out = np.full((len(pcts), x.shape[1]), np.nan)
    fin = np.isfinite(x)
    good = fin.any(axis=0)
    if np.all(fin):
        return np.percentile(x, pcts, axis=0)
    for j in np.flatnonzero(good):
        out[:, j] = np.percentile(x[fin[:, j], j], pcts)
    return out


# ------------------------------------------------------------------------ reading
def load_inversion(path) -> dict:
    """Read a stage-4 file back into plain arrays (used by stage 5, reports, figures)."""
    from pipeline.h5io import read_attr_json

    out = {"intervals": {}}
    with h5py.File(path, "r") as f:
        out["h"] = f["h_grid"][()]
        out["h_mc"] = f["h_grid_mc"][()] if "h_grid_mc" in f else out["h"]
        for key in ("tip", "solver_mode", "mc_samples", "seed", "E_star", "u_E_star"):
            out[key] = read_attr_json(f, key)
        out["laws"] = list(read_attr_json(f, "laws"))
        if isinstance(out["laws"], str):
            out["laws"] = [out["laws"]]
        out["order"] = list(read_attr_json(f, "interval_order"))
        out["systematic"] = {k: f["systematic"][k][()] for k in f["systematic"]}
        for nm in out["order"]:
            g = f["intervals"][nm]
            d = {k: read_dataset(g, k)[0] for k in g if isinstance(g[k], h5py.Dataset)}
            d["scans"] = int(g.attrs["scans"])
            d["reference"] = bool(g.attrs["reference"])
            d["n_flag"] = str(read_attr_json(g, "n_flag"))
            d["draws"] = {k: g["draws"][k][()] for k in g["draws"]}
            d["laws"] = {}
            for law in out["laws"]:
                gl = g[law]
                d["laws"][law] = {k: read_dataset(gl, k)[0] for k in gl}
                d["laws"][law]["W_A_samples"] = interp_loglog(
                    out["h_mc"], np.asarray(d["laws"][law]["W_A_samples"], dtype=float), out["h"])
            out["intervals"][nm] = d
    return out


__all__ = [
    "LAWS",
    "CONVENTIONS",
    "load_fit",
    "load_forces",
    "load_inversion",
    "run_inversion",
    "solve_w",
    "clip_n",
    "regime",
    "lambda_boundary",
    "write_synthetic_inputs",
]


# ------------------------------------------------------------- synthetic wear tests
def write_synthetic_fit(path, n_obs, lnr_obs, S, cov, flags=("synthetic",), rms_residual=0.1e-9, paraboloid=None):
    """A stage-2 style fit file with the fitted (n, ln R) and the covariance of (n, ln Q);
    ``paraboloid``: (ln R, var ln R) of the n = 2 fit (group fit_n2), or None."""
    lnq_obs = (n_obs - 2.0) * np.log(S) + (n_obs - 1.0) * lnr_obs
    with atomic_h5(path, stage="fit", synthetic=True) as f:
        if paraboloid is not None:
            gp = create_group(f, "fit_n2")
            for name, val in (("n", 2.0), ("ln_Q", paraboloid[0]), ("Q", np.exp(paraboloid[0])), ("R", np.exp(paraboloid[0])),
                              ("S", S), ("rms_residual", rms_residual)):
                write_dataset(gp, name, val, "1")
            write_dataset(gp, "cov_n_lnQ", np.diag([0.0, paraboloid[1]]), "1")
            write_dataset(gp, "flags", np.array([], dtype=object), "1")
        g = create_group(f, "fit")
        write_dataset(g, "n", n_obs, "1")
        write_dataset(g, "ln_Q", lnq_obs, "1")
        write_dataset(g, "Q", np.exp(lnq_obs), "m^(n-1)")
        write_dataset(g, "R", np.exp(lnr_obs), "m")
        write_dataset(g, "S", S, "1")
        write_dataset(g, "cov_n_lnQ", cov, "1")
        write_dataset(g, "rms_residual", rms_residual, "m")
        write_dataset(g, "flags", np.array(list(flags), dtype=object), "1")


def write_synthetic_inputs(outdir, *, W_A, h, E_star, intervals, u_E_star=0.0, n_curves=40, rel_sd_curve=0.08,
                           sigma_n=0.02, sigma_lnR=0.02, k=0.2, u_k=0.0, invols=50e-9, u_invols=0.0,
                           seed=1, perturb=True, potential="dugdale", model="mdn", exact=True, mechanics=None):
    """Generate stage-2/3 style fit and forces HDF5 files for a wear test with known truth.

    ``intervals``: list of dicts (name, n, R [m], S (default 1), scans, reference); an optional
    ``F_p`` entry overrides the computed true force.  True F_p from
    ``pulloff_force(n, Q, E*, W_A, h, potential, model, exact)``; the per-curve forces are
    Gaussian (relative sd ``rel_sd_curve``); with ``perturb`` the fitted (n, ln R) are drawn
    around the truth with sd (sigma_n, sigma_lnR), and the stored covariance of (n, ln Q) is
    the one propagated from those.  Returns (fit_h5s, forces_h5s, config_intervals).
    """
    mech = _mechanics(mechanics)
    outdir = Path(outdir)
    rng = np.random.default_rng(seed)
    fits, forces, cfg = {}, {}, []
    for iv in intervals:
        nm = str(iv["name"])
        n, R, S = float(iv["n"]), float(iv["R"]), float(iv.get("S", 1.0))
        q = S ** (n - 2.0) * R ** (n - 1.0)
        F_true = float(iv["F_p"]) if "F_p" in iv else float(
            mech.pulloff_force(n, q, E_star, W_A, h, potential=potential, model=model, exact=exact))
        curves = F_true * (1.0 + rel_sd_curve * rng.standard_normal(n_curves))
        if not perturb:
            curves = curves - curves.mean() + F_true
        n_obs = n + (sigma_n * rng.standard_normal() if perturb else 0.0)
        lnr_obs = np.log(R) + (sigma_lnR * rng.standard_normal() if perturb else 0.0)
        J = np.array([[1.0, 0.0], [np.log(S) + lnr_obs, n_obs - 1.0]])
        cov = J @ np.diag([sigma_n**2, sigma_lnR**2]) @ J.T
        fpath = outdir / "fits" / f"{nm}.h5"
        write_synthetic_fit(fpath, n_obs, lnr_obs, S, cov)
        ppath = outdir / "forces" / f"{nm}.h5"
        with atomic_h5(ppath, stage="forces", synthetic=True, F_p_true=F_true) as f:
            g = create_group(f, "interval")
            u_rel = float(np.hypot(u_k / k, u_invols / invols))
            write_dataset(g, "F_p_mean", curves.mean(), "N")
            write_dataset(g, "F_p_std", curves.std(ddof=1), "N")
            write_dataset(g, "F_p_sem", curves.std(ddof=1) / np.sqrt(n_curves), "N")
            write_dataset(g, "n_curves_used", n_curves, "1")
            write_dataset(g, "u_F_p_calibration_rel", u_rel, "1")
            gc = create_group(f, "curves")
            write_dataset(gc, "F_p", curves, "N")
            write_dataset(gc, "accepted", np.ones(n_curves, bool), "1")
            write_dataset(gc, "outlier", np.zeros(n_curves, bool), "1")
            write_dataset(gc, "used", np.ones(n_curves, bool), "1")
            c = create_group(f, "calibration")
            write_dataset(c, "u_factor_rel", u_rel, "1")
            write_dataset(c, "k", k, "N/m")
            write_dataset(c, "u_k", u_k, "N/m")
            write_dataset(c, "invols", invols, "m/V")
            write_dataset(c, "u_invols", u_invols, "m/V")
        fits[nm], forces[nm] = str(fpath), str(ppath)
        cfg.append({"name": nm, "scans": int(iv.get("scans", len(cfg) * 20)), "reference": bool(iv.get("reference", False))})
    return fits, forces, cfg
