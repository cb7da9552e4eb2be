"""W_A(h) of one interval per traction law, in the solver mode, and the regime it is in.

Solver modes apply to every law: "rigid" (closed forms: Eq. 12 and its Sec. 4.3 analogues),
"mdn" (always the full elastic model: M-D-n, Eqs. 4-11, for Dugdale; the elastic solver of
pipeline.mechanics.elastic_contact for L-J (Eq. 14), Tri1, Tri2) and "auto" (rigid where
Lambda < Lambda_b(n), the 5 % boundary of the law: Eq. 13 for Dugdale,
pipeline.mechanics.rigid_boundary for the others; else the full model).  Every law records
which model made each W_A (``elastic_used``; in the file ``model_used`` and the fraction of
Monte-Carlo samples solved with the full model).
"""

from __future__ import annotations

import numpy as np

import pipeline.mechanics as mech
from pipeline.inversion.montecarlo import PERCENTILES, sample_percentiles
from pipeline.inversion.shape import N_MIN

N_NEAR_2_FOR_MAUGIS = 0.25  # Maugis parameter reported for intervals with n < 2.25


def solve_w(F, n, q, e_star, h, law, mode, exact=False):
    """W_A for broadcastable inputs; NaN where the inputs are out of the model's domain.

    ``mode`` is the solver mode ("mdn" = the law's full elastic model, "rigid", "auto").
    Out-of-domain inputs (the mechanics raises ValueError) are isolated row by row and
    element by element so that a single bad Monte-Carlo draw never stops the run.
    """
    return _solve(F, n, q, e_star, h, law, mode, exact)[0]


def solve_w_and_model(F, n, q, e_star, h, law, mode, exact=False):
    """(W_A, elastic mask): :func:`solve_w` and, from the same solve, where the full elastic model
    made the value (:func:`uses_elastic_model` without solving the rigid inverse a second time)."""
    w, elastic = _solve(F, n, q, e_star, h, law, mode, exact)
    if elastic is None:  # an element out of the model's domain: the masks from the inputs
        return w, uses_elastic_model(F, n, q, e_star, h, mode, law)
    return w, elastic


def _solve(F, n, q, e_star, h, law, mode, exact):
    """(W_A, elastic mask) of :func:`solve_w` (the mask False where an input is invalid); the mask
    is None where the piecewise path was needed."""
    model = "elastic" if (mode == "mdn" and law != "dugdale") else mode
    F, n, q, e_star, h = np.broadcast_arrays(*(np.asarray(x, dtype=float) for x in (F, n, q, e_star, h)))
    out = np.full(F.shape, np.nan)
    elastic = np.zeros(F.shape, bool)
    ok = np.isfinite(F) & np.isfinite(n) & np.isfinite(q) & np.isfinite(e_star) & np.isfinite(h) & (F > 0)
    if not np.any(ok):
        return out, elastic

    def call(sel, with_regime=False):
        w, rig = mech.work_of_adhesion_and_regime(
            F[sel], n[sel], q[sel], e_star[sel], h[sel], potential=law, model=model, exact=exact
        )
        w = np.asarray(w, dtype=float)
        return (w, np.asarray(rig, dtype=bool)) if with_regime else w

    try:
        out[ok], rigid = call(ok, with_regime=True)
        elastic[ok] = ~rigid
        return out, elastic
    except ValueError:
        pass
    return _solve_piecewise(call, ok, out), None


