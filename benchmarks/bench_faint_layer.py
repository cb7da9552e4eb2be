"""The faint-layer test and its detection limit (``pipeline.tem.faint_layer``) on images of the
INDEPENDENT wave-optical simulator (``pipeline.synth.tem_wave``).

    .venv/bin/python benchmarks/bench_faint_layer.py [--grid N] [--dlc M] [--jobs 2]
        [--jsonl out.jsonl] [--summarize out.jsonl]

Two sets: the N (default 120) images of ``bench_tem_independent`` (uncoated / 1-2 nm oxide / 2-20 nm
DLC of contrast 5-30 %, particles near the apex in half), and M (default 60) images with a faint DLC
layer only (contrast 0.04-0.16, thickness 4-20 nm, the rest drawn as in the grid).  Each image goes
through stage 1 (``extract_profile``, workflow defaults); the truth is the layer's thickness beyond the
fitted edge: the mean distance of the fitted edge (0.3-0.95 x the profile height) inside the true outer
silhouette, clipped to the layer's thickness (0 for uncoated images).

Prints: images tested (a saturated vacuum is not); claims where less than 1 nm of layer lies beyond
the edge (false claims) and on uncoated images; layers above each image's OWN stated limit (at their
thickness beyond the edge) and how many were seen; detection by thickness beyond the edge x contrast;
the median stated limit at 5, 10, 20 nm; the found layers' thickness and contrast against the truth.
Never fails on a number.
"""

from __future__ import annotations

import argparse
import json
import os
import sys
from concurrent.futures import ProcessPoolExecutor

for _var in ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS"):
    os.environ.setdefault(_var, "1")

import numpy as np

sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))


def params(i):
    """Grid image i (< 1000: ``bench_tem_independent.case``) or faint-DLC image i (>= 1000)."""
    from bench_tem_independent import case

    from pipeline.synth.tem_wave import draw_params

    if i < 1000:
        return case(i)
    return draw_params(
        i,
        layer="DLC",
        apex_particles=bool(i % 2),
        layer_contrast=0.04 + 0.12 * ((i * 7919) % 97) / 96,
        layer_thickness=(4 + 16 * ((i * 104729) % 89) / 88) * 1e-9,
    )


def run_one(i):
    """Stage 1 on image i: a dict of the truth and the faint-layer result."""
    from pipeline.synth.tem_wave import simulate
    from pipeline.synth.tem_wave_truth import edge_errors
    from pipeline.tem.profiles import extract_profile
    from pipeline.tem.reading import TemImage

    p = params(i)
    img, truth = simulate(p)
    row = dict(i=i, layer=p.layer, T=p.layer_thickness * 1e9, kappa=truth["layer_contrast"])
    try:
        prof = extract_profile(TemImage(img.astype(float), p.pixel_size, "synthetic"))
    except ValueError as exc:
        return dict(row, error=str(exc))
    sel = (prof.z >= 0.3 * prof.profile_height) & (prof.z <= 0.95 * prof.profile_height)
    bias = edge_errors(prof.edge_px, truth, sel)["bias"] * 1e9
    row["beyond"] = 0.0 if p.layer == "none" else float(np.clip(-bias, 0.0, row["T"]))
    for k, v in prof.edge_model["faint_layer"].items():
        row[k] = v.tolist() if isinstance(v, np.ndarray) else v
    row["limit_table"] = {str(k): v for k, v in row.get("limit_table", {}).items()}
    return row


def summary(rows):
    """The tables of the module doc."""
    rows = [r for r in rows if "error" not in r and np.isfinite(r["beyond"])]
    tested = [r for r in rows if r.get("tested")]
    print(f"images {len(rows)}, tested {len(tested)}")
    none_beyond = [r for r in tested if r["beyond"] < 1.0]
    fc = [r["i"] for r in none_beyond if r["found"]]
    un = [r for r in tested if r["layer"] == "none"]
    print(f"claims with < 1 nm of layer beyond the edge: {len(fc)} of {len(none_beyond)} {fc}")
    print(f"claims on uncoated images: {sum(r['found'] for r in un)} of {len(un)}")
    above = []
    for r in tested:
        th = np.array(r["thickness"]) * 1e9
        if r["beyond"] >= max(1.0, th[0]):
            lim = float(np.interp(r["beyond"], th, r["contrast_limit"]))
            if r["kappa"] > lim:
                above.append((r["i"], round(r["beyond"], 1), round(r["kappa"], 3), round(lim, 3), r["found"]))
    print(f"layers above the image's stated limit: seen {sum(a[-1] for a in above)} of {len(above)}")
    for a in above:
        print("   (image, nm beyond, contrast, limit there, seen)", a)
    print("seen / images, by thickness beyond the fitted edge (rows) and contrast (columns):")
    kb = [(0.0, 0.1), (0.1, 0.2), (0.2, 0.5)]
    print("   " + " ".join(f"{f'{a}-{b}':>9}" for a, b in kb))
    for lo, hi in [(1, 3), (3, 5), (5, 10), (10, 21)]:
        cells = []
        for a, b in kb:
            s = [r for r in tested if r["layer"] != "none" and lo <= r["beyond"] < hi and a <= r["kappa"] < b]
            cells.append(f"{sum(r['found'] for r in s)}/{len(s)}")
        print(f"   {lo}-{hi} nm " + " ".join(f"{c:>9}" for c in cells))
    for T in ("5.0", "10.0", "20.0"):
        v = [r["limit_table"][T] for r in tested if T in r["limit_table"]]
        print(
            f"stated limit at {T} nm: median {np.median(v):.3f}, 90th percentile {np.percentile(v, 90):.3f} ({len(v)})"
        )
    f = [r for r in tested if r["found"] and r["beyond"] >= 1.0]
    if f:
        tr = np.array([r["found_thickness"] * 1e9 / r["beyond"] for r in f])
        cr = np.array([r["found_contrast"] / r["kappa"] for r in f])
        print(
            f"found layers: thickness / true beyond median {np.median(tr):.2f} (range {tr.min():.2f}-{tr.max():.2f}), "
            f"contrast / true median {np.median(cr):.2f} (range {cr.min():.2f}-{cr.max():.2f})"
        )


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--grid", type=int, default=120)
    ap.add_argument("--dlc", type=int, default=60)
    ap.add_argument("--jobs", type=int, default=1)
    ap.add_argument("--jsonl", default=None, help="write the rows here")
    ap.add_argument("--summarize", default=None, help="only print the tables of rows written before")
    a = ap.parse_args(argv)
    if a.summarize:
        with open(a.summarize) as fh:
            rows = [json.loads(line) for line in fh]
    else:
        ids = list(range(a.grid)) + list(range(1000, 1000 + a.dlc))
        with ProcessPoolExecutor(a.jobs) as ex:
            rows = list(ex.map(run_one, ids))
    if a.jsonl and not a.summarize:
        with open(a.jsonl, "w") as fh:
            for r in rows:
                fh.write(json.dumps(r, default=float) + "\n")
    for name, sel in (
        ("the 120-image grid", [r for r in rows if r["i"] < 1000]),
        ("faint DLC", [r for r in rows if r["i"] >= 1000]),
    ):
        if sel:
            print(f"\n== {name} ==")
            summary(sel)


if __name__ == "__main__":
    main()
