"""The TEM stage on images it does not model: the independent wave-optical simulator.

    .venv/bin/python benchmarks/bench_tem_independent.py [N] [--quick] [--jobs 2] [--csv out.csv]
        [--verbose] [--seed0 S] [--fix KEY=VALUE ...] [--figures DIR]

Draws N (default 120) images with ``pipeline.synth.tem_wave.draw_params`` (every parameter
in the ranges of that module's doc; the layer cycles none / oxide / DLC and particles near
the apex are on in every other pair of images, the rest is random by seed), saves each as an
instrument would (8/16-bit TIFF with ImageJ calibration, or an uncalibrated PNG whose pixel
size comes from the "tip YAML" as in the workflow, or a float32 TIFF), and runs it through
the workflow's path: ``read_tem_image`` -> ``extract_profile`` (workflow defaults: orientation
auto, 20 nm profile, coating auto, global refinement) -> profile HDF5 -> ``pipeline.fits.stage.run_fit``
(6 nm window, S = 1).  ``pipeline.synth.tem_wave_truth`` grades each against the truth.

Prints one row per image (with --verbose), then per category and overall: images, lost (the
inversion would drop them: the stage raised, an unusable fit flag, n far below 2), median
and max edge RMS (nm; edge points stage 2 fits vs the true outer silhouette), |dn| <= 0.1,
max |dn|, rigid Dugdale pull-off (Eq. 12, h = 1-6 nm) within 3 %, n within its reported
2 sigma_n, pull-off within its reported 2 SD (``F cov``: linear; ``F MC``: (n, ln Q) drawn as the
inversion draws them, 2.3-97.7 % of the draws), the edge's signed mean offset within 2 of its reported
SD (``e cov``: the edge covariance's common part), median |n_ideal - n| (stage 2 on the exact true
silhouette: the floor a perfect edge would reach), and the median times (s) of the
simulation and of the stage.  Never fails on time or error.
"""

from __future__ import annotations

import argparse
import collections
import csv
import os
import sys
import tempfile
import time

for _var in ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS"):
    os.environ.setdefault(_var, "1")  # one thread per process (set before numpy loads)

import numpy as np

LAYERS = ("none", "oxide", "DLC")


