"""The issue-16 targets where the Cramér-Rao bound allows them, on the independent wave-optical grid.

    .venv/bin/python benchmarks/bench_tem_bound.py GRADES.csv [--seed0 S] [--fix KEY=VALUE ...]
        [--jobs 2] [--csv out.csv] [--bounds-csv bounds.csv]

GRADES.csv is the per-image CSV of ``bench_tem_independent.py`` run with the same N, --seed0 and
--fix (the images are drawn again from them, not read from the CSV).  For each image the bound of
its Beer-Lambert twin (``pipeline.synth.tem_wave_bound``: the same tip, field, absorption lengths,
PSF and dose, without fringes, coherence or read noise) is computed, and the grades are split
by it: "allowed" where an unbiased fit at the bound would meet |dn| <= 0.1 (or the rigid Dugdale
pull-off within 3 %, Eq. 12, h 1-6 nm) with 95 % probability.  Prints, per split and overall:
images, lost, the targets met, the median ratio of the error to the bound (1 = a fit at the
bound), and n and pull-off coverage.  --bounds-csv: reuse bounds computed before (the
Fisher computation is ~0.5-25 s per image, ~30 min for the three sets on 2 cores); the three sets'
are kept in ``benchmarks/data/`` (``tem_bounds_grid.csv``: seed0 0; ``tem_bounds_held_out.csv``:
--seed0 1000; ``tem_bounds_dlc.csv``: --seed0 3000 --fix layer=DLC), and
``tests/test_tem_wave_bound.py`` recomputes one image of each against them, so a change of the
simulator or of the bound says when to compute them again.  Never fails on error or time.
"""

from __future__ import annotations

import argparse
import os
import sys

for _var in ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS"):
    os.environ.setdefault(_var, "1")  # one thread per process (set before numpy loads)

import numpy as np
import pandas as pd

sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))
from bench_tem_independent import _parse_fixed, case, map_images  # noqa: E402


def bound_one(job):
    """The twin's bound of grid image ``i`` (``pipeline.synth.tem_wave_bound.twin_bound``)."""
    from pipeline.synth.tem_wave_bound import twin_bound

    i, seed0, fixed = job
    return dict(i=i, **twin_bound(case(i, seed0, fixed)))


def _set_label(fixed):
    """The ``--fix`` keywords as the bounds file records them ("none" for none)."""
    return " ".join(f"{k}={v}" for k, v in sorted((fixed or {}).items())) or "none"


def bounds(n_images, seed0, fixed, jobs, path=None):
    """The bounds of images 0..n_images-1, read from ``path`` if it holds them all, else computed
    (and written there).  The file records the set (``seed0``, ``fix``): a file of another set, or one
    that does not say, is refused, not used (its images may be other images)."""
    if path and os.path.exists(path):
        b = pd.read_csv(path)
        if "seed0" not in b or "fix" not in b:
            raise SystemExit(f"{path} does not record its set (columns seed0, fix): compute the bounds again")
        if set(b.seed0) != {seed0} or set(b.fix) != {_set_label(fixed)}:
            raise SystemExit(
                f"{path} holds the bounds of --seed0 {sorted(set(b.seed0))} --fix {sorted(set(b.fix))!r}, "
                f"not of --seed0 {seed0} --fix {_set_label(fixed)!r}: give another --bounds-csv"
            )
        if set(range(n_images)) <= set(b.i):
            return b
    rows = []
    for r in map_images(bound_one, [(i, seed0, fixed) for i in range(n_images)], jobs):
        r.update(seed0=seed0, fix=_set_label(fixed))
        rows.append(r)
        print(
            f"  {r['i']:4d} CRB_n {r['crb_n']:.4f}  CRB pull-off {100 * r['crb_pulloff']:.2f} %  "
            f"({r['t_fisher']:.1f} s)",
            flush=True,
        )
    b = pd.DataFrame(rows)
    if path:
        b.to_csv(path, index=False)
    return b


