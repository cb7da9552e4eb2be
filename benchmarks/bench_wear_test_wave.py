"""The whole workflow on wear tests it did not generate: h and W_A against the truth, and the
coverage of their 95 % intervals (issue 16: what the TEM stage's errors do to the answer).

Each tip (``pipeline.synth.calibration_study.draw_case``, kind ``rigid``: 4-6 intervals from the
paraboloidal reference to n 4-6, InvOLS drifting 3-10 % between intervals, 8 force curves per
interval from the independent instrument simulator) has its shape measured as the workflow
measures it: every interval is imaged by the wave-optical TEM simulator (``pipeline.synth.tem_wave``:
Fresnel fringes, partial coherence, MTF, saturation, a layer per tip (none / oxide / DLC, by seed),
particles, slight asymmetric wear; imaging drawn per session) and run through stages 1 and 2
(``pipeline.synth.wave_shapes``), then stages 3-5 as in ``bench_calibration_coverage``.
``--shapes drawn`` runs the same tips with the fits drawn around the truth as stage 2 reports
them on the sample images (that bench's rigid row): the difference is the TEM stage's share.
``--shapes wave_known`` images them as ``wave`` does and gives stage 1 the sign of every image's
defocus (``tem.defocus``), as an operator who knows it would.

Prints one line per tip (h and W_A errors, covered or not, interval half-width, intervals lost,
the worn intervals' n against the truth in units of their sigma_n) and a summary; writes the
rows to ``--csv``.  Never fails on time or accuracy.

    python benchmarks/bench_wear_test_wave.py [tips, default 24] [--seed0 1000] [--jobs 2]
        [--shapes wave|wave_known|drawn] [--csv out.csv] [--intervals-csv intervals.csv]
"""

from __future__ import annotations

import argparse
import csv
import logging
import os
import time
from multiprocessing import get_context

for _var in ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS"):
    os.environ.setdefault(_var, "1")

import numpy as np  # noqa: E402


def run_tip(args):
    """One tip: the calibration study's result with its shape records summarised."""
    seed, shapes = args
    logging.basicConfig(level=logging.ERROR)
    from pipeline.synth.calibration_study import draw_case, run_case

    t0 = time.perf_counter()
    r = run_case(draw_case(seed, "rigid"), shapes=shapes)
    recs = r.pop("shape_records", [])
    worn = [x for x in recs if not x["reference"] and not x["lost"]]
    z = [(x["n_fit"] - x["n_true"]) / x["sigma_n"] for x in worn if x["sigma_n"] > 0]
    ref = recs[0] if recs else {}
    r.update(
        t_s=time.perf_counter() - t0,
        layer=ref.get("layer", ""),
        lost_intervals=sum(x["lost"] for x in recs),
        ref_dn=ref.get("n_fit", np.nan) - 2.0 if ref else np.nan,
        ref_sigma_n=ref.get("sigma_n", np.nan),
        worn_max_abs_z=float(np.max(np.abs(z))) if z else np.nan,
        worn_used=len(z),
        worn_n_in_2sigma=int(np.sum(np.abs(z) <= 2.0)),
        lost_reasons=" | ".join(f"{x['interval']}: {x['lost_reason']}" for x in recs if x["lost"]),
        intervals_detail=[dict(x, seed=seed) for x in recs],
    )
    return r


def _line(r):
    if r.get("status") != "ok":
        lost = r.get("lost_reasons", "")
        return f"seed {r['seed']:5d} {r.get('layer', ''):5s} status {r.get('status')!r}  lost: {lost}"
    return (
        f"seed {r['seed']:5d} {r['layer']:5s} dh {100 * r['h_err']:+6.1f}% dW {100 * r['W_err']:+6.1f}% "
        f"h {'covered' if r['h_covered'] else 'MISSED '} W {'covered' if r['W_covered'] else 'MISSED '} "
        f"half-width {100 * r['h_rel_halfwidth']:5.1f}% chi2 {r['chi2']:6.2f}/{r['dof']} tau {100 * r['tau']:4.1f}% "
        f"lost {r['lost_intervals']} ref dn {r['ref_dn']:+.2f}+-{r['ref_sigma_n']:.2f} "
        f"worn max|dn/sigma| {r['worn_max_abs_z']:.1f} ({r['t_s']:.0f} s)"
    )


def summary(rows):
    _summary_line(rows, f"\n{len(rows)} tips")
    for layer in sorted({r.get("layer", "") for r in rows} - {""}):
        _summary_line(
            [r for r in rows if r.get("layer") == layer],
            f"  {layer}: {sum(r.get('layer') == layer for r in rows)} tips",
        )


def _summary_line(rows, head):
    ok = [r for r in rows if r.get("status") == "ok"]
    if not ok:
        print(f"{head}, none with an h")
        return
    dh = np.abs([r["h_err"] for r in ok])
    dw = np.abs([r["W_err"] for r in ok])
    print(
        f"{head}, {len(ok)} with an h; intervals lost {sum(r.get('lost_intervals', 0) for r in rows)}; "
        f"median / max |dh| {100 * np.median(dh):.1f} / {100 * dh.max():.1f} %, "
        f"|dW_A| {100 * np.median(dw):.1f} / {100 * dw.max():.1f} %; 95 % interval covers h in "
        f"{sum(r['h_covered'] for r in ok)} of {len(ok)} ({sum(not np.isfinite(r['h_rel_halfwidth']) for r in ok)} "
        f"of them open: the interval reaches the end of the h grid), W_A in {sum(r['W_covered'] for r in ok)}; "
        f"median half-width of h {100 * np.nanmedian([r['h_rel_halfwidth'] for r in ok]):.0f} %; "
        f"widened (tau > 0) {sum(r['tau'] > 0 for r in ok)}; worn intervals' n within 2 sigma_n: "
        f"{sum(r.get('worn_n_in_2sigma', 0) for r in rows)} of {sum(r.get('worn_used', 0) for r in rows)}"
    )


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("tips", nargs="?", type=int, default=24)
    ap.add_argument("--seed0", type=int, default=1000)
    ap.add_argument("--jobs", type=int, default=2)
    ap.add_argument("--shapes", choices=("wave", "wave_known", "drawn"), default="wave")
    ap.add_argument("--csv")
    ap.add_argument("--intervals-csv", help="one row per interval: the true and fitted n, sigma_n, imaging, flags")
    a = ap.parse_args(argv)
    work = [(a.seed0 + s, a.shapes) for s in range(a.tips)]
    rows = []
    with get_context("spawn").Pool(a.jobs) as pool:
        for r in pool.imap(run_tip, work):
            print(_line(r), flush=True)
            rows.append(r)
    summary(rows)
    details = [x for r in rows for x in r.pop("intervals_detail", [])]
    for path, table in ((a.csv, rows), (a.intervals_csv, details)):
        if path:
            keys = sorted({k for r in table for k in r})
            with open(path, "w", newline="") as f:
                w = csv.DictWriter(f, keys)
                w.writeheader()
                w.writerows(table)


if __name__ == "__main__":
    main()
