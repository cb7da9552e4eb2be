"""Wear tests with per-interval InvOLS drift, run through stages 3-5: accuracy and coverage of h.

Each case is a tip of 4-6 intervals (a paraboloidal reference, then n rising to 4-6) whose
chip is remounted for every interval: the true InvOLS changes by ``drift`` (relative SD, 3-10 %)
from interval to interval, k stays.  Every interval has ``n_curves`` force curves (written as
CSV in volts, as an instrument would) with ``scatter`` (2-5 %) curve-to-curve pull-off
variation; the true interval F_p comes from the full M-D-n model (Zheng & Yu) for W_A and h.
The power-law fits are drawn around the true shape as stage 2 measures it (n and the radius at
the top of the fit window nearly independent, with the sample images' sigma_n 0.03-0.08 and
sigma(ln r_h) 0.001-0.003; the TEM stage itself is not part of this study); the reference also
gets the paraboloid fit (n held at 2) that stage 2 writes and stage 4 uses for a reference
consistent with n = 2.  The tip configuration gives k but no InvOLS at all, the situation
the default per-interval calibration has to handle.

Inconsistent cases on purpose: ``ref_bias`` (the reference interval's forces off by this
factor: a wrong reference) and ``hidden_bias`` (one worn interval's forces off by it, which no
calibration sees).  The report (``run_case``) says how far h and W_A are from the truth and
whether the 95 % interval covers it.
"""

from __future__ import annotations

import tempfile
from contextlib import contextmanager
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from pipeline.synth import wave_shapes


@dataclass
class Case:
    seed: int
    kind: str  # rigid | elastic | wrong_reference | hidden_bias
    n: list
    R: float  # m
    S: float
    W_A: float  # J/m^2
    h: float  # m
    E_star: float  # Pa
    k: float  # N/m
    u_k_rel: float
    invols: np.ndarray  # m/V per interval (true)
    scatter: float
    n_curves: int
    sigma_n: float
    sigma_ln_rh: float  # 1-sigma of ln r_h, the radius at the top of the 6 nm fit window
    bias: np.ndarray = field(default_factory=lambda: np.ones(0))  # force factor per interval (1: none)


def draw_case(seed: int, kind: str = "rigid") -> Case:
    """One random wear test of the given kind (module doc)."""
    rng = np.random.default_rng([seed, 0xCA11])
    m = int(rng.integers(4, 7))
    n_end = rng.uniform(4.0, 6.0)
    n = [2.0] + list(np.linspace(2.0 + (n_end - 2.0) / (m - 1), n_end, m - 1))
    drift = rng.uniform(0.03, 0.10)
    invols0 = rng.uniform(40e-9, 80e-9)
    elastic = kind == "elastic"
    case = Case(
        seed=seed,
        kind=kind,
        n=n,
        R=rng.uniform(8e-9, 30e-9),
        S=rng.uniform(1.0, 2.0),
        # elastic: Lambda 1.4-2.7 x the Eq. 13 boundary (the M-D-n solution needed); rigid: well below
        W_A=rng.uniform(0.3, 1.0) if elastic else rng.uniform(0.04, 0.1),
        h=rng.uniform(0.4e-9, 0.8e-9) if elastic else rng.uniform(2.5e-9, 6e-9),
        E_star=rng.uniform(30e9, 60e9) if elastic else rng.uniform(60e9, 150e9),
        # a ten times stiffer lever for the large elastic pull-offs (its deflection within the detector's +-10 V)
        k=rng.uniform(0.5, 3.0) * (10.0 if elastic else 1.0),
        u_k_rel=0.05,
        invols=invols0 * (1.0 + drift * rng.standard_normal(m)),
        scatter=rng.uniform(0.02, 0.05),
        n_curves=8,
        sigma_n=rng.uniform(0.03, 0.08),
        sigma_ln_rh=rng.uniform(0.001, 0.003),
        bias=np.ones(m),
    )
    if kind == "wrong_reference":
        case.bias[0] = 1.0 + rng.choice([-1.0, 1.0]) * 0.10
    elif kind == "hidden_bias":
        case.bias[int(rng.integers(1, m))] = 1.0 + rng.choice([-1.0, 1.0]) * 0.10
    return case


FIT_HEIGHT = 6e-9