def _solve_piecewise(call, ok, out):
    """The slow path of :func:`solve_w`: chunks of 64, then single elements (NaN where the
    mechanics refuses one)."""
    idx = np.flatnonzero(ok.ravel())
    flat = out.ravel()
    for chunk in np.array_split(idx, max(1, idx.size // 64)):
        sel = np.zeros(ok.size, bool)
        sel[chunk] = True
        try:
            flat[chunk] = call(sel.reshape(ok.shape))
        except ValueError:
            for i in chunk:
                one = np.zeros(ok.size, bool)
                one[i] = True
                try:
                    flat[i] = call(one.reshape(ok.shape))[0]
                except ValueError:
                    flat[i] = np.nan
    return flat.reshape(ok.shape)


def regime(W, n, q, e_star, h):
    """Lambda (Eq. 8 corrected) and the rigid-valid mask Lambda < Lambda_b(n) (Eq. 13)."""
    W, n, q, e_star, h = np.broadcast_arrays(*(np.asarray(x, dtype=float) for x in (W, n, q, e_star, h)))
    lam = np.full(W.shape, np.nan)
    ok = np.isfinite(W) & (W > 0) & np.isfinite(n) & np.isfinite(q)
    if np.any(ok):
        lam[ok] = mech.transition_parameter(n[ok], q[ok], e_star[ok], W[ok], h[ok])
    lam_b = np.full(W.shape, np.nan)
    if np.any(ok):
        lam_b[ok] = mech.lambda_boundary(n[ok])
    valid = np.zeros(W.shape, bool)
    valid[ok] = lam[ok] < lam_b[ok]
    return lam, lam_b, valid


def uses_elastic_model(F, n, q, e_star, h, mode, law="dugdale"):
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
    F, n, q, e_star, h = np.broadcast_arrays(*(np.asarray(x, dtype=float) for x in (F, n, q, e_star, h)))
    ok = np.isfinite(F) & (F > 0) & np.isfinite(n) & np.isfinite(q) & np.isfinite(e_star)
    out = np.zeros(F.shape, bool)
    if np.any(ok):
        out[ok] = ~np.asarray(mech.model_used(n[ok], q[ok], e_star[ok], h[ok], F_p=F[ok], potential=law), dtype=bool)
    return out


SAMPLE_ROWS = 2048  # Monte-Carlo samples solved at a time (their temporaries stay in the CPU's cache)


def _solve_samples(samples, hm, law, mode, exact):
    """(W_A, elastic mask) of the Monte-Carlo samples (columns (S, 1) of ``samples``) on ``hm``,
    ``SAMPLE_ROWS`` samples at a time."""
    S = len(samples["F"])
    w = np.empty((S, hm.size))
    elastic = np.empty((S, hm.size), bool)
    for a in range(0, S, SAMPLE_ROWS):
        rows = {k: v[a : a + SAMPLE_ROWS] for k, v in samples.items()}
        w[a : a + SAMPLE_ROWS], elastic[a : a + SAMPLE_ROWS] = solve_w_and_model(
            rows["F"], rows["n"], rows["Q"], rows["E_star"], hm[None, :], law, mode, exact
        )
    return w, elastic


def law_curves(law, central, samples, h, hm, mode, exact=False) -> dict:
    """One law's W_A(h) for an interval: the central curve on ``h`` and the Monte-Carlo samples on
    ``hm`` (shape (samples, hm)), which model made each (``elastic_used``, and the fraction of
    finite samples solved with it, interpolated onto ``h``), and for Dugdale Lambda(h),
    Lambda_b (Eq. 13), the rigid regime and, near n = 2, the Maugis parameter.

    ``central``: dict F (N), n, Q (m^(n-1)), E_star (Pa), R (m); ``samples``: F, n, Q, E_star
    as columns (samples, 1)."""
    F, n, q, e_star = central["F"], central["n"], central["Q"], central["E_star"]
    w_c = solve_w(F, n, q, e_star, h, law, mode, exact)
    w_s, used_s = _solve_samples(samples, hm, law, mode, exact)
    out = {
        "W_A": w_c,
        # the samples as stored (float32), with what is taken from them at full precision
        "samples": w_s.astype(np.float32),
        "sample_percentiles": sample_percentiles(w_s, PERCENTILES),
        "finite_fraction": np.isfinite(w_s).mean(axis=0),
        "elastic_used": uses_elastic_model(F, n, q, e_star, h, mode, law),
    }
    if mode == "auto":
        fin = np.isfinite(w_s)
        cnt = fin.sum(axis=0)
        frac = (used_s & fin).sum(axis=0) / np.maximum(cnt, 1)
        out["elastic_fraction"] = np.interp(np.log(h), np.log(hm), np.where(cnt > 0, frac, np.nan))
    else:
        out["elastic_fraction"] = np.full(h.shape, 1.0 if mode == "mdn" else 0.0)
    if law == "dugdale":
        lam, lam_b, valid = regime(w_c, n, q, e_star, h)
        out.update(Lambda=lam, Lambda_boundary=lam_b, rigid_valid=valid)
        if np.isfinite(n) and n < N_MIN + N_NEAR_2_FOR_MAUGIS:
            out["maugis"] = np.asarray(mech.maugis_parameter(central["R"], e_star, w_c, h), dtype=float)
    return out
