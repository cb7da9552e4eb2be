"""Per-interval InvOLS (issue 15): error and coverage of h and W_A over many synthetic wear tests.

Each case (``pipeline.synth.calibration_study``): 4-6 intervals, InvOLS drifting 3-10 % between
intervals (chip remounted for every TEM session), 8 curves per interval with 2-5 % scatter, a
tip YAML with k but no InvOLS; stages 3-5 run as in the workflow (Dugdale law, M-D-n where the
adhesion map needs it).  Kinds: rigid, elastic (transition regime), wrong_reference (the
reference's forces 10 % off) and hidden_bias (one worn interval's forces 10 % off); the
``/oracle`` rows are the same rigid and elastic cases with a perfect calibration.

Prints per kind and per model of inconsistent intervals (random effects, the default, and Birge
scaling): median and worst |h error|, |W_A error|, worst interval F_p error (as stage 4 uses it),
coverage of the 95 % intervals of h and W_A, how often the intervals were widened, and the run
time.  The force curves come from the independent instrument simulator
(``pipeline.synth.afm_instrument``; ``--generator lorentzian`` for the stage's own).  Usage:

    python benchmarks/bench_calibration_coverage.py [seeds per kind, default 40] [--kinds rigid,hidden_bias]
        [--generator lorentzian]
"""

from __future__ import annotations

import logging
import sys
import time

import numpy as np

from pipeline.synth.calibration_study import draw_case, run_case

KINDS = ("rigid", "elastic", "wrong_reference", "hidden_bias", "rigid/oracle", "elastic/oracle")


def main(n_seeds=40, generator="instrument", kinds=KINDS):
    """``kind/oracle``: the same cases with every interval's true InvOLS given (a perfect
    calibration): what is left is the error of the shape fits and of the pull-off scatter."""
    rows = {}
    for kind in kinds:
        t0 = time.perf_counter()
        base, _, oracle = kind.partition("/")
        rows[kind] = [
            run_case(draw_case(1000 + s, base), oracle_invols=bool(oracle), generator=generator) for s in range(n_seeds)
        ]
        rows[kind + "_t"] = time.perf_counter() - t0
    head = (
        f"{'kind':22s} {'cases':>5s} {'med|dh|':>8s} {'max|dh|':>8s} {'med|dW|':>8s} {'max|dW|':>8s} "
        f"{'max|dF|':>8s} {'cov h':>6s} {'cov W':>6s} {'widened':>8s} {'med hw':>7s} {'L/Lb>1':>6s} {'s/case':>7s}"
    )
    print(head)
    for kind in kinds:
        for _model, pre in (("random effects", ""), ("Birge", "birge_")):
            r = [x for x in rows[kind] if x[pre + "status"] == "ok"]
            if not r:
                continue
            dh = np.abs([x[pre + "h_err"] for x in r])
            dw = np.abs([x[pre + "W_err"] for x in r])
            widened = [(x["tau"] > 0) if not pre else (x["birge"] > 1) for x in r]
            name = f"{kind} ({'RE' if not pre else 'Birge'})"
            print(
                f"{name:22s} {len(r):5d} {100 * np.median(dh):7.2f}% "
                f"{100 * dh.max():7.2f}% {100 * np.median(dw):7.2f}% "
                f"{100 * dw.max():7.2f}% {100 * max(x['fp_err_max'] for x in r):7.2f}% "
                f"{100 * np.mean([x[pre + 'h_covered'] for x in r]):5.0f}% "
                f"{100 * np.mean([x[pre + 'W_covered'] for x in r]):5.0f}% "
                f"{100 * np.mean(widened):7.0f}% {100 * np.nanmedian([x[pre + 'h_rel_halfwidth'] for x in r]):6.1f}% "
                f"{np.mean([x['lambda_over_boundary'] > 1 for x in r]):6.2f} {rows[kind + '_t'] / len(rows[kind]):7.2f}"
            )
            for x in [x for x in r if not x[pre + "h_covered"]][:3]:
                print(
                    f"    missed: seed {x['seed']} dh {100 * x[pre + 'h_err']:+.1f}% dW {100 * x[pre + 'W_err']:+.1f}% "
                    f"chi2 {x[pre + 'chi2']:.2f}/{x[pre + 'dof']} tau {100 * x['tau']:.1f}% birge {x['birge']:.2f} "
                    f"half-width {100 * x[pre + 'h_rel_halfwidth']:.1f}%"
                )


if __name__ == "__main__":
    logging.basicConfig(level=logging.ERROR)  # the per-interval warnings are in the HDF5 files
    args = [a for a in sys.argv[1:] if not a.startswith("--")]
    gen = (
        "lorentzian"
        if "--generator" in sys.argv and sys.argv[sys.argv.index("--generator") + 1] == "lorentzian"
        else "instrument"
    )
    args = [a for a in args if a != "lorentzian"]
    kinds = tuple(sys.argv[sys.argv.index("--kinds") + 1].split(",")) if "--kinds" in sys.argv else KINDS
    args = [a for a in args if not ("--kinds" in sys.argv and a == sys.argv[sys.argv.index("--kinds") + 1])]
    main(int(args[0]) if args else 40, gen, kinds)