def _observed_shape(case: Case, n: float, rng):
    """A fitted (n, ln R) and cov(n, ln Q) drawn as stage 2 measures them: n and ln r_h (the
    radius at the top of the fit window) nearly independent, sigma_n and sigma_ln_rh as on the
    sample tips' images (0.03-0.14 and 0.001-0.003); ln Q = n ln r_h - ln n - ln h_fit."""
    lnq = (n - 2.0) * np.log(case.S) + (n - 1.0) * np.log(case.R)
    ln_rh = (lnq + np.log(n) + np.log(FIT_HEIGHT)) / n
    n_obs = n + case.sigma_n * rng.standard_normal()
    ln_rh_obs = ln_rh + case.sigma_ln_rh * rng.standard_normal()
    lnq_obs = n_obs * ln_rh_obs - np.log(n_obs) - np.log(FIT_HEIGHT)
    T = np.array([[1.0, 0.0], [ln_rh_obs - 1.0 / n_obs, n_obs]])
    cov = T @ np.diag([case.sigma_n**2, case.sigma_ln_rh**2]) @ T.T
    return n_obs, (lnq_obs - (n_obs - 2.0) * np.log(case.S)) / (n_obs - 1.0), cov


def true_forces(case: Case) -> np.ndarray:
    """True interval F_p (N), M-D-n model, before any bias."""
    from pipeline.mechanics import pulloff_force

    n = np.asarray(case.n, float)
    q = case.S ** (n - 2.0) * case.R ** (n - 1.0)
    return np.asarray(pulloff_force(n, q, case.E_star, case.W_A, case.h, model="mdn", exact=True), float)


def _instrument(case: Case, rng):
    """An instrument for the case (``pipeline.synth.afm_instrument``): anti-alias filter (none or
    1-3 kHz), detector noise 0.02-0.1 nm, laser interference up to 0.2 nm in a third of the tips,
    the lever's resonance from its stiffness."""
    from pipeline.synth.afm_instrument import Instrument, Lever

    lever = Lever(k=case.k, f0=20e3 * np.sqrt(case.k / 0.1), Q=float(rng.uniform(30, 300)))
    inst = Instrument(
        lowpass=float(rng.choice([0.0, 1e3, 2e3, 3e3])),
        detector_noise=float(rng.uniform(0.02e-9, 0.1e-9)),
        interference=float(rng.uniform(0, 0.2e-9)) if rng.random() < 1 / 3 else 0.0,
        trigger=20e-9,
    )
    return lever, inst


def _write_curves(case: Case, i, n, Fi, folder, rng, generator, lever, inst):
    """The interval's curves: (paths, true F_p per curve, reader settings)."""
    F_curves = Fi * (1.0 + case.scatter * rng.standard_normal(case.n_curves))
    if generator == "lorentzian":  # the stage's own generator (force_curves.make_force_curve)
        from pipeline.synth.force_curves import make_force_curve, write_curve_csv

        paths = []
        for j, Fj in enumerate(F_curves):
            # trigger deflection: 20 nm, or a third of the adhesive jump where that is larger
            c = make_force_curve(
                float(Fj),
                case.k,
                float(case.invols[i]),
                seed=int(rng.integers(2**31)),
                offset_V=float(rng.normal(0, 0.05)),
                tilt=float(rng.normal(0, 2e5)),
                noise=0.1e-9,
                setpoint_deflection=max(20e-9, Fj / case.k / 3.0),
            )
            paths.append(write_curve_csv(folder / f"c{j}.csv", c))
        return paths, F_curves, {}
    from dataclasses import replace

    from pipeline.synth.afm_instrument import READER, Interaction, simulate_curve, write_instrument_csv

    q = case.S ** (n - 2.0) * case.R ** (n - 1.0)
    paths, truth = [], []
    lv = replace(lever, invols=float(case.invols[i]))
    for j, Fj in enumerate(F_curves):
        ins = replace(
            inst,
            offset_V=float(rng.normal(0, 0.1)),
            tilt=float(rng.normal(0, 2e5)),
            trigger=max(20e-9, float(Fj) / case.k / 3.0),
        )
        c = simulate_curve(
            Interaction(float(Fj), "dugdale", case.h, float(n), q, case.E_star), lv, ins, seed=int(rng.integers(2**31))
        )
        paths.append(write_instrument_csv(folder / f"c{j}.tsv", c))
        truth.append(c.truth["F_p"])
    return paths, np.array(truth), dict(READER)


def _reference_paraboloid(case: Case):
    """The reference's paraboloid fit (n held at 2), as stage 2 writes it: (ln r, its variance)."""
    lnr2 = np.log(case.R) + 2.0 * case.sigma_ln_rh * np.random.default_rng([case.seed, 0xA2B]).standard_normal()
    return (lnr2, (2.0 * case.sigma_ln_rh) ** 2)


