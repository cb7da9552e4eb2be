"""Benchmark of pipeline.mechanics: speed and accuracy of every solver variant.

Run:  .venv/bin/python benchmarks/bench_mechanics.py [--quick]
Prints a table; never fails on time (targets are reported, not asserted).
Accuracy references: 40-digit mpmath M-D-n solve (tests/test_mechanics_mpmath.py) and
40-digit mpmath quadrature + golden-section maximisation for the rigid laws.
"""

from __future__ import annotations

import argparse
import importlib.util
import sys
import time
from pathlib import Path

import mpmath as mp
import numpy as np

import pipeline.mechanics as M
from pipeline.mechanics.mdn import pulloff_mdn_exact

ROOT = Path(__file__).resolve().parents[1]


def _load_mp_reference():
    spec = importlib.util.spec_from_file_location("mp_ref", ROOT / "tests" / "test_mechanics_mpmath.py")
    mod = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(mod)
    return mod.mp_pulloff


def mp_rigid_ratio(n, law):
    """40-digit rigid F_max(law)/F_Dugdale: int_0^inf sigma(D + w^(n/2)) dw maximised over D."""
    with mp.workdps(40):
        n = mp.mpf(n)
        z0 = 1 / mp.mpf("0.974")

        def sig(s):
            if law == "tri1":
                return 4 * s if s <= mp.mpf(1) / 2 else max(4 * (1 - s), 0)
            if law == "tri2":
                return s if s <= 1 else max(2 - s, 0)
            d = z0 + s
            return 8 / (3 * z0) * ((z0 / d) ** 3 - (z0 / d) ** 9)

        def F(D):
            f = lambda w: sig(D + w ** (n / 2))
            if law == "lj":
                return mp.quad(f, [0, 1, mp.inf])
            top = 1 if law == "tri1" else 2
            br = sorted(
                {b ** (2 / n) for b in (mp.mpf(1) / 2 - D, 1 - D, 2 - D) if 0 < b < top - D + 1e-30}
                | {0, (top - D) ** (2 / n)}
            )
            return mp.quad(f, br)

        lo, hi = mp.mpf(0), mp.mpf(1.5)
        g = (mp.sqrt(5) - 1) / 2
        x1, x2 = hi - g * (hi - lo), lo + g * (hi - lo)
        f1, f2 = F(x1), F(x2)
        for _ in range(70):
            if f1 > f2:
                hi, x2, f2 = x2, x1, f1
                x1 = hi - g * (hi - lo)
                f1 = F(x1)
            else:
                lo, x1, f1 = x1, x2, f2
                x2 = lo + g * (hi - lo)
                f2 = F(x2)
        return max(f1, f2, F(mp.mpf(0)))


def timeit(fn, repeat=3):
    best = np.inf
    for _ in range(repeat):
        t = time.perf_counter()
        fn()
        best = min(best, time.perf_counter() - t)
    return best