def split_table(d):
    """Rows of the table: per split (the bound allows |dn| <= 0.1 / not; allows the 3 % pull-off / not)."""
    d = d.assign(
        dn_met=d.dn.abs() <= 0.1,
        f_met=d.pulloff_error.abs() <= 0.03,
        dn_ratio=d.dn.abs() / d.crb_n,
        f_ratio=d.pulloff_error.abs() / d.crb_pulloff,
    )
    out = []
    for name, m in (
        ("all", np.ones(len(d), bool)),
        ("bound allows |dn| <= 0.1", d.allowed_dn.to_numpy(bool)),
        ("bound does not", ~d.allowed_dn.to_numpy(bool)),
        ("bound allows pull-off 3 %", d.allowed_pulloff.to_numpy(bool)),
        ("bound does not ", ~d.allowed_pulloff.to_numpy(bool)),
    ):
        s = d[m]
        u = s[~s.lost.astype(bool)]
        out.append(
            dict(
                split=name,
                images=len(s),
                lost=int(s.lost.astype(bool).sum()),
                dn_met=u.dn_met.mean(),
                p_dn=u.p_dn.mean(),
                f_met=u.f_met.mean(),
                p_f=u.p_pulloff.mean(),
                dn_ratio=u.dn_ratio.median(),
                f_ratio=u.f_ratio.median(),
                sigma_ratio=(u.sigma_n / u.crb_n).median(),
                n_cov=u.n_covered.astype(bool).mean(),
                f_cov=u.pulloff_covered_mc.astype(bool).mean(),
            )
        )
    return pd.DataFrame(out)


def print_table(t):
    print(
        f"\n{'':27} {'images':>6} {'lost':>4} | {'|dn|<=0.1':>9} {'(at bound)':>10} {'|dn|/CRB':>8} "
        f"{'sigma_n/CRB':>11} | {'F<=3%':>6} {'(at bound)':>10} {'dF/CRB':>6} | {'n cov':>5} {'F cov':>5}"
    )
    for r in t.itertuples():
        print(
            f"{r.split:27} {r.images:6d} {r.lost:4d} | {100 * r.dn_met:8.0f}% {100 * r.p_dn:9.0f}% {r.dn_ratio:8.1f} "
            f"{r.sigma_ratio:11.1f} | {100 * r.f_met:5.0f}% {100 * r.p_f:9.0f}% {r.f_ratio:6.1f} | "
            f"{100 * r.n_cov:4.0f}% {100 * r.f_cov:4.0f}%"
        )
    print(
        "\n'(at bound)': the share an unbiased fit at the twin's bound would meet, averaged over the used images;"
        "\n|dn|/CRB, dF/CRB, sigma_n/CRB: medians over the used images (1 = at the bound); "
        "cov: n within 2 sigma_n, pull-off within the drawn 95.4 %"
    )


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("grades", help="per-image CSV of bench_tem_independent.py")
    ap.add_argument("--seed0", type=int, default=0)
    ap.add_argument("--fix", action="append", metavar="KEY=VALUE", help="as given to bench_tem_independent.py")
    ap.add_argument("--jobs", type=int, default=2)
    ap.add_argument("--bounds-csv", default=None, help="bounds computed before (or where to write them)")
    ap.add_argument("--csv", default=None, help="write grades and bounds joined to this CSV")
    a = ap.parse_args(argv)
    g = pd.read_csv(a.grades)
    if "seed" in g and set(g.seed - g.i) != {a.seed0}:
        raise SystemExit(f"{a.grades} holds the images of --seed0 {sorted(set(g.seed - g.i))}: give that --seed0")
    b = bounds(len(g), a.seed0, _parse_fixed(a.fix), a.jobs, a.bounds_csv)
    d = g.merge(b, on="i")
    print_table(split_table(d))
    if a.csv:
        d.to_csv(a.csv, index=False)


if __name__ == "__main__":
    main()
