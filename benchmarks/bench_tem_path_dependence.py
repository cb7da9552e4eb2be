"""Path dependence of the TEM stage: the independent grid twice, once with a perturbation that must not matter.

    .venv/bin/python benchmarks/bench_tem_path_dependence.py [N] [--quick] [--jobs 2]
        [--perturb table|image] [--rel R] [--seed0 S] [--csv out.csv]  (both rows of every image)

Runs the images of ``bench_tem_independent`` (its ``case`` and ``run_one``: simulate, save as
an instrument would, ``read_tem_image`` -> ``extract_profile`` -> ``run_fit``, graded against
the truth) twice on the same simulated image: as is, and perturbed by a last-bit change such
as another CPU or BLAS, or a re-ordered sum, makes:

- ``table`` (default, R = 1e-13): ``pipeline.tem.projection.core_radius_sq_table`` (the coated
  body's core table) times (1 + R).  It touches only the coated model: the coating search of
  every image (``coating: auto``) and the final fit of the images it calls coated.
- ``image`` (R = 1e-12): the window ``silhouette_fit.fit_silhouette`` is given times (1 + R):
  every fit of stage 1, the single-layer one too.

A result that is a function of the image alone does not move; the table counts the images
whose fitted n moved by more than 1e-6, 0.01, 0.1, whose interval changed between used and
lost, and whose light-layer decision (single / coated / ambiguous) changed, and prints the
images that moved by more than 0.01.  Also the accuracy summary of both runs (as
``bench_tem_independent``) and the stage-1 time (``t_profile``, s).  Never fails.
"""

from __future__ import annotations

import argparse
import os
import sys
import time

for _var in ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS"):
    os.environ.setdefault(_var, "1")  # one thread per process (set before numpy loads)

import numpy as np

sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))
from bench_tem_independent import grid_arguments, map_images, run_one, summary_row, write_rows  # noqa: E402

THRESHOLDS = (1e-6, 0.01, 0.1)


def _decision(r):
    """single / coated / ambiguous / lost-before-grading ('-')."""
    if r.get("lost") and "dn" not in r:
        return "-"
    return "ambiguous" if r.get("coating_ambiguous") else (r.get("coating_model") or "-")


def _perturbation(kind, rel):
    """(module, attribute name, perturbed replacement) of the perturbation ``kind``."""
    import pipeline.tem.silhouette_fit as sf
    import pipeline.tem.silhouette_model as sm

    if kind == "table":
        orig = sm.core_radius_sq_table

        def table(rho_sq, dz, thickness):
            return orig(rho_sq, dz, thickness) * (1.0 + rel)

        return sm, "core_radius_sq_table", table
    orig = sf.fit_silhouette

    def fit(flat, *args, **kw):
        if kw.get("binning") == 1:  # the binned fit's inner call: its window is scaled already
            return orig(flat, *args, **kw)
        return orig(np.asarray(flat, float) * (1.0 + rel), *args, **kw)

    return sf, "fit_silhouette", fit


def pair(args):
    """Grid image ``i`` as is and perturbed, on one simulation: (row, perturbed row)."""
    i, seed0, workdir, kind, rel = args
    import pipeline.synth.tem_wave as tw

    simulate = tw.simulate
    memo = {}

    def simulate_once(p):
        if p.seed not in memo:
            memo[p.seed] = simulate(p)
        return memo[p.seed]

    tw.simulate = simulate_once
    module, name, perturbed = _perturbation(kind, rel)
    orig = getattr(module, name)
    try:
        a = run_one((i, seed0, workdir, {}, None))
        setattr(module, name, perturbed)
        b = run_one((i, seed0, workdir, {}, None))
    finally:
        setattr(module, name, orig)
        tw.simulate = simulate
    return a, b