def main(argv=None):
    ap = argparse.ArgumentParser()
    ap.add_argument("--quick", action="store_true", help="fewer mpmath reference points")
    args = ap.parse_args(argv)
    rng = np.random.default_rng(2024)

    t0 = time.perf_counter()
    M.build_table()
    from pipeline.mechanics.tables import table_spline

    table_spline()
    t_table = time.perf_counter() - t0

    mp_pulloff = _load_mp_reference()
    k = 8 if args.quick else 24
    n_ref = np.concatenate([[2.0, 20.0], rng.uniform(2, 20, k - 2)])
    l_ref = np.exp(np.concatenate([[np.log(1e-6), np.log(1e6)], rng.uniform(np.log(1e-6), np.log(1e6), k - 2)]))
    t0 = time.perf_counter()
    ref = np.array([float(mp_pulloff(a, b)) for a, b in zip(n_ref, l_ref)])
    t_ref = time.perf_counter() - t0

    rows = []
    # M-D-n exact and fast
    N = 2000
    nn, ll = rng.uniform(2, 20, N), np.exp(rng.uniform(np.log(1e-6), np.log(1e6), N))
    t_exact = timeit(lambda: M.pulloff_nd(nn, ll, exact=True), 1) / N
    err_exact = np.max(np.abs(M.pulloff_nd(n_ref, l_ref, exact=True) / ref - 1))
    rows.append(("M-D-n exact (direct solve)", t_exact, err_exact, f"mpmath, {k} pts"))
    N = 10**6
    nn6, ll6 = rng.uniform(2, 20, N), np.exp(rng.uniform(np.log(1e-6), np.log(1e6), N))
    t_fast = timeit(lambda: M.pulloff_nd(nn6, ll6)) / N
    err_fast = np.max(np.abs(M.pulloff_nd(n_ref, l_ref) / ref - 1))
    sub = slice(0, 4000)
    err_fast_dense = np.max(np.abs(M.pulloff_nd(nn6[sub], ll6[sub]) / pulloff_mdn_exact(nn6[sub], ll6[sub]) - 1))
    rows.append(("M-D-n fast (quintic table)", t_fast, max(err_fast, err_fast_dense), "mpmath + 4000 exact pts"))
    t_auto = timeit(lambda: M.pulloff_nd(nn6, ll6, model="auto")) / N
    rows.append(("auto (rigid | M-D-n fast)", t_auto, np.nan, "model switch"))
    # rigid closed forms
    n_rig = (
        np.array([2.0, 3.0, 5.0, 10.0, 20.0])
        if args.quick
        else np.array([2.0, 2.5, 3.0, 4.0, 5.0, 7.0, 10.0, 15.0, 20.0])
    )
    for law in ("dugdale", "tri1", "tri2", "lj"):
        t_r = timeit(lambda: M.pulloff_nd(nn6, ll6, potential=law, model="rigid")) / N
        if law == "dugdale":
            err = np.max(
                np.abs(
                    M.pulloff_nd(n_rig, 0.3, model="rigid") / (n_rig ** (2 / n_rig) * 0.3 ** ((n_rig - 2) / n_rig)) - 1
                )
            )
            note = "Eq. 12 identity"
        else:
            r_ref = np.array([float(mp_rigid_ratio(v, law)) for v in n_rig])
            err = np.max(np.abs(M.rigid_pulloff_ratio(n_rig, law) / r_ref - 1))
            note = f"mpmath quad, n={n_rig.min():g}..{n_rig.max():g}"
        rows.append((f"rigid closed form, {law}", t_r, err, note))

    # W_A(h) curve and Monte-Carlo inversion
    h = np.geomspace(0.05e-9, 50e-9, 200)
    Q = M.q_from_rs(4.0, 30e-9, 1.0)
    F = M.pulloff_force(4.0, Q, 150e9, 0.1, 1e-9)
    t_curve = {
        m: timeit(lambda m=m: M.work_of_adhesion(F, 4.0, Q, 150e9, h, model=m), 20) for m in ("mdn", "rigid", "auto")
    }
    t_curve_exact = timeit(lambda: M.work_of_adhesion(F, 4.0, Q, 150e9, h, exact=True), 1)
    W_true = M.work_of_adhesion(F, 4.0, Q, 150e9, h, exact=True)
    err_curve = np.max(np.abs(M.work_of_adhesion(F, 4.0, Q, 150e9, h) / W_true - 1))

    Nmc = 10**6
    n_mc = rng.uniform(2, 8, Nmc)
    Q_mc = M.q_from_rs(n_mc, rng.normal(30e-9, 3e-9, Nmc).clip(5e-9), 1.0)
    E_mc = rng.normal(150e9, 10e9, Nmc)
    F_mc = rng.normal(20e-9, 2e-9, Nmc).clip(1e-9)
    t_mc = timeit(lambda: M.work_of_adhesion(F_mc, n_mc, Q_mc, E_mc, 2e-9), 1)
    W_mc = M.work_of_adhesion(F_mc[:2000], n_mc[:2000], Q_mc[:2000], E_mc[:2000], 2e-9)
    W_mc_exact = M.work_of_adhesion(F_mc[:2000], n_mc[:2000], Q_mc[:2000], E_mc[:2000], 2e-9, exact=True)
    err_mc = np.max(np.abs(W_mc / W_mc_exact - 1))

    print(f"\npipeline.mechanics benchmark (python {sys.version.split()[0]}, numpy {np.__version__})")
    print(f"table build/load: {t_table * 1e3:.0f} ms; mpmath reference ({k} M-D-n points): {t_ref:.1f} s\n")
    print(f"{'variant':<32}{'time / eval':>14}{'evals / s':>12}{'max rel err':>14}  reference")
    print("-" * 96)
    for name, t, err, note in rows:
        e = "   n/a" if np.isnan(err) else f"{err:.2e}"
        print(f"{name:<32}{t * 1e6:>11.3f} us{1 / t:>12.3g}{e:>14}  {note}")
    print("-" * 96)
    ok = lambda c: "OK " if c else "MISS"
    print(
        f"fast-path pull-off evaluations/s: {1 / t_fast:.3g}  (target >= 1e6 at <= 1e-6)  "
        f"[{ok(1 / t_fast >= 1e6 and max(err_fast, err_fast_dense) <= 1e-6)}]"
    )
    for m in ("mdn", "rigid", "auto"):
        print(
            f"200-point W_A(h) curve, {m:<5} fast: {t_curve[m] * 1e3:7.3f} "
            f"ms  (target <= 5 ms)  [{ok(t_curve[m] <= 5e-3)}]"
        )
    print(
        f"200-point W_A(h) curve, mdn exact: {t_curve_exact * 1e3:7.1f} ms; fast vs exact max rel err {err_curve:.2e}"
    )
    print(
        f"1e6 Monte-Carlo inversions (random n, Q, F_p, E*; one h), mdn fast: {t_mc:.2f} s  "
        f"(target <= 10 s)  [{ok(t_mc <= 10)}]; rel err vs exact (2000 pts) {err_mc:.2e}"
    )


if __name__ == "__main__":
    main()
