"""The stage-5 file ``adhesion_range.h5``: its writer and its reader (the only place the layout is
spelled).

Layout (every dataset has ``units``): ``h_grid``, ``ci_percentiles``; ``intervals/<name>/`` the
interval's shape, forces and InvOLS as stage 4 used them, and for Dugdale Lambda(h),
Lambda_boundary (Eq. 13), rigid_valid, model_used (model_used_<law> for the other laws);
``laws/<law>/reference/`` W_ref, W_ref_pcts, max_rel_change, flatness_h_min;
``laws/<law>/intervals/<name>/`` h_cross, crossings, h_pcts, slope, crossing_fraction,
h_samples and the W_A(h) curves with status, note and side attributes;
``laws/<law>/global/`` h, W_A, their percentiles, chi2(h), W_common(h), chi2_min, dof,
p_value, birge_ratio, tau, the widening of the CIs, the per-sample estimates and the reference
W_A at the estimate.  Root attributes: tip, source, laws, interval_order, conventions,
solver_mode, mc_samples, E_star, ci_percentiles, min_slope, n_sigma_near_2, lj_z0_over_h.
"""

from __future__ import annotations

import h5py
import numpy as np

from pipeline.adhesion_range.crossings import MIN_SLOPE, N_SIGMA_NEAR_2
from pipeline.adhesion_range.curves import CI_PCTS
from pipeline.h5io import atomic_h5, create_group, read_attr_json, read_dataset, write_dataset
from pipeline.inversion.laws import CONVENTIONS, LJ_Z0_OVER_H

# what each interval's group repeats from the inversion (the InvOLS keys: inversion files written
# since InvOLS is per interval)
INTERVAL_KEYS = (
    ("n", "1"),
    ("u_n", "1"),
    ("n_used", "1"),
    ("ln_Q_used", "1"),
    ("Q", "m^(n-1)"),
    ("R", "m"),
    ("S", "1"),
    ("F_p_mean", "N"),
    ("F_p_sem", "N"),
    ("F_p_std", "N"),
    ("n_curves", "1"),
    ("invols", "m/V"),
    ("u_invols", "m/V"),
    ("invols_method", "1"),
    ("invols_contact", "m/V"),
    ("u_invols_contact", "m/V"),
    ("invols_check", "1"),
)


def write_range_h5(out_h5, inv, results, *, tip="", source=""):
    """Write the stage-5 file from the inversion ``inv`` (``load_inversion``) and the per-law
    ``results`` of ``analyse_law``."""
    h = inv["h"]
    with atomic_h5(
        out_h5,
        stage="adhesion_range",
        tip=tip,
        source=source,
        laws=list(results),
        interval_order=inv["order"],
        conventions=CONVENTIONS,
        solver_mode=inv["solver_mode"],
        mc_samples=int(inv["mc_samples"]),
        E_star=float(inv["E_star"]),
        ci_percentiles=list(CI_PCTS),
        min_slope=MIN_SLOPE,
        n_sigma_near_2=N_SIGMA_NEAR_2,
        lj_z0_over_h=LJ_Z0_OVER_H,
    ) as f:
        write_dataset(f, "h_grid", h, "m", "adhesion range grid")
        write_dataset(f, "ci_percentiles", np.array(CI_PCTS), "1", "percentiles stored in *_pcts datasets")
        gi = create_group(f, "intervals")
        for nm in inv["order"]:
            _write_interval(gi, nm, inv["intervals"][nm])
        gl_all = create_group(f, "laws")
        for law, res in results.items():
            gl = create_group(gl_all, law, convention=CONVENTIONS[law])
            if res.get("reference") is not None:
                _write_reference(gl, res["reference"])
            gint = create_group(gl, "intervals")
            for nm in inv["order"]:
                _write_crossing(gint, nm, res["intervals"][nm], inv["intervals"][nm]["laws"][law])
            if res.get("global") is not None:
                _write_global(gl, res["global"], res.get("reference"))


