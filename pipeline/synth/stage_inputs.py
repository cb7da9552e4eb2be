"""Stage-2 and stage-3 files of a generated wear test with known truth, to run stages 4-5 on
(tests, benchmarks, ``calibration_study``) without images or force curves.

They are written with the files' own writers' layout (groups ``fit``/``fit_n2`` of stage 2;
``interval``/``curves``/``calibration`` of stage 3), read back by ``pipeline.inversion.io.load_fit``
and ``pipeline.forces.io.load_forces``; the root attribute ``synthetic`` marks them.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from pipeline import mechanics
from pipeline.h5io import atomic_h5, create_group, write_dataset


def write_synthetic_fit(path, n_obs, lnr_obs, S, cov, flags=("synthetic",), rms_residual=0.1e-9, paraboloid=None):
    """A stage-2 style fit file with the fitted (n, ln R) and the covariance of (n, ln Q);
    ``paraboloid``: (ln R, var ln R) of the n = 2 fit (group fit_n2), or None."""
    lnq_obs = (n_obs - 2.0) * np.log(S) + (n_obs - 1.0) * lnr_obs
    with atomic_h5(path, stage="fit", synthetic=True) as f:
        if paraboloid is not None:
            gp = create_group(f, "fit_n2")
            for name, val in (
                ("n", 2.0),
                ("ln_Q", paraboloid[0]),
                ("Q", np.exp(paraboloid[0])),
                ("R", np.exp(paraboloid[0])),
                ("S", S),
                ("rms_residual", rms_residual),
            ):
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


def write_synthetic_forces(path, curves, F_true, *, k, u_k, invols, u_invols):
    """A stage-3 style forces file: the per-curve pull-offs ``curves`` (N, all used), their mean,
    SD and SEM, and a calibration (k, InvOLS with uncertainties, independent)."""
    n_curves = len(curves)
    with atomic_h5(path, stage="forces", synthetic=True, F_p_true=F_true) as f:
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


def write_synthetic_inputs(
    outdir,
    *,
    W_A,
    h,
    E_star,
    intervals,
    n_curves=40,
    rel_sd_curve=0.08,
    sigma_n=0.02,
    sigma_lnR=0.02,
    k=0.2,
    u_k=0.0,
    invols=50e-9,
    u_invols=0.0,
    seed=1,
    perturb=True,
    potential="dugdale",
    model="mdn",
    exact=True,
):
    """Generate stage-2/3 style fit and forces HDF5 files for a wear test with known truth.

    ``intervals``: list of dicts (name, n, R [m], S (default 1), scans, reference); an optional
    ``F_p`` entry overrides the computed true force.  True F_p from
    ``pulloff_force(n, Q, E*, W_A, h, potential, model, exact)``; the per-curve forces are
    Gaussian (relative sd ``rel_sd_curve``); with ``perturb`` the fitted (n, ln R) are drawn
    around the truth with sd (sigma_n, sigma_lnR), and the stored covariance of (n, ln Q) is
    the one propagated from those.  Returns (fit_h5s, forces_h5s, config_intervals).
    """
    outdir = Path(outdir)
    rng = np.random.default_rng(seed)
    fits, forces, cfg = {}, {}, []
    for iv in intervals:
        nm = str(iv["name"])
        n, R, S = float(iv["n"]), float(iv["R"]), float(iv.get("S", 1.0))
        q = S ** (n - 2.0) * R ** (n - 1.0)
        F_true = (
            float(iv["F_p"])
            if "F_p" in iv
            else float(mechanics.pulloff_force(n, q, E_star, W_A, h, potential=potential, model=model, exact=exact))
        )
        curves = F_true * (1.0 + rel_sd_curve * rng.standard_normal(n_curves))
        if not perturb:
            curves = curves - curves.mean() + F_true
        n_obs = n + (sigma_n * rng.standard_normal() if perturb else 0.0)
        lnr_obs = np.log(R) + (sigma_lnR * rng.standard_normal() if perturb else 0.0)
        J = np.array([[1.0, 0.0], [np.log(S) + lnr_obs, n_obs - 1.0]])
        cov = J @ np.diag([sigma_n**2, sigma_lnR**2]) @ J.T
        fits[nm], forces[nm] = str(outdir / "fits" / f"{nm}.h5"), str(outdir / "forces" / f"{nm}.h5")
        write_synthetic_fit(fits[nm], n_obs, lnr_obs, S, cov)
        write_synthetic_forces(forces[nm], curves, F_true, k=k, u_k=u_k, invols=invols, u_invols=u_invols)
        cfg.append(
            {"name": nm, "scans": int(iv.get("scans", len(cfg) * 20)), "reference": bool(iv.get("reference", False))}
        )
    return fits, forces, cfg