def case(i, seed0=0, fixed=None):
    """Parameters of grid image ``i``: the layer cycles, apex particles on in every other pair;
    ``fixed``: keywords of ``draw_params`` that override the draw (e.g. defocus=0)."""
    from pipeline.synth.tem_wave import draw_params

    kw = dict(layer=LAYERS[i % 3], apex_particles=bool((i // 3) % 2))
    kw.update(fixed or {})
    return draw_params(seed0 + i, **kw)


def _parse_fixed(items):
    """["defocus=0", "layer=none", "apex_particles=False"] -> dict with numbers / bools / strings."""
    out = {}
    for it in items or []:
        k, _, v = it.partition("=")
        if v in ("True", "False", "None"):
            out[k] = {"True": True, "False": False, "None": None}[v]
            continue
        for conv in (int, float):
            try:
                out[k] = conv(v)
                break
            except ValueError:
                pass
        else:
            out[k] = v
    return out


def run_one(args):
    """Simulate, save, run the stage, grade: one CSV row (dict).  ``args``: (i, seed0, workdir, fixed,
    figdir[, defocus_known]); with ``defocus_known`` the stage is told the sign of the image's defocus
    (``tem.defocus``), as an operator who knows it would."""
    i, seed0, workdir, fixed, figdir, *known = args
    from pipeline.synth.tem_wave import simulate, write_image
    from pipeline.synth.tem_wave_truth import evaluate_file

    p = case(i, seed0, fixed)
    t0 = time.perf_counter()
    img, truth = simulate(p)
    t_sim = time.perf_counter() - t0
    fmt = "float tif" if p.bits == 0 else ("png" if (i * 7) % 10 < 3 else "tif")
    path = os.path.join(workdir, f"img_{i:04d}.{'png' if fmt == 'png' else 'tif'}")
    write_image(path, img, p.pixel_size)
    fig = os.path.join(figdir, f"image_{i:04d}.png") if figdir else None
    defocus = ("underfocus" if p.defocus > 0 else "overfocus") if known and known[0] and p.defocus else "auto"
    g = evaluate_file(path, truth, pixel_size=p.pixel_size if fmt == "png" else None, figure=fig, defocus=defocus)
    os.remove(path)
    apex_parts = [q for q in truth["particles"] if q["kind"] == "apex"]
    row = dict(
        i=i,
        seed=p.seed,
        n=p.n,
        R_nm=p.R * 1e9,
        S=p.S,
        layer=p.layer,
        layer_nm=p.layer_thickness * 1e9,
        layer_contrast=truth["layer_contrast"],
        asymmetry=p.asymmetry,
        apex_particles=len(apex_parts),
        particle_flank=truth["particle_flank"] or "",
        lowest_particle_nm=min((q["height"] for q in apex_parts), default=np.nan) * 1e9,
        particle_protrusion_nm=max((q["protrusion"] for q in apex_parts), default=np.nan) * 1e9,
        shank_blobs=len(truth["particles"]) - len(apex_parts),
        kv=p.kv,
        defocus_um=p.defocus * 1e6,
        fringe_nm=truth["optics"]["fringe_width"] * 1e9,
        cs_mm=p.cs * 1e3,
        aperture_mrad=p.aperture * 1e3,
        pixel_nm=p.pixel_size * 1e9,
        side_px=p.shape[0],
        snr=p.snr,
        bits=p.bits,
        file=fmt,
        saturated=truth["saturated_fraction"] > 0.01,
        rotation_deg=p.rotation_deg,
        orientation=p.orientation,
        t_sim_s=t_sim,
    )
    for k, v in g.items():
        if k in ("fit_flags", "edge_flags"):
            v = " | ".join(v)  # the flags are sentences, some with ";" in them
        elif k in (
            "edge_rms",
            "edge_rms_left",
            "edge_rms_right",
            "edge_bias",
            "edge_bias_sd",
            "edge_max",
            "apex_error",
            "apex_dz",
            "coating_found",
            "blur_sigma",
            "dim_zone",
            "bright_band",
        ):
            k, v = k + "_nm", v * 1e9
        row[k] = v
    return row


def categories():
    """(label, predicate) pairs of the summary table."""
    return [
        ("all", lambda r: True),
        ("uncoated", lambda r: r["layer"] == "none"),
        ("oxide 1-2 nm", lambda r: r["layer"] == "oxide"),
        ("DLC 2-20 nm", lambda r: r["layer"] == "DLC"),
        ("particles near apex", lambda r: r["apex_particles"] > 0),
        ("no particles near apex", lambda r: r["apex_particles"] == 0),
        ("shank contamination", lambda r: r["shank_blobs"] > 0),
        ("|df| < 0.1 um", lambda r: abs(r["defocus_um"]) < 0.1),
        ("|df| 0.1-0.5 um", lambda r: 0.1 <= abs(r["defocus_um"]) < 0.5),
        ("|df| >= 0.5 um (fringes)", lambda r: abs(r["defocus_um"]) >= 0.5),
        ("asymmetric (e != 0)", lambda r: r["asymmetry"] != 0),
        ("axisymmetric", lambda r: r["asymmetry"] == 0),
        ("8 bit", lambda r: r["bits"] == 8),
        ("16 bit", lambda r: r["bits"] == 16),
        ("float32", lambda r: r["bits"] == 0),
        ("saturated vacuum", lambda r: r["saturated"]),
        ("SNR 5-10", lambda r: r["snr"] < 10),
        ("SNR 10-20", lambda r: 10 <= r["snr"] < 20),
        ("SNR 20-30", lambda r: r["snr"] >= 20),
        ("pixel 0.1-0.2 nm", lambda r: r["pixel_nm"] < 0.2),
        ("pixel 0.2-0.35 nm", lambda r: 0.2 <= r["pixel_nm"] < 0.35),
        ("pixel 0.35-0.5 nm", lambda r: r["pixel_nm"] >= 0.35),
        ("100-170 kV", lambda r: r["kv"] < 170),
        ("170-240 kV", lambda r: 170 <= r["kv"] < 240),
        ("240-300 kV", lambda r: r["kv"] >= 240),
        ("256-511 px", lambda r: r["side_px"] < 512),
        ("512-1024 px", lambda r: r["side_px"] >= 512),
        ("n 2-3", lambda r: r["n"] < 3),
        ("n 3-4.5", lambda r: 3 <= r["n"] < 4.5),
        ("n 4.5-6", lambda r: r["n"] >= 4.5),
    ]


def summary_row(rows):
    """Statistics of one category (see module doc)."""
    used = [r for r in rows if not r["lost"]]
    lost = len(rows) - len(used)
    arr = lambda k: np.array([r[k] for r in used], float)  # noqa: E731
    out = dict(N=len(rows), lost=lost)
    if used:
        e, dn, fp = arr("edge_rms_nm"), np.abs(arr("dn")), arr("pulloff_error")
        out.update(
            edge_med=np.nanmedian(e),
            edge_max=np.nanmax(e),
            dn01=np.mean(dn <= 0.1),
            dn_max=np.max(dn),
            fp3=np.mean(fp <= 0.03),
            cov_n=np.mean([r["n_covered"] for r in used]),
            cov_fp=np.mean([r["pulloff_covered"] for r in used]),
            cov_fp_mc=np.mean([r["pulloff_covered_mc"] for r in used]),
            cov_e=np.mean([r["edge_bias_covered"] for r in used]),
            dn_ideal=np.median(np.abs(arr("dn_ideal"))),
        )
    out.update(t_sim=np.median([r["t_sim_s"] for r in rows]), t_stage=np.median([r["t_stage"] for r in rows]))
    return out


def print_table(rows):
    hdr = (
        f"{'category':<26} {'N':>4} {'lost':>4} | {'edge med':>8} {'edge max':>8} | {'|dn|<=.1':>8} "
        f"{'max|dn|':>7} | {'dF<=3%':>6} | {'n cov':>5} {'F cov':>5} {'F MC':>5} {'e cov':>5} | {'|dn| ideal':>10} | "
        f"{'t sim':>5} {'t stage':>7}"
    )
    print(hdr)
    print("-" * len(hdr))
    for label, pred in categories():
        sel = [r for r in rows if pred(r)]
        if not sel:
            continue
        s = summary_row(sel)
        if "edge_med" in s:
            print(
                f"{label:<26} {s['N']:>4} {s['lost']:>4} | {s['edge_med']:8.3f} {s['edge_max']:8.2f} | "
                f"{s['dn01']:8.0%} {s['dn_max']:7.2f} | {s['fp3']:6.0%} | {s['cov_n']:5.0%} {s['cov_fp']:5.0%} "
                f"{s['cov_fp_mc']:5.0%} {s['cov_e']:5.0%} | "
                f"{s['dn_ideal']:10.3f} | {s['t_sim']:5.2f} {s['t_stage']:7.2f}"
            )
        else:
            print(f"{label:<26} {s['N']:>4} {s['lost']:>4} | (all lost)")
    print("\nlight-layer decision of the edge model (coated = layer found, ambiguous = flagged, single = neither):")
    for layer in LAYERS:
        sel = [r for r in rows if r["layer"] == layer and not (r["lost"] and "dn" not in r)]
        c = collections.Counter(("ambiguous" if r["coating_ambiguous"] else r["coating_model"] or "-") for r in sel)
        found = [r for r in sel if r["coating_model"] == "coated"]
        dt = np.median([r["coating_found_nm"] - r["layer_nm"] for r in found]) if found else np.nan
        print(
            f"  true {layer:<6} {len(sel):3d}: "
            + ", ".join(f"{k} {v}" for k, v in sorted(c.items()))
            + (f"; found layer - true layer median {dt:+.2f} nm" if found and layer != "none" else "")
        )
    reasons = collections.Counter(r["lost_reason"].split(" (")[0][:110] for r in rows if r["lost"])
    if reasons:
        print("\nintervals lost, by reason:")
        for k, v in reasons.most_common():
            print(f"  {v:3d}  {k}")


def grid_arguments(ap, jobs):
    """The grid's command-line arguments (N, --quick, --seed0, --jobs, --csv) on ``ap``."""
    ap.add_argument("n", nargs="?", type=int, default=120, help="number of images (default 120)")
    ap.add_argument("--quick", action="store_true", help="12 images (every layer with and without particles)")
    ap.add_argument("--seed0", type=int, default=0, help="seed of image 0")
    ap.add_argument("--jobs", type=int, default=jobs, help="worker processes (one thread each)")
    ap.add_argument("--csv", default=None, help="write the per-image rows to this CSV")


def map_images(func, jobs, n_jobs):
    """``func`` over ``jobs`` in order, on ``n_jobs`` forked worker processes (or in this one)."""
    if n_jobs > 1:
        import multiprocessing as mp

        with mp.get_context("fork").Pool(n_jobs, maxtasksperchild=10) as pool:
            yield from pool.imap(func, jobs)
    else:
        yield from map(func, jobs)


def write_rows(path, rows):
    """The per-image rows (dicts) as a CSV, every key a column."""
    keys = list(dict.fromkeys(k for r in rows for k in r))
    with open(path, "w", newline="") as fh:
        w = csv.DictWriter(fh, fieldnames=keys)
        w.writeheader()
        w.writerows(rows)
    print(f"\nper-image rows: {path}")


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    grid_arguments(ap, jobs=2)
    ap.add_argument("--verbose", action="store_true", help="print one row per image")
    ap.add_argument(
        "--figures",
        default=None,
        metavar="DIR",
        help="save per image a PNG of the apex with the true and the extracted edge",
    )
    ap.add_argument(
        "--fix",
        action="append",
        metavar="KEY=VALUE",
        help="hold a draw_params keyword for every image (repeatable), e.g. --fix defocus=0 "
        "--fix layer=none --fix apex_particles=False (SI units)",
    )
    ap.add_argument(
        "--defocus-known",
        action="store_true",
        help="tell the stage the sign of each image's defocus (tem.defocus: underfocus / overfocus)",
    )
    a = ap.parse_args(argv)
    n = 12 if a.quick else a.n
    t0 = time.perf_counter()
    rows = []
    with tempfile.TemporaryDirectory() as tmp:
        fixed = _parse_fixed(a.fix)
        if a.figures:
            os.makedirs(a.figures, exist_ok=True)
        jobs = [(i, a.seed0, tmp, fixed, a.figures, a.defocus_known) for i in range(n)]
        for r in map_images(run_one, jobs, a.jobs):
            rows.append(r)
            _progress(r, a.verbose)
    wall = time.perf_counter() - t0
    print(
        f"\n{n} independent-simulator images through the current TEM stage + stage 2 "
        f"(wall {wall:.0f} s on {a.jobs} process(es)){'; held: ' + ', '.join(a.fix) if a.fix else ''}"
        f"{'; the defocus sign given' if a.defocus_known else ''}\n"
    )
    print_table(rows)
    used = [r for r in rows if not r["lost"]]
    if used:
        bad = sorted(used, key=lambda r: -abs(r["dn"]))[:8]
        print("\nlargest |dn| among used intervals:")
        for r in bad:
            print(
                f"  image {r['i']:3d}: n {r['n']:.2f} dn {r['dn']:+.2f} (sigma_n {r['sigma_n']:.2f}, ideal "
                f"{r['dn_ideal']:+.2f}) edge {r['edge_rms_nm']:.2f} nm, {r['layer']} {r['layer_nm']:.1f} nm, "
                f"e {r['asymmetry']:+.3f}, particles {r['apex_particles']}, df {r['defocus_um']:+.2f} um, "
                f"px {r['pixel_nm']:.2f}, SNR {r['snr']:.0f}, coating model {r['coating_model'] or '-'}"
            )
    if a.csv:
        write_rows(a.csv, rows)


def _progress(r, verbose):
    if verbose:
        if r["lost"]:
            print(f"  {r['i']:4d} LOST {r['lost_reason'][:100]}", flush=True)
        else:
            print(
                f"  {r['i']:4d} n {r['n']:.2f} dn {r['dn']:+.3f} sn {r['sigma_n']:.3f} edge {r['edge_rms_nm']:.3f} "
                f"nm dF {100 * r['pulloff_error']:.1f} % {r['layer']} t {r['t_sim_s']:.1f}+{r['t_stage']:.1f} s",
                flush=True,
            )
    else:
        print(".", end="", flush=True, file=sys.stderr)


if __name__ == "__main__":
    main()
