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
from pipeline.inversion.shape import N_MIN

N_NEAR_2_FOR_MAUGIS = 0.25  # Maugis parameter reported for intervals with n < 2.25


def solve_w(F, n, q, e_star, h, law, mode, exact=False):
    """W_A for broadcastable inputs; NaN where the inputs are out of the model's domain.

    ``mode`` is the solver mode ("mdn" = the law's full elastic model, "rigid", "auto").
    Out-of-domain inputs (the mechanics raises ValueError) are isolated row by row and
    element by element so that a single bad Monte-Carlo draw never stops the run.
    """
    model = "elastic" if (mode == "mdn" and law != "dugdale") else mode
    F, n, q, e_star, h = np.broadcast_arrays(*(np.asarray(x, dtype=float) for x in (F, n, q, e_star, h)))
    out = np.full(F.shape, np.nan)
    ok = np.isfinite(F) & np.isfinite(n) & np.isfinite(q) & np.isfinite(e_star) & np.isfinite(h) & (F > 0)
    if not np.any(ok):
        return out

    def call(sel):
        return np.asarray(
            mech.work_of_adhesion(F[sel], n[sel], q[sel], e_star[sel], h[sel], potential=law, model=model, exact=exact),
            dtype=float,
        )

    try:
        out[ok] = call(ok)
        return out
    except ValueError:
        pass
    return _solve_piecewise(call, ok, out)


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


def law_curves(law, central, samples, h, hm, mode, exact=False) -> dict:
    """One law's W_A(h) for an interval: the central curve on ``h`` and the Monte-Carlo samples on
    ``hm`` (shape (samples, hm)), which model made each (``elastic_used``, and the fraction of
    finite samples solved with it, interpolated onto ``h``), and for Dugdale Lambda(h),
    Lambda_b (Eq. 13), the rigid regime and, near n = 2, the Maugis parameter.

    ``central``: dict F (N), n, Q (m^(n-1)), E_star (Pa), R (m); ``samples``: F, n, Q, E_star
    as columns (samples, 1)."""
    F, n, q, e_star = central["F"], central["n"], central["Q"], central["E_star"]
    w_c = solve_w(F, n, q, e_star, h, law, mode, exact)
    w_s = solve_w(samples["F"], samples["n"], samples["Q"], samples["E_star"], hm[None, :], law, mode, exact)
    out = {"W_A": w_c, "samples": w_s, "elastic_used": uses_elastic_model(F, n, q, e_star, h, mode, law)}
    if mode == "auto":
        used_s = uses_elastic_model(
            samples["F"], samples["n"], samples["Q"], samples["E_star"], hm[None, :], "auto", law
        )
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