def _weighted_truth(forces_h5, F_curves) -> float:
    """The true pull-off force of an interval weighted as stage 3 weighted its curves."""
    import h5py

    with h5py.File(forces_h5) as f:
        return float(np.sum(f["curves/weight"][()] * F_curves))


def run_case(
    case: Case,
    workdir=None,
    *,
    mc_samples=1000,
    cantilever=None,
    h_grid=None,
    oracle_invols=False,
    generator="instrument",
    shapes="drawn",
) -> dict:
    """Write the case's curves and fits, run stages 3-5 (Dugdale law), compare with the truth.

    ``generator``: ``instrument`` (default; ``pipeline.synth.afm_instrument``, which shares no
    code or force law with the stage: the tip's own Dugdale law over its power-law shape, a
    Sneddon contact, filters, ringing, interference) or ``lorentzian`` (the stage's own
    ``force_curves`` generator).  ``cantilever``: the tip's ``cantilever:`` section (SI);
    default k with its uncertainty and no InvOLS (per interval, from the contact slopes).
    ``oracle_invols``: every interval is given its true InvOLS with no uncertainty instead
    (what the data would give with a perfect calibration: the errors left are the shape fits'
    and the pull-off scatter's).  ``shapes``: ``drawn`` (default; the fits drawn around the true
    shape, ``_observed_shape``) or ``wave`` (every interval imaged by the wave-optical TEM
    simulator and measured by stages 1 and 2, ``pipeline.synth.wave_shapes``: the whole workflow
    on data it did not generate; an interval whose stage raises is left out, as a user would,
    and a lost reference ends the case with status ``reference lost``) or ``wave_known`` (the same,
    the operator giving stage 1 the sign of every image's defocus, ``tem.defocus``).  Returns a dict of the
    errors and the coverage of the 95 % intervals; ``fp_err_max`` is the worst interval F_p (as
    stage 4 uses it, after the contact compliance correction) against the weighted truth of the
    curves used; ``shape_records`` (wave) the stage-2 result of every interval."""
    from pipeline.inversion.io import load_inversion
    from pipeline.inversion.stage import run_inversion

    rng = np.random.default_rng([case.seed, 0x5EED])
    F = true_forces(case) * case.bias
    cant = cantilever or {"spring_constant": case.k, "spring_constant_uncertainty": case.u_k_rel * case.k}
    lever, inst = _instrument(case, np.random.default_rng([case.seed, 0x1257]))
    if shapes not in ("drawn", "wave", "wave_known"):
        raise ValueError(f"run_case: shapes must be 'drawn', 'wave' or 'wave_known', got {shapes!r}")
    wave = shapes != "drawn"
    materials = wave_shapes.tip_materials(case.seed) if wave else None
    with _workdir(workdir) as root:
        cant = {**cant, "base_dir": str(root)}
        fits, forces, ivs, truth_F, shape_records = {}, {}, [], {}, []
        for i, (n, Fi) in enumerate(zip(case.n, F)):
            nm = f"i{i}"
            fits[nm] = str(root / "fits" / f"{nm}.h5")
            if wave:  # imaged and measured first: the image's area sets the true force
                p = wave_shapes.interval_params(case.seed, i, n, case.R, case.S, materials)
                Path(fits[nm]).parent.mkdir(parents=True, exist_ok=True)
                rec = wave_shapes.wave_interval_fit(
                    p, fits[nm], root, case.S, case.h, defocus_known=shapes == "wave_known"
                )
                shape_records.append(dict(rec, interval=nm, reference=i == 0))
                if rec["raised"]:  # the stage raised: the interval is dropped
                    del fits[nm]
                    if i == 0:
                        break
                    continue
                Fi = Fi * rec["area_factor"]
            forces[nm], truth_F[nm] = _interval_forces(
                case, i, n, Fi, root, rng, generator, (lever, inst), cant, oracle_invols
            )
            if not wave:
                _drawn_fit(case, i, n, fits[nm], rng)
            ivs.append({"name": nm, "scans": 10 * i, "reference": i == 0})
        if "i0" not in fits:
            status = {"status": "reference lost", "shape_records": shape_records}
            return {"seed": case.seed, "kind": case.kind, "intervals": len(case.n), **status}
        run_inversion(
            fits,
            forces,
            root / "inversion.h5",
            intervals=ivs,
            E_star=case.E_star,
            u_E_star=0.03 * case.E_star,
            h_grid=np.geomspace(0.1e-9, 20e-9, 160) if h_grid is None else h_grid,
            laws=("dugdale",),
            mc_samples=mc_samples,
            seed=case.seed,
            tip=f"case{case.seed}",
        )
        out = _against_truth(load_inversion(root / "inversion.h5"), case, truth_F)
    out["shape_records"] = shape_records
    return out


