"""The coating test where it is hardest: a 1.5 nm light oxide at coarse pixels, strong blur, low SNR.

    .venv/bin/python benchmarks/bench_thin_oxide.py [--seeds 4] [--jobs 2]

Images of tips with and without a 1.5 nm oxide (n 2, 3, 4, 6; rotations -12..14 deg; both
orientations) at 0.5 nm px / blur 2 px / SNR 10 and 5, and 0.25 nm px / blur 2 px / SNR 5, fitted
with ``tem.coating: auto``. Per image: the decision of the coating test (found = coated model with
its thickness, flagged = "coating ambiguous", neither = single layer, unflagged), the chi^2 gain of
the layer, the errors (RMS edge distance to the true outer surface, dn, max Dugdale pull-off error
over h = 1-6 nm) and whether they are covered by what the pipeline reports:
|dn| <= max(0.1, 3.5 sigma_n) and |dF| <= max(3 %, 3.5 sigma_F) ("covered" in the table), and
the RMS edge error <= 3.5 x the reported edge SD ("edge cov.").
Then the counts per regime. The issue's targets are 0.1 in n and 3 % in the pull-off; 3.5 x the
reported SD is the slow grid test's allowance where the image cannot meet them.
"""

from __future__ import annotations

import argparse
import itertools
import os

for _var in ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS"):
    os.environ.setdefault(_var, "1")

import numpy as np

REGIMES = [(0.5e-9, 10.0), (0.5e-9, 5.0), (0.25e-9, 5.0)]  # (pixel size m, edge SNR), blur 2 px
NS = [2.0, 3.0, 4.0, 6.0]
ROTATIONS = [-12.0, -4.0, 0.0, 7.0, 14.0]


def run_case(case):
    """Fit one image; return a flat dict of its decision, errors and reported uncertainty (SI)."""
    from pipeline.synth.tem_truth import coating_decision, evaluate_case

    n, px, snr, coat, s = case
    e = evaluate_case(n, px, 2.0, snr, ROTATIONS[s % 5], coat, seed=500 + s, orientation="up" if s % 2 else "down")
    ct = e["profile"].edge_model.get("coating_test") or {}
    rep = e["reported"]
    decision = coating_decision(e["profile"])
    decision = "neither" if decision == "single" else decision  # neither found nor flagged
    covered = abs(e["dn"]) <= max(0.1, 3.5 * rep["sigma_n"]) and e["force_err_max"] <= max(
        0.03, 3.5 * rep["sigma_force"]
    )
    edge_covered = e["rms_normal"] <= 3.5 * rep["edge_sd"]
    return dict(
        n=n,
        px=px,
        snr=snr,
        coat=coat,
        seed=s,
        decision=decision,
        gain=ct.get("dchi2", np.nan),
        rms=e["rms_normal"],
        dn=e["dn"],
        dF=e["force_err_max"],
        sigma_n=rep["sigma_n"],
        sigma_F=rep["sigma_force"],
        covered=covered,
        edge_covered=edge_covered,
        t=e["t_profile"],
    )


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--seeds", type=int, default=4, help="images per (regime, n, coating)")
    ap.add_argument("--jobs", type=int, default=2, help="worker processes")
    a = ap.parse_args(argv)
    cases = [
        (n, px, snr, coat, s) for coat in (1.5e-9, 0.0) for (px, snr) in REGIMES for n in NS for s in range(a.seeds)
    ]
    if a.jobs > 1:
        from multiprocessing import Pool

        with Pool(a.jobs) as pool:
            rows = pool.map(run_case, cases, chunksize=1)
    else:
        rows = [run_case(c) for c in cases]
    print(
        f"{'oxide':>5} {'px nm':>5} {'SNR':>4} {'n':>3} {'seed':>4} | {'decision':>8} {'gain':>7} | {'rms nm':>6} "
        f"{'dn':>6} {'sig_n':>5} {'dF %':>5} {'sigF %':>6} {'covered':>7} {'edge cov.':>9} {'t s':>5}"
    )
    for r in rows:
        print(
            f"{r['coat'] * 1e9:5.1f} {r['px'] * 1e9:5.2f} {r['snr']:4.0f} {r['n']:3.0f} {r['seed']:4d} | "
            f"{r['decision']:>8} {r['gain']:7.1f} | {r['rms'] * 1e9:6.2f} {r['dn']:+6.3f} {r['sigma_n']:5.3f} "
            f"{100 * r['dF']:5.1f} {100 * r['sigma_F']:6.1f} {str(r['covered']):>7} {str(r['edge_covered']):>9} "
            f"{r['t']:5.2f}"
        )
    print(
        f"\n{'oxide':>5} {'px nm':>5} {'SNR':>4} | {'images':>6} {'found':>5} {'flagged':>7} {'neither':>7} "
        f"{'covered':>7} {'edge cov.':>9} {'median rms nm':>13}"
    )
    for coat, regime in itertools.product((1.5e-9, 0.0), REGIMES + [None]):
        px, snr = regime or (None, None)
        sel = [r for r in rows if r["coat"] == coat and (px is None or (r["px"] == px and r["snr"] == snr))]
        count = lambda d: sum(r["decision"] == d for r in sel)  # noqa: E731
        label = "all" if px is None else f"{px * 1e9:5.2f} {snr:4.0f}"
        print(
            f"{coat * 1e9:5.1f} {label:>10} | {len(sel):6d} {count('found'):5d} {count('flagged'):7d} "
            f"{count('neither'):7d} {sum(r['covered'] for r in sel):7d} {sum(r['edge_covered'] for r in sel):9d} "
            f"{np.median([r['rms'] for r in sel]) * 1e9:13.2f}"
        )


if __name__ == "__main__":
    main()