def _write_interval(gi, nm: str, d: dict) -> None:
    g = create_group(gi, nm, scans=d["scans"], reference=d["reference"], n_flag=d["n_flag"])
    for key, unit in INTERVAL_KEYS:
        if key in d:
            write_dataset(g, key, d[key], unit)
    dl = d["laws"].get("dugdale")
    if dl is not None:
        write_dataset(g, "Lambda", dl["Lambda"], "1", "Lambda(h) at the central Dugdale W_A(h)")
        write_dataset(g, "Lambda_boundary", dl["Lambda_boundary"], "1", "Eq. 13")
        write_dataset(g, "rigid_valid", dl["rigid_valid"], "1", "Lambda < Lambda_b(n)")
        write_dataset(g, "model_used", dl["model_used"], "1", "Dugdale model per h")
        if "maugis_lambda" in dl:
            write_dataset(g, "maugis_lambda", dl["maugis_lambda"], "1", "Maugis parameter at the central W_A(h)")
    for law, dlaw in d["laws"].items():  # which model made the other laws' W_A(h)
        if law != "dugdale" and "model_used" in dlaw:
            write_dataset(g, f"model_used_{law}", dlaw["model_used"], "1", f"{law} model per h (rigid or elastic)")


def _write_reference(gl, ref: dict) -> None:
    gr = create_group(gl, "reference", intervals=ref["intervals"])
    write_dataset(gr, "W_ref", ref["W_ref"], "J/m^2", "reference W_A(h) (central)")
    write_dataset(gr, "W_ref_pcts", ref["W_ref_pcts"], "J/m^2", "percentiles (ci_percentiles) of W_ref(h)")
    write_dataset(
        gr, "max_rel_change", ref["max_rel_change"], "1", "(max - min)/median of W_ref(h) over h >= flatness_h_min"
    )
    write_dataset(gr, "flatness_h_min", ref["flatness_h_min"], "m", "lower end of the flatness check")


def _write_crossing(gint, nm: str, info: dict, dl: dict) -> None:
    g = create_group(gint, nm, status=info["status"], note=info.get("note", ""), side=info.get("side", ""))
    write_dataset(g, "h_cross", info.get("h", np.nan), "m", "crossing with the reference (NaN unless status ok)")
    write_dataset(g, "crossings", np.asarray(info.get("crossings", []), float), "m", "all roots on the central curves")
    write_dataset(
        g,
        "h_pcts",
        info.get("h_pcts", np.full(len(CI_PCTS), np.nan)),
        "m",
        "percentiles of the per-sample crossings (NaN: open, censored at the grid edge)",
    )
    write_dataset(g, "slope", info.get("slope", np.nan), "1", "|d ln(W/W_ref)/d ln h| at the crossing")
    write_dataset(
        g,
        "crossing_fraction",
        info.get("crossing_fraction", np.nan),
        "1",
        "fraction of MC samples with a crossing inside the grid",
    )
    if "h_samples" in info:
        write_dataset(g, "h_samples", info["h_samples"], "m", "per-sample crossing (NaN: none in grid)")
    write_dataset(g, "W_A", dl["W_A"], "J/m^2", "central W_A(h) (copied from the inversion)")
    write_dataset(g, "W_A_p16", dl["W_A_p16"], "J/m^2", "16th percentile of the MC W_A(h)")
    write_dataset(g, "W_A_p84", dl["W_A_p84"], "J/m^2", "84th percentile of the MC W_A(h)")