@contextmanager
def _workdir(workdir):
    """``workdir`` as a Path, or a temporary directory removed afterwards."""
    if workdir is not None:
        yield Path(workdir)
        return
    with tempfile.TemporaryDirectory() as tmp:
        yield Path(tmp)


def _interval_forces(case, i, n, Fi, root, rng, generator, instrument, cant, oracle_invols):
    """Write interval ``i``'s curves and run stage 3 on them: (forces HDF5 path, true F_p weighted as
    stage 3 weighted the curves)."""
    from pipeline.forces.stage import run_forces

    nm = f"i{i}"
    paths, F_curves, reader = _write_curves(case, i, n, Fi, root / "curves" / nm, rng, generator, *instrument)
    out = str(root / "forces" / f"{nm}.h5")
    icfg = (
        {"deflection_sensitivity": float(case.invols[i]), "deflection_sensitivity_uncertainty": 0.0}
        if oracle_invols
        else {}
    )
    run_forces(
        paths,
        out,
        root / "forces" / f"{nm}.png",
        cantilever=cant,
        reader=reader,
        tip=f"case{case.seed}",
        interval=nm,
        interval_cfg=icfg,
    )
    return out, _weighted_truth(out, F_curves)


def _drawn_fit(case, i, n, path, rng):
    """Interval ``i``'s stage-2 file with the fit drawn around the true shape (``_observed_shape``;
    the reference also gets its paraboloid fit)."""
    from pipeline.synth.stage_inputs import write_synthetic_fit

    n_obs, lnr_obs, cov = _observed_shape(case, n, rng)
    para = _reference_paraboloid(case) if i == 0 else None
    write_synthetic_fit(path, n_obs, lnr_obs, case.S, cov, flags=("",), rms_residual=0.05e-9, paraboloid=para)


def _against_truth(inv: dict, case: Case, truth_F: dict) -> dict:
    """The errors of F_p, h and W_A against the case's truth and whether the 95 % intervals cover
    it, for random effects (keys unprefixed) and Birge scaling (``birge_`` keys)."""
    from pipeline.adhesion_range.analysis import analyse_law

    fp_err = [inv["intervals"][nm]["F_p_mean"] / truth_F[nm] - 1.0 for nm in truth_F]
    out = {
        "seed": case.seed,
        "kind": case.kind,
        "intervals": len(case.n),
        "drift_sd": float(np.std(case.invols) / np.mean(case.invols)),
        "fp_err_max": float(np.max(np.abs(fp_err))),
        "lambda_over_boundary": _max_lambda_ratio(case),
    }
    for model in ("random_effects", "birge"):  # the default first: its keys are unprefixed
        res = analyse_law(inv, "dugdale", model)
        if "global" not in res:  # no usable reference (stage 2 flagged it): no h, said so
            out.update(status=res.get("status", "no_reference"), note=" ".join(res.get("notes", [])))
            return out
        g = res["global"]
        hp, wp = np.asarray(g["h_pcts"]), np.asarray(g["W_pcts"])
        r = {
            "status": g.get("status", ""),
            "h_err": g["h"] / case.h - 1.0,
            "W_err": g["W_A"] / case.W_A - 1.0,
            "h_covered": bool(np.nan_to_num(hp[0], nan=-np.inf) <= case.h <= np.nan_to_num(hp[-1], nan=np.inf)),
            "W_covered": bool(wp[0] <= case.W_A <= wp[-1]),
            "h_rel_halfwidth": 0.5 * (hp[-1] - hp[0]) / g["h"],
            "birge": float(g.get("birge_ratio", np.nan)),
            "tau": float(g.get("tau", np.nan)),
            "chi2": float(g["chi2_min"]),
            "dof": int(g["dof"]),
            "note": g.get("note", ""),
        }
        out.update(r if model == "random_effects" else {f"birge_{k}": v for k, v in r.items()})
    return out


def _max_lambda_ratio(case: Case) -> float:
    """Largest Lambda / Lambda_b(n) over the worn intervals at the true W_A, h (> 1: elastic, Eq. 13)."""
    from pipeline.inversion.solve import regime

    n = np.asarray(case.n[1:], float)
    q = case.S ** (n - 2.0) * case.R ** (n - 1.0)
    lam, lam_b, _ = regime(np.full(n.shape, case.W_A), n, q, np.full(n.shape, case.E_star), np.full(n.shape, case.h))
    return float(np.nanmax(lam / lam_b))