def compare(pairs):
    """Counts of the table (dict) and the rows that moved by more than 0.01 in n."""
    moved = {t: 0 for t in THRESHOLDS}
    lost_changed = decision_changed = both_graded = 0
    big = []
    for a, b in pairs:
        if a.get("lost") != b.get("lost"):
            lost_changed += 1
        if _decision(a) != _decision(b):
            decision_changed += 1
        if "n_fit" in a and "n_fit" in b:
            both_graded += 1
            d = abs(a["n_fit"] - b["n_fit"])
            for t in THRESHOLDS:
                moved[t] += d > t
            if d > 0.01 or _decision(a) != _decision(b) or a.get("lost") != b.get("lost"):
                big.append((a, b, d))
    return dict(moved=moved, lost_changed=lost_changed, decision_changed=decision_changed, graded=both_graded), big


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    grid_arguments(ap, jobs=1)
    ap.add_argument("--perturb", choices=("table", "image"), default="table", help="what is perturbed (module doc)")
    ap.add_argument("--rel", type=float, default=None, help="relative perturbation (table 1e-13, image 1e-12)")
    a = ap.parse_args(argv)
    import tempfile

    n = 12 if a.quick else a.n
    rel = a.rel if a.rel is not None else {"table": 1e-13, "image": 1e-12}[a.perturb]
    t0 = time.perf_counter()
    with tempfile.TemporaryDirectory() as tmp:
        jobs = [(i, a.seed0, tmp, a.perturb, rel) for i in range(n)]
        pairs = []
        for p in map_images(pair, jobs, a.jobs):
            pairs.append(p)
            print(".", end="", flush=True, file=sys.stderr)
    wall = time.perf_counter() - t0
    counts, big = compare(pairs)
    print(
        f"\n{n} images of bench_tem_independent, each fitted as is and with the "
        f"{'core table' if a.perturb == 'table' else 'fitted window'} x (1 + {rel:g}) "
        f"(wall {wall:.0f} s on {a.jobs} process(es))\n"
    )
    m = counts["moved"]
    print(f"  images graded in both runs            {counts['graded']:4d}")
    for t in THRESHOLDS:
        print(f"  |n_fit change| > {t:<8g}             {m[t]:4d}")
    print(f"  used <-> lost changed                 {counts['lost_changed']:4d}")
    print(f"  light-layer decision changed          {counts['decision_changed']:4d}")
    if big:
        print("\nimages that moved (n change > 0.01, or decision / lost changed):")
        for x, y, d in big:
            print(
                f"  image {x['i']:3d}: n_fit {x['n_fit']:.4f} -> {y['n_fit']:.4f} (|d| {d:.3g}), "
                f"{_decision(x)} -> {_decision(y)}, {'lost' if x['lost'] else 'used'} -> "
                f"{'lost' if y['lost'] else 'used'}; true n {x['n']:.2f}, {x['layer']} {x['layer_nm']:.1f} nm"
            )
    print(
        f"\n{'run':<12} {'lost':>4} | {'edge med':>8} | {'|dn|<=.1':>8} | {'dF<=3%':>6} | {'n cov':>5} | "
        f"{'stage 1 median (s)':>18} {'stage 1 sum (s)':>15}"
    )
    for label, rows in (("as is", [p[0] for p in pairs]), ("perturbed", [p[1] for p in pairs])):
        s = summary_row(rows)
        t1 = np.array([r.get("t_profile", np.nan) for r in rows], float)
        print(
            f"{label:<12} {s['lost']:>4} | {s.get('edge_med', np.nan):8.3f} | {s.get('dn01', np.nan):8.0%} | "
            f"{s.get('fp3', np.nan):6.0%} | {s.get('cov_n', np.nan):5.0%} | {np.nanmedian(t1):18.2f} "
            f"{np.nansum(t1):15.1f}"
        )
    if a.csv:
        rows = [dict(r, run=run) for p in pairs for run, r in zip(("as is", "perturbed"), p)]
        write_rows(a.csv, rows)


if __name__ == "__main__":
    main()