def _write_global(gl, gg: dict, ref) -> None:
    g = create_group(
        gl, "global", status=gg.get("status", ""), note=gg.get("note", ""), intervals_used=gg["intervals_used"]
    )
    write_dataset(g, "h", gg["h"], "m", "global h (argmin chi2)")
    write_dataset(g, "W_A", gg["W_A"], "J/m^2", "common W_A at the global h")
    write_dataset(g, "h_pcts", gg["h_pcts"], "m", "percentiles of per-sample global h (NaN: open at grid edge)")
    write_dataset(g, "W_pcts", gg["W_pcts"], "J/m^2", "percentiles of per-sample common W_A")
    write_dataset(g, "chi2", gg["chi2"], "1", "chi2(h) of the GLS common mean")
    write_dataset(g, "W_common", gg["W_common"], "J/m^2", "GLS common W_A(h)")
    write_dataset(g, "chi2_min", gg["chi2_min"], "1")
    write_dataset(g, "dof", gg["dof"], "1", "number of intervals used - 2")
    write_dataset(g, "p_value", gg.get("p_value", np.nan), "1", "chi2 survival probability")
    write_dataset(
        g,
        "birge_ratio",
        gg.get("birge_ratio", np.nan),
        "1",
        "max(1, sqrt(chi2_min/dof)) (NaN: dof 0); the CIs are scaled by it only with inconsistency: birge",
    )
    write_dataset(
        g,
        "tau",
        gg.get("tau", np.nan),
        "1",
        "between-interval scatter of ln W_A added to every interval (random effects; 0: consistent)",
    )
    for key, desc in (
        ("ci_widening_h", "ratio of the widths of the 95 % interval of h with and without tau"),
        ("ci_widening_W", "the same for W_A"),
    ):
        write_dataset(g, key, gg.get(key, 1.0), "1", desc)
    if "h_pcts_unscaled" in gg:
        write_dataset(g, "h_pcts_unscaled", gg["h_pcts_unscaled"], "m", "h percentiles before the widening")
        write_dataset(g, "W_pcts_unscaled", gg["W_pcts_unscaled"], "J/m^2", "W_A percentiles before the widening")
    if "h_jackknife_rel_sd" in gg:
        write_dataset(
            g,
            "h_jackknife_rel_sd",
            gg["h_jackknife_rel_sd"],
            "1",
            "jackknife SD of ln h over the fits leaving one interval out (the interval of h holds +-1.96 of it)",
        )
    if "h_unscaled" in gg:
        write_dataset(g, "h_unscaled", gg["h_unscaled"], "m", "global h without the between-interval scatter")
        write_dataset(g, "W_A_unscaled", gg["W_A_unscaled"], "J/m^2", "global W_A without it")
    if "h_samples" in gg:
        write_dataset(g, "h_samples", gg["h_samples"], "m", "per-sample global h")
        write_dataset(g, "W_samples", gg["W_samples"], "J/m^2", "per-sample common W_A")
        write_dataset(
            g, "edge_fraction", gg["edge_fraction"], "1", "fraction of samples with the minimum at a grid end"
        )
    if ref is not None:
        hv, w, pc = ref["at_global_h"]
        write_dataset(g, "W_ref_at_h", w, "J/m^2", "reference W_A at the global h (grid median if none)")
        write_dataset(g, "W_ref_at_h_pcts", pc, "J/m^2", "percentiles of the reference W_A there")
        write_dataset(g, "W_ref_h", hv, "m", "h at which W_ref_at_h is evaluated")


def load_range(path) -> dict:
    """Read a stage-5 file into nested dicts (for reports and figures): tip, h, order,
    solver_mode, E_star, law_order, intervals {name: datasets and attributes} and laws {law:
    convention, reference, intervals, global}."""
    out = {"laws": {}, "intervals": {}}
    with h5py.File(path, "r") as f:
        out["tip"] = str(read_attr_json(f, "tip"))
        out["h"] = f["h_grid"][()]
        out["order"] = list(read_attr_json(f, "interval_order"))
        out["solver_mode"] = str(read_attr_json(f, "solver_mode"))
        out["E_star"] = float(f.attrs["E_star"])
        laws = read_attr_json(f, "laws")
        out["law_order"] = [laws] if isinstance(laws, str) else list(laws)
        for nm in out["order"]:
            g = f["intervals"][nm]
            d = {k: read_dataset(g, k)[0] for k in g}
            d.update(
                scans=int(g.attrs["scans"]),
                reference=bool(g.attrs["reference"]),
                n_flag=str(read_attr_json(g, "n_flag")),
            )
            out["intervals"][nm] = d
        for law in out["law_order"]:
            out["laws"][law] = _read_law(f["laws"][law], out["order"])
    return out


def _read_law(gl, order) -> dict:
    law = {"convention": str(read_attr_json(gl, "convention")), "intervals": {}}
    if "reference" in gl:
        law["reference"] = {k: read_dataset(gl["reference"], k)[0] for k in gl["reference"]}
        law["reference"]["intervals"] = read_attr_json(gl["reference"], "intervals")
    for nm in order:
        g = gl["intervals"][nm]
        d = {k: read_dataset(g, k)[0] for k in g}
        d.update(
            status=str(read_attr_json(g, "status")),
            note=str(read_attr_json(g, "note")),
            side=str(read_attr_json(g, "side")),
        )
        law["intervals"][nm] = d
    if "global" in gl:
        g = gl["global"]
        glob = {k: read_dataset(g, k)[0] for k in g}
        glob.update(
            status=str(read_attr_json(g, "status")),
            note=str(read_attr_json(g, "note")),
            intervals_used=read_attr_json(g, "intervals_used"),
        )
        if isinstance(glob["intervals_used"], str):
            glob["intervals_used"] = [glob["intervals_used"]] if glob["intervals_used"] else []
        law["global"] = glob
    return law
