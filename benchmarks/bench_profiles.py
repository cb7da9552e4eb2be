"""Accuracy and speed of the TEM profile + power-law fit stages on synthetic images.

    .venv/bin/python benchmarks/bench_profiles.py [--quick] [--tip-b] [--refine normals|global]

Prints one row per image: pixel size, blur, edge SNR, coating, n, rotation ->
RMS profile error (orthogonal distance to the true outer surface over the 6 nm
fit window), RMS r(z) error (z >= 0.5 nm), |n_fit - n|, the max error of the
rigid Dugdale pull-off (n h Q)^(2/n) (Eq. 12) over h = 1-6 nm, and the run
time of the profile extraction; then the bundled sample tip B (fitted n per
interval) and the time for one 2048 x 2048 image.
"""

from __future__ import annotations

import argparse
import itertools
import os
import time

for _var in ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS"):
    os.environ.setdefault(_var, "1")  # the run-time target is for one core (set before numpy loads)

import numpy as np

from pipeline.synth.tem_truth import coating_decision, evaluate_case

# (pixel size m, blur sigma px, edge SNR, rotation deg) combinations crossed with n and coating
CONDITIONS = [
    (0.1e-9, 1.0, 20.0, 3.0),
    (0.25e-9, 0.5, np.inf, -8.0),
    (0.25e-9, 2.0, 5.0, 12.0),
    (0.5e-9, 1.0, 10.0, -3.0),
    (0.5e-9, 2.0, 5.0, 15.0),
]
COATINGS = [0.0, 1.5e-9, 15e-9]  # none, native oxide (tip B), DLC (tip A)
NS = [2.0, 3.0, 4.0, 6.0]


def tip_b_images():
    """The bundled sample tip B (``pipeline.synth.wear_test.sample_tips()[1]``: 0.2 nm px,
    blur 1.2 px, SNR 15, 1.5 nm oxide, R = 10 nm, S = 2, contamination on the last
    interval), re-rendered with the seeds drawn exactly as ``generate_tip`` draws them
    (same images as data_samples/tipB_Si/tem); yields (name, image, truth)."""
    from pipeline.synth.tem_image import render_tem_image
    from pipeline.synth.wear_test import sample_tips

    t = sample_tips()[1]
    rng = np.random.default_rng(t.seed)
    for i, (name, n) in enumerate(zip(t.interval_names(), t.n)):
        rot = t.rotation_deg + rng.normal(0, 0.5)
        seed = int(rng.integers(2**31))
        img, truth = render_tem_image(
            n,
            t.Q(n),
            t.pixel_size,
            shape=(512, 512),
            blur_sigma_px=t.blur_sigma_px,
            edge_snr=t.edge_snr,
            rotation_deg=rot,
            coating_thickness=t.coating,
            orientation="down",
            seed=seed,
            S=t.S,
            contamination=(i == len(t.n) - 1),
        )
        # draws of the force curves of this interval (generate_tip order)
        rng.standard_normal(t.curves_per_interval)
        for _ in range(t.curves_per_interval):
            rng.integers(2**31), rng.normal(0.0, 0.05), rng.normal(0.0, 2e5)
        yield name, img, truth


def bench_tip_b():
    from pipeline.fits.profile_fit import fit_tip_profile
    from pipeline.synth.tem_truth import force_errors, profile_errors
    from pipeline.tem.profiles import extract_profile
    from pipeline.tem.reading import TemImage

    print("\nsample tip B (0.2 nm px, blur 1.2 px, SNR 15, 1.5 nm oxide, R = 10 nm, S = 2)")
    print(
        f"{'interval':>8} {'n':>5} {'n_fit':>6} {'sig_n':>6} | {'rmsN nm':>8} {'|dF|max%':>8} {'coat nm':>7} {'t s':>5}"
    )
    for name, img, truth in tip_b_images():
        px = truth["pixel_size"]
        t0 = time.perf_counter()
        prof = extract_profile(TemImage(img.astype(np.float64), px, "synthetic"))
        dt = time.perf_counter() - t0
        fit = fit_tip_profile(prof, 6e-9)
        pe = profile_errors(prof, truth, 6e-9)
        fe = np.max(np.abs(force_errors(fit.n, fit.Q, truth)))
        print(
            f"{name:>8} {truth['n']:5.2f} {fit.n:6.3f} {fit.sigma_n:6.3f} | {pe['rms_normal'] * 1e9:8.3f} "
            f"{100 * fe:8.2f} {prof.edge_model['coating_thickness'] * 1e9:7.2f} {dt:5.2f}",
            flush=True,
        )


def _layer(e):
    """The coating decision of the edge model: 'single', 'coated 1.49' (nm) or 'ambiguous'."""
    d = coating_decision(e["profile"])
    if d == "found":
        return f"coated {e['profile'].edge_model['coating_thickness'] * 1e9:.2f}"
    return "ambiguous" if d == "flagged" else "single"


