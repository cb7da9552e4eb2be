"""Benchmark of the elastic contact solver (pipeline.mechanics.elastic_contact) and its fast path.

Run:  OMP_NUM_THREADS=1 .venv/bin/python benchmarks/bench_elastic_contact.py [--quick]
Prints tables; never fails on time (targets are reported, not asserted).

1. Direct solve, Dugdale law, against the M-D-n solution (the exact answer for that law):
   run time, grid size and error per grid level over n 2-20, Lambda 0.01-30.
   Target (issue #21): one pull-off <= 1 s at <= 0.5 % error.
2. Direct solve of L-J, Tri1, Tri2: run time at the default level and the change to level 4.
3. Fast path (table of y = log(P~_law / P~_MDn)): evaluations per second of the vectorised
   forward call and error against the direct solve at random off-node points.
   Target: >= 1e5 evaluations/s at <= 0.5 %.
"""

from __future__ import annotations

import argparse
import sys
import time

import numpy as np

import pipeline.mechanics as M
from pipeline.mechanics import elastic_tables as T
from pipeline.mechanics.elastic_contact import elastic_pulloff
from pipeline.mechanics.mdn import pulloff_mdn_exact


def _cases(quick):
    ns = (2.0, 5.0, 20.0) if quick else (2.0, 3.0, 5.0, 10.0, 20.0)
    lams = (0.01, 0.3, 3.0, 30.0) if quick else (0.01, 0.1, 0.3, 1.0, 3.0, 10.0, 30.0)
    return [(n, lam) for n in ns for lam in lams]


def _timed(fn):
    t = time.perf_counter()
    out = fn()
    return out, time.perf_counter() - t


def dugdale_table(quick):
    levels = (1.0, 2.0, 4.0) if quick else (1.0, 1.5, 2.0, 3.0, 4.0)
    print("\n1. Direct solve, Dugdale law, against M-D-n (exact), n 2-20 x Lambda 0.01-30")
    print(
        f"{'level':>6}{'cases':>7}{'nodes (median)':>16}{'time median':>13}"
        f"{'time max':>10}{'err median':>12}{'err max':>10}"
    )
    print("-" * 74)
    verdict = ""
    for lev in levels:
        ts, errs, nodes = [], [], []
        for n, lam in _cases(quick):
            r, t = _timed(lambda: elastic_pulloff(n, lam, "dugdale", level=lev))
            ts.append(t)
            nodes.append(r.nodes)
            errs.append(abs(r.pulloff_nd / float(pulloff_mdn_exact(n, lam)) - 1.0))
        print(
            f"{lev:>6g}{len(ts):>7}{np.median(nodes):>16.0f}{np.median(ts):>11.3f} s{max(ts):>8.2f} s"
            f"{np.median(errs):>11.2e}{max(errs):>10.2e}"
        )
        if lev == 2.0:
            ok = max(ts) <= 1.0 and max(errs) <= 5e-3
            verdict = (
                f"default level 2: every pull-off <= {max(ts):.2f} s at <= {100 * max(errs):.2f} % "
                f"(target <= 1 s at <= 0.5 %) [{'OK' if ok else 'MISS'}]"
            )
    print(verdict)
    # the error estimate (level/2 re-solve) against the true error, default level
    est = [(elastic_pulloff(n, lam, "dugdale", estimate_error=True), n, lam) for n, lam in _cases(quick)]
    ratio = [
        abs(r.pulloff_nd / float(pulloff_mdn_exact(n, lam)) - 1) / max(r.error_estimate, 1e-12) for r, n, lam in est
    ]
    print(
        f"error estimate (level 2 vs level 1): true error / estimate median {np.median(ratio):.2f}, "
        f"max {max(ratio):.2f}"
    )


def other_laws_table(quick):
    print("\n2. Direct solve, L-J / Tri1 / Tri2 (no exact reference): time at level 2 and change to level 4")
    print(f"{'law':>6}{'cases':>7}{'time median':>13}{'time max':>10}{'|L2-L4| median':>16}{'|L2-L4| max':>13}")
    print("-" * 65)
    for law in ("lj", "tri1", "tri2"):
        ts, d = [], []
        for n, lam in _cases(quick):
            r2, t = _timed(lambda: elastic_pulloff(n, lam, law, level=2.0))
            ts.append(t)
            d.append(abs(r2.ratio / elastic_pulloff(n, lam, law, level=4.0).ratio - 1.0))
        print(f"{law:>6}{len(ts):>7}{np.median(ts):>11.3f} s{max(ts):>8.2f} s{np.median(d):>16.2e}{max(d):>13.2e}")


def fast_path_table(quick):
    rng = np.random.default_rng(21)
    N = 10**6
    nn = rng.uniform(2, 20, N)
    ll = np.exp(rng.uniform(np.log(1e-4), np.log(1e3), N))
    k = 8 if quick else 30
    print(
        "\n3. Fast path (table): evaluations/s (10^6 random (n, Lambda)) and error vs the direct solve "
        f"({k} random off-node points per law, Lambda 1e-3-30)"
    )
    print(f"{'law':>6}{'evals/s fwd':>13}{'evals/s inverse':>17}{'err max':>10}{'err rms':>10}  target")
    print("-" * 76)
    Q = M.q_from_rs(nn[: 10**5], 25e-9, 1.0)
    E = np.full(10**5, 50e9)
    h = np.full(10**5, 0.5e-9)
    for law in ("lj", "tri1", "tri2"):
        _, t = _timed(lambda: M.pulloff_nd(nn, ll, potential=law, model="elastic"))
        F = M.pulloff_force(nn[: 10**5], Q, E, 0.2, h, potential=law, model="elastic")
        _, ti = _timed(lambda: M.work_of_adhesion(F, nn[: 10**5], Q, E, h, potential=law, model="elastic"))
        err = np.array(
            [
                T.table_error(
                    law,
                    float(np.exp(rng.uniform(np.log(2), np.log(20)))),
                    float(np.exp(rng.uniform(np.log(1e-3), np.log(30)))),
                )
                for _ in range(k)
            ]
        )
        ok = N / t >= 1e5 and np.max(np.abs(err)) <= 5e-3
        print(
            f"{law:>6}{N / t:>13.3g}{1e5 / ti:>17.3g}{np.max(np.abs(err)):>10.2e}{np.sqrt(np.mean(err**2)):>10.2e}"
            f"  >= 1e5/s at <= 0.5 % [{'OK' if ok else 'MISS'}]"
        )


def main(argv=None):
    ap = argparse.ArgumentParser()
    ap.add_argument("--quick", action="store_true", help="fewer cases and levels")
    args = ap.parse_args(argv)
    print(f"pipeline.mechanics.elastic_contact benchmark (python {sys.version.split()[0]}, numpy {np.__version__})")
    t0 = time.perf_counter()
    T.load_elastic_table()
    print(
        f"table load: {1e3 * (time.perf_counter() - t0):.0f} ms (built "
        f"in {float(T.load_elastic_table()['build_seconds']):.0f} s)"
    )
    dugdale_table(args.quick)
    other_laws_table(args.quick)
    fast_path_table(args.quick)


if __name__ == "__main__":
    main()
