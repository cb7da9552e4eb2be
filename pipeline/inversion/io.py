"""Files of stage 4: the stage-2 fit it reads (:func:`load_fit`, from ``pipeline.fits.io``, where the fit
file's layout is spelled) and the inversion file it writes
(:func:`write_inversion_h5`, :func:`load_inversion`: the only place its layout is spelled).

Inversion file layout (every dataset has ``units``): ``h_grid``, ``h_grid_mc`` (the subset on
which the Monte-Carlo samples are stored) and ``h_grid_mc_index``; ``systematic/`` the shared
draws (cal_factor, k_factor, invols_factor, E_star) and the tip's k, u_k, invols, u_invols;
``intervals/<name>/`` the shape and forces used (n, u_n, ln_Q, Q, R, S, cov_n_lnQ, n_used,
ln_Q_used, F_p_mean, F_p_sem, F_p_std, n_curves, the InvOLS and its contact-slope check,
contact_compliance_factor), ``draws/`` (F_p_mean, cal_factor, n, n_raw, ln_Q, n_clipped) and one
group per law (W_A, W_A_samples on h_grid_mc, W_A_p16/p50/p84, valid_fraction, model_used,
mdn_fraction or elastic_fraction; Dugdale also Lambda, Lambda_boundary, rigid_valid and near
n = 2 maugis_lambda).  Root attributes: tip, solver_mode, laws, mc_samples, mc_h_points, seed,
E_star, u_E_star, exact, interval_order, the sampling rules, n_policy, conventions and
calibration_notes.
"""

from __future__ import annotations

import h5py
import numpy as np

from pipeline.fits.io import load_fit
from pipeline.h5io import (
    atomic_h5,
    create_group,
    read_attr_json,
    read_dataset,
    write_dataset,
)
from pipeline.inversion.hgrid import interp_loglog
from pipeline.inversion.laws import CONVENTIONS, full_model_name
from pipeline.inversion.montecarlo import PERCENTILES
from pipeline.inversion.shape import N_POLICY

FP_SAMPLING = "Student t (dof = n_curves - 1; normal if < 3 curves) around F_p_mean with F_p_sem, truncated > 0"
__all__ = ["load_fit", "write_inversion_h5", "load_inversion"]

SYSTEMATIC = (
    "k and E* drawn once per sample, shared by all intervals; InvOLS per interval (its own draw) "
    "unless stage 3 marks it shared by the tip"
)


# ---------------------------------------------------------------------- the inversion file
def write_inversion_h5(
    out_h5,
    *,
    settings: dict,
    h,
    mc_idx,
    cal: dict,
    cal_notes: list,
    systematic: dict,
    intervals: list,
    fits: dict,
    forces: dict,
    results: dict,
) -> None:
    """Write the inversion file (module doc).  ``settings``: tip, solver_mode, laws, mc_samples,
    seed, E_star, u_E_star, exact; ``results``: per interval (run_inversion) n_used, ln_Q_used,
    n_flag, notes, shape_model, draws and per law the curves of ``solve.law_curves``."""
    hm = h[mc_idx]
    names = [str(iv["name"]) for iv in intervals]
    st = settings
    with atomic_h5(
        out_h5,
        stage="inversion",
        tip=st["tip"],
        solver_mode=st["solver_mode"],
        laws=list(st["laws"]),
        mc_samples=st["mc_samples"],
        mc_h_points=int(hm.size),
        seed=int(st["seed"]),
        E_star=float(st["E_star"]),
        u_E_star=float(st["u_E_star"] or 0.0),
        exact=bool(st["exact"]),
        interval_order=names,
        fp_sampling=FP_SAMPLING,
        systematic=SYSTEMATIC,
        n_policy=N_POLICY,
        conventions=CONVENTIONS,
        calibration_notes=cal_notes,
    ) as f:
        write_dataset(f, "h_grid", h, "m", "adhesion range grid")
        write_dataset(f, "h_grid_mc", hm, "m", "subset of h_grid on which the MC samples are evaluated")
        write_dataset(f, "h_grid_mc_index", mc_idx, "1", "indices of h_grid_mc in h_grid")
        _write_systematic(f, systematic, cal)
        gi = create_group(f, "intervals")
        for iv in intervals:
            nm = str(iv["name"])
            fit, fo, res = fits[nm], forces[nm], results[nm]
            g = create_group(
                gi,
                nm,
                scans=int(iv.get("scans", -1)),
                reference=bool(iv.get("reference", False)),
                n_flag=res["n_flag"],
                fit_flags=fit["flags"],
                notes=res["notes"],
                shape_model=res["shape_model"],
            )
            _write_interval_inputs(g, fit, fo, res)
            _write_draws(create_group(g, "draws"), res["draws"])
            for law, lr in res["laws"].items():
                _write_law(create_group(g, law, convention=CONVENTIONS[law], model=st["solver_mode"]), law, lr, h, hm)


