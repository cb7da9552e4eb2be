"""Cramér-Rao lower bounds for the power index n on the synthetic TEM accuracy grid.

    .venv/bin/python benchmarks/bench_profiles_crb.py [--quick] [--px 0.5 ...] [--n 2 ...] [--convergence]

For the grid of the slow accuracy test (tests/test_tem_profiles.py::GRID, finite
SNR, rotation 0): n in {2, 3, 4, 6} with R from ``pipeline.synth.tem_truth.TIP_SHAPES``
(Q = R^(n-1)), pixel size {0.1, 0.25, 0.5} nm, blur {0.5, 2} px, edge SNR {10, 5},
coating {0, 1.5, 15} nm, image side as in ``evaluate_case``.  One row per case:
CRB of n with the shank above the 6 nm window and all nuisances free, the
"optimistic" CRB (only n, log Q, apex row/col and rotation free), the probability
P(|dn| <= 0.1) of a Gaussian with the full-nuisance CRB as sd, the largest over
h = 1..6 nm of the CRB of the relative rigid Dugdale pull-off (Eq. 12) error, and
the time of the Fisher computation.  The Fisher matrix scales exactly with
SNR^2 (Poisson, fixed geometry), so it is computed once per case at SNR 5 and
the SNR 10 row reuses it (same time shown).  --convergence: CRB_n of three cases
for several finite-difference steps and supersample 5 vs 9.  --efficiency SEEDS: the
fit's scatter against the stored bounds (tests/data/crb_grid.csv) at SNR 10, blur 0.5 px,
n 2 and 6, uncoated and 1.5 nm oxide, over SEEDS images (rotations and orientations varied).
"""

from __future__ import annotations

import argparse
import itertools
import math
import os
import time

for _var in ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS"):
    os.environ.setdefault(_var, "1")  # the run-time target is for one core (set before numpy loads)

import numpy as np

from pipeline.synth.tem_fisher import crb_summary, fisher_information
from pipeline.synth.tem_truth import TIP_SHAPES

NS = [2.0, 3.0, 4.0, 6.0]
PXS = [0.1e-9, 0.25e-9, 0.5e-9]
BLURS = [0.5, 2.0]
SNRS = [10.0, 5.0]
COATINGS = [0.0, 1.5e-9, 15e-9]
HEIGHTS = np.arange(1, 7) * 1e-9


def case_fisher(n, px, blur, coat, seed=0, **kw):
    """Fisher information of one grid case at SNR 5 (image side as in ``evaluate_case``)."""
    R = TIP_SHAPES[int(round(n))]
    side = int(np.clip(np.ceil(95e-9 / px / 32) * 32, 384, 1024))
    return fisher_information(
        n,
        R ** (n - 1),
        px,
        (side, side),
        blur_sigma_px=blur,
        edge_snr=5.0,
        coating_thickness=coat,
        rotation_deg=0.0,
        seed=seed,
        **kw,
    )


def p_within(sd, tol=0.1):
    """P(|dn| <= tol) for dn ~ N(0, sd^2)."""
    return math.erf(tol / (math.sqrt(2.0) * sd))


def fit_efficiency(n, px, blur, snr, coat, crb, seeds):
    """' | median sigma_n / CRB, RMS(n_fit - n) / CRB' of the pipeline's fit over noise seeds."""
    from pipeline.synth.tem_truth import evaluate_case

    out = [evaluate_case(n, px, blur, snr, 0.0, coat, seed=1000 + k) for k in range(seeds)]
    sn = np.median([o["sigma_n"] for o in out])
    rms = math.sqrt(np.mean([o["dn"] ** 2 for o in out]))
    return f" | {sn / crb:11.2f} {rms / crb:12.2f}"


def efficiency_table(seeds, csv="tests/data/crb_grid.csv"):
    """RMS, SD and mean of n_fit - n and the median reported sigma_n, in units of the stored
    CRB, over ``seeds`` images per case (SNR 10, blur 0.5 px; n 2, 6; no coating / 1.5 nm oxide);
    RMS/sigma_n > 1 is a reported uncertainty smaller than the real scatter."""
    import pandas as pd

    from pipeline.synth.tem_truth import evaluate_case

    t = pd.read_csv(csv)
    print(f"fit efficiency over {seeds} images per case (SNR 10, blur 0.5 px; 1 = at the bound)")
    print(
        f"{'px nm':>5} {'coat':>4} {'n':>2} | {'CRB_n':>6} {'RMS/CRB':>7} {'SD/CRB':>6} {'sigma_n/CRB':>11} "
        f"{'mean dn':>7} {'RMS/sigma_n':>11}"
    )
    for n, px, coat in itertools.product([2.0, 6.0], PXS, [0.0, 1.5e-9]):
        row = t[
            (t.n == n)
            & np.isclose(t.pixel_size_nm, px * 1e9)
            & (t.blur_px == 0.5)
            & np.isclose(t.coating_nm, coat * 1e9)
            & (t.edge_snr == 10.0)
        ].iloc[0]
        out = [
            evaluate_case(
                n,
                px,
                0.5,
                10.0,
                [4.7, -3.1, 9.0, -11.0][k % 4],
                coat,
                seed=700 + k,
                orientation="up" if k % 2 else "down",
            )
            for k in range(seeds)
        ]
        dn = np.array([o["dn"] for o in out])
        sn = np.median([o["sigma_n"] for o in out])
        crb = row.crb_n
        print(
            f"{px * 1e9:5.2f} {coat * 1e9:4.1f} {n:2.0f} | {crb:6.4f} {np.sqrt(np.mean(dn**2)) / crb:7.2f} "
            f"{dn.std(ddof=1) / crb:6.2f} {sn / crb:11.2f} {dn.mean():+7.3f} {np.sqrt(np.mean(dn**2)) / sn:11.2f}",
            flush=True,
        )


