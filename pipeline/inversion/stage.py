"""Stage 4 entry point: the fits and forces of a tip's intervals -> W_A(h) per interval and
traction law with Monte-Carlo samples (``inversion.h5``, layout in ``pipeline.inversion.io``)."""

from __future__ import annotations

import logging
import time

import numpy as np

from pipeline.forces.io import load_forces
from pipeline.inversion.calibration import correct_contact_compliance, implausible_forces, tip_calibration
from pipeline.inversion.hgrid import mc_grid_index
from pipeline.inversion.io import load_fit, write_inversion_h5
from pipeline.inversion.laws import LAWS, SOLVER_MODES
from pipeline.inversion.montecarlo import draw_interval, draw_systematic, interval_calibration_factor, seed_streams
from pipeline.inversion.shape import IntervalShape, interval_shape
from pipeline.inversion.solve import law_curves

log = logging.getLogger(__name__)


def _interval_result(shape, dr, notes, solved_laws) -> dict:
    """One interval's result as ``write_inversion_h5`` takes it."""
    return {
        "n_used": shape.n,
        "ln_Q_used": shape.ln_Q,
        "n_flag": shape.n_flag,
        "draws": dr,
        "notes": notes,
        "shape_model": shape.model,
        "laws": solved_laws,
    }


def _settings(tip, solver_mode, laws, n_samples, seed, E_star, u_E_star, exact) -> dict:
    """The run's settings as ``write_inversion_h5`` stores them."""
    return {
        "tip": tip,
        "solver_mode": solver_mode,
        "laws": laws,
        "mc_samples": n_samples,
        "seed": seed,
        "E_star": E_star,
        "u_E_star": u_E_star,
        "exact": exact,
    }


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
):
    """Stage 4: W_A(h) per interval and traction law, with Monte-Carlo samples.

    ``fit_h5s``/``forces_h5s`` map interval name -> stage-2/stage-3 HDF5 file;
    ``intervals`` is the config list of dicts (name, scans, reference); ``E_star``,
    ``u_E_star`` in Pa; ``h_grid`` in m; ``mc_samples`` the Monte-Carlo size, its samples stored
    on ``mc_h_points`` points of the grid.  Writes ``out_h5`` (``pipeline.inversion.io``) and
    returns a small summary dict.
    """
    t0 = time.perf_counter()
    laws, h, n_samples = _checked_arguments(laws, solver_mode, h_grid, mc_samples)
    mc_idx = mc_grid_index(h.size, mc_h_points)
    names, fits, forces = _load_inputs(fit_h5s, forces_h5s, intervals)
    cal, cal_notes = tip_calibration(forces, names)
    fp_notes = implausible_forces({nm: forces[nm]["F_p_mean"] for nm in names})
    for note in cal_notes + fp_notes:
        log.warning(note)
    shared, own, own_invols = seed_streams(seed, tip, len(names))
    sysd = draw_systematic(shared, cal, float(E_star), float(u_E_star), n_samples)

    results = {}
    refs = {str(iv["name"]): bool(iv.get("reference", False)) for iv in intervals}
    for i, nm in enumerate(names):
        shape = interval_shape(fits[nm], refs[nm])
        forces[nm], compliance = correct_contact_compliance(forces[nm], shape.n, shape.Q, float(E_star))
        dr = draw_interval(own[i], shape.fit, forces[nm], n_samples)
        dr["cal_factor"] = interval_calibration_factor(own_invols[i], sysd, forces[nm], n_samples)
        if not shape.usable:
            dr["n"][:] = np.nan
        notes = _interval_notes(nm, shape, forces[nm], dr, compliance, fp_notes)
        _log_interval(tip, nm, shape, forces[nm], compliance, notes)
        solved = _solve_laws(laws, shape, forces[nm], dr, sysd, E_star, h, h[mc_idx], solver_mode, exact)
        results[nm] = _interval_result(shape, dr, notes, solved)
        log.info(
            "%s: interval %d/%d (%s) solved for %d laws x %d Monte-Carlo samples, %.1f s so far",
            tip,
            i + 1,
            len(names),
            nm,
            len(laws),
            n_samples,
            time.perf_counter() - t0,
        )

    settings = _settings(tip, solver_mode, laws, n_samples, seed, E_star, u_E_star, exact)
    write_inversion_h5(
        out_h5,
        settings=settings,
        h=h,
        mc_idx=mc_idx,
        cal=cal,
        cal_notes=cal_notes,
        systematic=sysd,
        intervals=intervals,
        fits=fits,
        forces=forces,
        results=results,
    )
    return {"seconds": time.perf_counter() - t0, "intervals": names, "laws": laws}