def _write_systematic(f, sysd: dict, cal: dict) -> None:
    g = create_group(f, "systematic")
    source = (
        "u_F_p_calibration_rel of stage 3" if np.isfinite(cal.get("u_cal_rel", np.nan)) else "k and InvOLS independent"
    )
    write_dataset(
        g, "cal_factor", sysd["cal_factor"], "1", "(k InvOLS)/(k0 InvOLS0) per MC sample (shared)", source=source
    )
    write_dataset(g, "k_factor", sysd["k_factor"], "1", "k/k0 per MC sample (shared)")
    write_dataset(g, "invols_factor", sysd["invols_factor"], "1", "InvOLS/InvOLS0 per MC sample (shared)")
    write_dataset(g, "E_star", sysd["E_star"], "Pa", "E* per MC sample (shared)")
    write_dataset(g, "k", cal["k"], "N/m", "spring constant")
    write_dataset(g, "u_k", cal["u_k"], "N/m", "1-sigma uncertainty of k")
    write_dataset(g, "invols", cal["invols"], "m/V", "deflection sensitivity")
    write_dataset(g, "u_invols", cal["u_invols"], "m/V", "1-sigma uncertainty of InvOLS")


def _write_interval_inputs(g, fit: dict, fo: dict, res: dict) -> None:
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
    write_dataset(
        g,
        "contact_compliance_factor",
        fo.get("contact_compliance_factor", 1.0),
        "1",
        "contact-slope InvOLS and F_p divided by this (the tip's finite contact stiffness; 1: not applied)",
    )


def _write_draws(gs, dr: dict) -> None:
    write_dataset(gs, "F_p_mean", dr["F_p_mean"], "N", "sampled mean F_p (before the calibration factor)")
    write_dataset(gs, "cal_factor", dr["cal_factor"], "1", "(k InvOLS)/(k0 InvOLS0) of this interval per sample")
    write_dataset(gs, "n", dr["n"], "1", "sampled n after clipping (NaN: invalid draw)")
    write_dataset(gs, "n_raw", dr["n_raw"], "1", "sampled n before clipping")
    write_dataset(gs, "ln_Q", dr["ln_Q"], "1", "sampled ln Q after clipping")
    write_dataset(gs, "n_clipped", dr["n_clipped"], "1", "draw had n < 2 and was clipped")