def _use_refine(refine):
    """Make every extract_profile call of this run use ``refine`` (evaluate_case imports it
    from the module at call time)."""
    import functools

    import pipeline.tem.profiles as profiles

    orig = getattr(profiles.extract_profile, "__wrapped_orig__", profiles.extract_profile)
    wrapped = functools.partial(orig, refine=refine)
    wrapped.__wrapped_orig__ = orig
    profiles.extract_profile = wrapped
    print(f"edge refinement: {refine}")


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--quick", action="store_true", help="n = 2 and 4 only, two conditions")
    ap.add_argument("--tip-b", action="store_true", help="only the sample tip B case")
    ap.add_argument(
        "--refine",
        choices=("normals", "global"),
        default=None,
        help="edge refinement passed to extract_profile (default: its default)",
    )
    a = ap.parse_args(argv)
    if a.refine is not None:
        _use_refine(a.refine)
    if a.tip_b:
        return bench_tip_b()
    conds = CONDITIONS[1:3] if a.quick else CONDITIONS
    ns = [2.0, 4.0] if a.quick else NS
    print(
        f"{'px nm':>6} {'blur':>5} {'SNR':>5} {'coat nm':>7} {'n':>4} {'rot':>5} | {'rmsN nm':>8} {'rms_r nm':>8} "
        f"{'|dn|':>6} {'sig_n':>6} {'|dF|max%':>8} {'t s':>6} | {'layer':>11} {'dn/sn':>5} {'rms/sd':>6}  flags"
    )
    rows = []
    for (px, blur, snr, rot), coat, n in itertools.product(conds, COATINGS, ns):
        seed = len(rows)
        try:
            e = evaluate_case(n, px, blur, snr, rot, coat, seed=seed, orientation="down" if seed % 3 else "up")
        except ValueError as exc:
            print(f"{px * 1e9:6.2f} {blur:5.1f} {snr:5.0f} {coat * 1e9:7.1f} {n:4.0f} {rot:5.0f} | FAILED: {exc}")
            continue
        rows.append(e)
        print(
            f"{px * 1e9:6.2f} {blur:5.1f} {snr:5.0f} {coat * 1e9:7.1f} {n:4.0f} {rot:5.0f} | "
            f"{e['rms_normal'] * 1e9:8.3f} {e['rms_r'] * 1e9:8.3f} {abs(e['dn']):6.3f} {e['sigma_n']:6.3f} "
            f"{100 * e['force_err_max']:8.2f} {e['t_profile']:6.2f} | {_layer(e):>11} "
            f"{abs(e['dn']) / e['sigma_n']:5.1f} {e['rms_normal'] / e['reported']['edge_sd']:6.1f}  "
            f"{','.join(e['flags'])}",
            flush=True,
        )
    if rows:
        arr = lambda k: np.array([r[k] for r in rows])  # noqa: E731
        layer = np.array([coating_decision(r["profile"]) for r in rows])
        coat_true = np.array([r["truth"].get("coating_thickness", 0.0) for r in rows])
        thin = (coat_true > 0) & (coat_true < 5e-9)
        print(
            f"\nlight layer: thin oxide images {thin.sum()}: found {np.sum(thin & (layer == 'found'))}, "
            f"flagged ambiguous {np.sum(thin & (layer == 'flagged'))}; images without a thin layer {(~thin).sum()}: "
            f"layer found {np.sum(~thin & (layer == 'found'))}, flagged {np.sum(~thin & (layer == 'flagged'))}"
        )
        print(
            f"\nsummary over {len(rows)} images: median rmsN {np.median(arr('rms_normal')) * 1e9:.3f} nm, "
            f"max {arr('rms_normal').max() * 1e9:.3f} nm; |dn| <= 0.1 in {np.mean(np.abs(arr('dn')) <= 0.1):.0%}; "
            f"|dF| <= 3 % in {np.mean(arr('force_err_max') <= 0.03):.0%}; "
            f"median time {np.median(arr('t_profile')):.2f} s"
        )
    bench_tip_b()
    # one large image
    from pipeline.synth.tem_image import render_tem_image
    from pipeline.tem.profiles import extract_profile
    from pipeline.tem.reading import TemImage

    img, _ = render_tem_image(3.0, (15e-9) ** 2, 0.1e-9, shape=(2048, 2048), edge_snr=20, seed=7)
    im = TemImage(img.astype(np.float64), 0.1e-9, "synthetic")
    extract_profile(im)  # warm-up (imports, caches)
    t0 = time.perf_counter()
    extract_profile(im)
    print(f"2048 x 2048 image (0.1 nm px, 20 nm profile): {time.perf_counter() - t0:.2f} s")


if __name__ == "__main__":
    main()