def _load_inputs(fit_h5s: dict, forces_h5s: dict, intervals: list):
    """(interval names, their stage-2 fits, their stage-3 forces), or a KeyError naming an interval
    without either file."""
    names = [str(iv["name"]) for iv in intervals]
    for nm in names:
        if nm not in fit_h5s or nm not in forces_h5s:
            raise KeyError(f"interval {nm!r} has no fit or forces file")
    fits = {nm: load_fit(fit_h5s[nm]) for nm in names}
    forces = {nm: load_forces(forces_h5s[nm]) for nm in names}
    return names, fits, forces


def _checked_arguments(laws, solver_mode, h_grid, mc_samples):
    """(laws in lower case, the sorted h grid, the Monte-Carlo size), or a ValueError."""
    laws = [str(x).lower() for x in laws]
    for law in laws:
        if law not in LAWS:
            raise ValueError(f"unknown traction law {law!r}; expected one of {LAWS}")
    if solver_mode not in SOLVER_MODES:
        raise ValueError(f"solver_mode {solver_mode!r} not in {SOLVER_MODES}")
    h = np.sort(np.asarray(h_grid, dtype=float).ravel())
    if h.size < 3 or np.any(h <= 0):
        raise ValueError("h_grid needs at least 3 positive values (m)")
    n_samples = int(mc_samples)
    if n_samples < 10:
        raise ValueError("mc_samples must be >= 10")
    return laws, h, n_samples


def _solve_laws(laws, shape: IntervalShape, fo: dict, dr: dict, sysd: dict, E_star, h, hm, solver_mode, exact) -> dict:
    """Every law's W_A(h) of one interval: the central curve from the best estimates, the samples
    from the draws (F_p times the calibration factor, the clipped (n, Q), the shared E*)."""
    central = {"F": fo["F_p_mean"], "n": shape.n, "Q": shape.Q, "E_star": E_star, "R": shape.fit["R"]}
    samples = {
        "F": (dr["F_p_mean"] * dr["cal_factor"])[:, None],
        "n": dr["n"][:, None],
        "Q": np.exp(dr["ln_Q"])[:, None],
        "E_star": sysd["E_star"][:, None],
    }
    return {law: law_curves(law, central, samples, h, hm, solver_mode, exact) for law in laws}


def _interval_notes(nm: str, shape: IntervalShape, fo: dict, dr: dict, compliance: float, fp_notes: list) -> list:
    """What a reader of this interval's result must know, in words."""
    notes = (
        list(fo["warnings"])
        + [f"TEM edge: {x}" for x in shape.fit.get("edge_notes", [])]
        + ([shape.note] if shape.note else [])
        + [x for x in fp_notes if x.startswith(f"interval {nm}:")]
    )
    if compliance > 1.001:
        notes.append(
            f"InvOLS from the contact slopes corrected for the tip's contact stiffness (Sneddon, DMT load): "
            f"F_p divided by {compliance:.4f}, half the correction added to its uncertainty"
        )
    if not (np.isfinite(fo["F_p_sem"]) and fo["F_p_sem"] > 0):
        notes.append("no statistical uncertainty of F_p (fewer than 2 curves): only calibration/fit/E* propagated")
    if shape.n_flag == "n_clipped_to_2":
        notes.append(f"fitted n = {shape.fit['n']:.4f} < 2 clipped to 2 keeping R")
    if shape.n_flag == "fit_flagged":
        notes.append(
            f"power-law fit flagged {', '.join(shape.bad_fit_flags)}: interval not used (check its profile figure)"
        )
    if np.any(dr["n_clipped"]):
        notes.append(f"{np.mean(dr['n_clipped']):.0%} of MC draws had n < 2 and were clipped to 2 keeping R")
    return notes


def _log_interval(tip: str, nm: str, shape: IntervalShape, fo: dict, compliance: float, notes: list) -> None:
    fit = shape.fit
    log.info(
        "%s %s: n = %.3f +- %.3f (%s), F_p = %.4g nN%s; %s",
        tip,
        nm,
        fit["n"],
        fit["u_n"],
        shape.n_flag,
        fo["F_p_mean"] * 1e9,
        f" (contact compliance {compliance:.4f} applied)" if compliance > 1 else "",
        "; ".join(notes) or "no notes",
    )