def _write_law(gl, law: str, lr: dict, h, hm) -> None:
    write_dataset(gl, "W_A", lr["W_A"], "J/m^2", "W_A(h) from the best estimates")
    write_dataset(
        gl,
        "W_A_samples",
        lr["samples"],
        "J/m^2",
        "Monte-Carlo samples of W_A on h_grid_mc, shape (sample, h_mc); "
        "interpolate linearly in (ln h, ln W_A) for the full grid",
    )
    valid_frac = interp_loglog(hm, lr["finite_fraction"], h, log_y=False)
    for p, row in zip(PERCENTILES, lr["sample_percentiles"]):
        write_dataset(
            gl,
            f"W_A_p{int(p)}",
            interp_loglog(hm, row, h),
            "J/m^2",
            f"{p:g}th percentile of the MC samples (on h_grid)",
        )
    write_dataset(gl, "valid_fraction", valid_frac, "1", "fraction of MC samples with a finite W_A")
    full = full_model_name(law)
    used = np.where(lr["elastic_used"], full, "rigid").astype(object)
    write_dataset(gl, "model_used", used, "1", "model used for the central W_A per h (rigid, mdn or elastic)")
    write_dataset(
        gl,
        f"{full}_fraction",
        lr["elastic_fraction"],
        "1",
        f"fraction of MC samples solved with the full model ({full})",
    )
    if law == "dugdale":
        write_dataset(gl, "Lambda", lr["Lambda"], "1", "transition parameter at the central W_A(h)")
        write_dataset(gl, "Lambda_boundary", lr["Lambda_boundary"], "1", "Eq. 13 boundary at n_used")
        write_dataset(gl, "rigid_valid", lr["rigid_valid"], "1", "Lambda < Lambda_b(n)")
        if "maugis" in lr:
            write_dataset(gl, "maugis_lambda", lr["maugis"], "1", "Maugis parameter (n ~ 2)")


def load_inversion(path, samples_on_grid: bool = True) -> dict:
    """Read a stage-4 file back into plain arrays (used by stage 5, reports, figures); the
    Monte-Carlo samples are interpolated onto the full h grid, or with ``samples_on_grid=False``
    left as stored (float32 on ``h_mc``; :func:`samples_on_h_grid` interpolates one law of one
    interval when it is needed, so that a large Monte Carlo is not held on the full grid for every
    law at once)."""
    out = {"intervals": {}, "samples_on_grid": bool(samples_on_grid)}
    with h5py.File(path, "r") as f:
        out["h"] = f["h_grid"][()]
        out["h_mc"] = f["h_grid_mc"][()] if "h_grid_mc" in f else out["h"]
        for key in ("tip", "solver_mode", "mc_samples", "seed", "E_star", "u_E_star"):
            out[key] = read_attr_json(f, key)
        laws = read_attr_json(f, "laws")
        out["laws"] = [laws] if isinstance(laws, str) else list(laws)
        out["order"] = list(read_attr_json(f, "interval_order"))
        out["systematic"] = {k: f["systematic"][k][()] for k in f["systematic"]}
        for nm in out["order"]:
            out["intervals"][nm] = _read_interval(f["intervals"][nm], out)
    return out


def samples_on_h_grid(inv: dict, samples):
    """Monte-Carlo samples of W_A of one law and interval (``load_inversion``) on the full h grid
    (S, H): as they are where ``load_inversion`` interpolated them, else interpolated now."""
    if inv.get("samples_on_grid", True):
        return samples
    return interp_loglog(inv["h_mc"], np.asarray(samples, dtype=float), inv["h"])


def _read_interval(g, inv: dict) -> dict:
    d = {k: read_dataset(g, k)[0] for k in g if isinstance(g[k], h5py.Dataset)}
    d["scans"] = int(g.attrs["scans"])
    d["reference"] = bool(g.attrs["reference"])
    d["n_flag"] = str(read_attr_json(g, "n_flag"))
    d["draws"] = {k: g["draws"][k][()] for k in g["draws"]}
    d["laws"] = {}
    for law in inv["laws"]:
        gl = g[law]
        d["laws"][law] = {k: read_dataset(gl, k)[0] for k in gl}
        if inv["samples_on_grid"]:
            d["laws"][law]["W_A_samples"] = interp_loglog(
                inv["h_mc"], np.asarray(d["laws"][law]["W_A_samples"], dtype=float), inv["h"]
            )
    return d