def convergence(n=2.0, px=0.5e-9, blur=0.5, coat=0.0):
    print(f"convergence, n {n:g}, px {px * 1e9:g} nm, blur {blur:g} px, coating {coat * 1e9:g} nm, SNR 5")
    print(f"{'step px':>7} {'ss':>3} | {'CRB_n':>7} {'CRB_opt':>7} {'dF%':>6} {'t s':>5}")
    ref = None
    for step, ss in [(0.3, 5), (0.2, 5), (0.5, 5), (0.3, 9), (0.2, 9)]:
        res = case_fisher(n, px, blur, coat, step_px=step, supersample=ss)
        s = crb_summary(res, HEIGHTS)
        ref = ref or s["crb_n"]
        print(
            f"{res.info['steps']['apex_px']:7.3f} {ss:3d} | {s['crb_n']:7.4f} {s['crb_n_opt']:7.4f} "
            f"{100 * s['crb_dugdale'].max():6.2f} {res.elapsed:5.1f}   ({100 * (s['crb_n'] / ref - 1):+.2f} % "
            f"vs first row)",
            flush=True,
        )


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--quick", action="store_true", help="0.5 nm pixels, n = 2 and 6, no 1.5 nm coating")
    ap.add_argument("--px", type=float, nargs="+", help="pixel sizes (nm) to run")
    ap.add_argument("--n", type=float, nargs="+", help="power indices to run")
    ap.add_argument(
        "--fit",
        type=int,
        default=0,
        metavar="SEEDS",
        help="also run the profile extraction + fit on SEEDS noise seeds per row and print its "
        "sigma_n and the RMS of n_fit - n in units of the CRB (efficiency: 1 = at the bound)",
    )
    ap.add_argument("--csv", help="also write the rows to this CSV (tests/data/crb_grid.csv is made this way)")
    ap.add_argument(
        "--convergence",
        action="store_true",
        help="step / supersample convergence on three cases "
        "(0.5 nm px / n 2, 0.1 nm px / n 6, 0.25 nm px / 15 nm coating)",
    )
    ap.add_argument(
        "--efficiency",
        type=int,
        default=0,
        metavar="SEEDS",
        help="the fit's scatter against the stored bounds (no Fisher computation)",
    )
    a = ap.parse_args(argv)
    if a.efficiency:
        return efficiency_table(a.efficiency)
    if a.convergence:
        for case in [(2.0, 0.5e-9, 0.5, 0.0), (6.0, 0.1e-9, 2.0, 1.5e-9), (2.0, 0.25e-9, 0.5, 15e-9)]:
            convergence(*case)
        return None
    pxs = [p * 1e-9 for p in a.px] if a.px else ([0.5e-9] if a.quick else PXS)
    ns = a.n or ([2.0, 6.0] if a.quick else NS)
    coats = [0.0, 15e-9] if a.quick else COATINGS
    print(
        f"{'px nm':>5} {'blur':>4} {'coat':>4} {'n':>2} {'R nm':>4} {'SNR':>3} | {'CRB_n':>6} {'CRB_opt':>7} "
        f"{'P(|dn|<=.1)':>11} {'CRB dF% max_h':>13} {'opt dF%':>7} | {'P':>3} {'t s':>5}"
        + (" | sigma_n/CRB rms(dn)/CRB" if a.fit else "")
    )
    rows, table = [], []
    for i, (px, blur, coat, n) in enumerate(itertools.product(pxs, BLURS, coats, ns)):
        t0 = time.perf_counter()
        res = case_fisher(n, px, blur, coat, seed=i)
        dt = time.perf_counter() - t0
        for snr in SNRS:
            s = crb_summary(res, HEIGHTS, edge_snr=snr)
            p = p_within(s["crb_n"])
            rows.append((snr, s["crb_n"], p, s["crb_dugdale"].max()))
            table.append(
                {
                    "n": n,
                    "pixel_size_nm": px * 1e9,
                    "blur_px": blur,
                    "coating_nm": coat * 1e9,
                    "edge_snr": snr,
                    "crb_n": s["crb_n"],
                    "crb_n_optimistic": s["crb_n_opt"],
                    "crb_dugdale_max_percent": 100 * s["crb_dugdale"].max(),
                }
            )
            R = TIP_SHAPES[int(n)]
            print(
                f"{px * 1e9:5.2f} {blur:4.1f} {coat * 1e9:4.1f} {n:2.0f} {R * 1e9:4.0f} {snr:3.0f} | "
                f"{s['crb_n']:6.3f} {s['crb_n_opt']:7.3f} {p:11.3f} {100 * s['crb_dugdale'].max():13.2f} "
                f"{100 * s['crb_dugdale_opt'].max():7.2f} | {len(res.names):3d} {dt:5.1f}"
                + (fit_efficiency(n, px, blur, snr, coat, s["crb_n"], a.fit) if a.fit else ""),
                flush=True,
            )
    if a.csv:
        import pandas as pd

        pd.DataFrame(table).to_csv(a.csv, index=False, float_format="%.6g")
    r = np.array(rows)
    for snr in SNRS:
        m = r[:, 0] == snr
        print(
            f"SNR {snr:g}: {m.sum()} cases, CRB_n > 0.1 in {np.sum(r[m, 1] > 0.1)}, P(|dn|<=0.1) < 0.95 in "
            f"{np.sum(r[m, 2] < 0.95)}, CRB of the Dugdale error > 3 % in {np.sum(r[m, 3] > 0.03)}"
        )


if __name__ == "__main__":
    main()
