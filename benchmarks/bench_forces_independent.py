"""Forces stage on curves from an independent instrument simulator (pipeline.synth.afm_instrument).

The simulator shares no code or force law with the stage's own generator: rigid power-law tips
under a Dugdale law of range h (smooth detachment of a stiff lever), short-range van der Waals and
exponential laws, a Sneddon contact of finite stiffness, lever ringing, thermal noise, the ADC's
anti-alias filter, and instrument faults (laser interference, detector nonlinearity, drift, piezo
sensor noise).  Each scenario: intervals of 8 curves with 3 % pull-off scatter, InvOLS from the
interval's own contact slopes (the default), k given.  Prints per scenario: the interval mean F_p
error against the weighted mean of the used curves' truth (median and worst over seeds), the InvOLS error, how often
|error| <= 2 u (u: statistical + InvOLS), curves dropped (rejected or flagged as outliers), time per curve.

Usage: python benchmarks/bench_forces_independent.py [seeds per scenario, default 6] [--only NAME]
"""

from __future__ import annotations

import logging
import sys
import tempfile
import time
from pathlib import Path

import h5py
import numpy as np

from pipeline.synth.afm_instrument import READER, Instrument, Interaction, Lever, write_interval


def q_of(n, R, S=1.0):
    return S ** (n - 2.0) * R ** (n - 1.0)


def scenarios():
    """name -> (Interaction kwargs, Lever kwargs, Instrument kwargs); F_p in N."""
    out = {}
    for n in (2.0, 4.0, 6.0):
        for k in (0.1, 0.5, 2.0):
            F = 4e-9 * (1 + (n - 2))
            out[f"dugdale h4.5 n{n:g} k{k:g}"] = (
                dict(F_p=F, law="dugdale", ell=4.5e-9, n=n, Q=q_of(n, 15e-9)),
                dict(k=k, f0=20e3 * np.sqrt(k / 0.1)),
                {},
            )
    for k in (10.0, 40.0):
        out[f"dugdale h3 n3 k{k:g} (stiff)"] = (
            dict(F_p=20e-9, law="dugdale", ell=3e-9, n=3.0, Q=q_of(3, 15e-9)),
            dict(k=k, f0=300e3),
            dict(detector_noise=0.01e-9),
        )
    for k in (0.2, 1.0, 3.0):
        out[f"vdw a0 0.3 k{k:g}"] = (
            dict(F_p=6e-9, law="vdw", ell=0.3e-9, n=2.0, Q=15e-9),
            dict(k=k, f0=20e3 * np.sqrt(k / 0.1)),
            {},
        )
        out[f"exponential 0.8 n4 k{k:g}"] = (
            dict(F_p=8e-9, law="exponential", ell=0.8e-9, n=4.0, Q=q_of(4, 15e-9)),
            dict(k=k, f0=20e3 * np.sqrt(k / 0.1)),
            {},
        )
    base = (dict(F_p=6e-9, law="dugdale", ell=4.5e-9, n=3.0, Q=q_of(3, 15e-9)), dict(k=0.3, f0=30e3))
    out["faults: interference 0.3 nm"] = (*base, dict(interference=0.3e-9))
    out["faults: detector nonlinearity 2 %/100 nm"] = (base[0], {**base[1], "alpha": 2e5}, {})
    out["faults: drift 2 nm/s + walk"] = (*base, dict(drift_rate=2e-9, drift_walk=0.2e-9))
    out["faults: 1 kHz filter, 12 bit"] = (*base, dict(lowpass=1e3, adc_bits=12))
    out["faults: height sensor noise 0.1 nm"] = (*base, dict(z_noise=0.1e-9))
    out["faults: noisy (0.15 nm)"] = (*base, dict(detector_noise=0.15e-9))
    return out


def run_scenario(name, spec, seeds, workdir):
    from pipeline.forces.io import load_forces
    from pipeline.forces.stage import run_forces

    it_kw, lv_kw, in_kw = spec
    rows = []
    for s in range(seeds):
        rng = np.random.default_rng([s, 77])
        invols = 60e-9 * (1 + 0.05 * rng.standard_normal())
        lever = Lever(invols=invols, **lv_kw)
        inst = Instrument(offset_V=float(rng.normal(0, 0.2)), tilt=float(rng.normal(0, 2e5)), **in_kw)
        folder = Path(workdir) / f"{abs(hash(name))}_{s}"
        t0 = time.perf_counter()
        paths, truths = write_interval(folder, Interaction(**it_kw), lever, inst, n_curves=8, scatter=0.03, seed=s)
        t_sim = time.perf_counter() - t0
        out = folder / "f.h5"
        t0 = time.perf_counter()
        try:
            run_forces(
                paths,
                out,
                folder / "f.png",
                cantilever={"spring_constant": lever.k, "base_dir": str(folder)},
                reader=dict(READER),
                tip="bench",
                interval=name,
            )
        except Exception as exc:  # noqa: BLE001 - the benchmark reports it
            rows.append({"fail": f"{type(exc).__name__}: {exc}"[:160]})
            continue
        t_run = time.perf_counter() - t0
        f = load_forces(out)
        with h5py.File(out) as h:  # the truth of the curves the mean is made of, with their weights
            w = h["curves/weight"][()]
        truth_F = float(np.sum(w * np.array([t["F_p"] for t in truths])))
        err = f["F_p_mean"] / truth_F - 1
        u_rel = np.hypot(f["F_p_sem"] / f["F_p_mean"], f["u_invols"] / f["invols"])
        rows.append(
            {
                "err": err,
                "u": u_rel,
                "inv_err": f["invols"] / invols - 1,
                "rej": 8 - f["n_curves"],
                "t": t_run / 8,
                "t_sim": t_sim / 8,
            }
        )
    return rows


def main(seeds=6, only=None):
    logging.basicConfig(level=logging.ERROR)
    print(
        f"{'scenario':42s} {'ok':>3s} {'med|dF|':>8s} {'max|dF|':>8s} {'mean dF':>8s} {'med|dInv|':>9s} "
        f"{'<=2u':>5s} {'drop':>4s} {'s/curve':>7s}"
    )
    with tempfile.TemporaryDirectory() as tmp:
        for name, spec in scenarios().items():
            if only and only not in name:
                continue
            rows = run_scenario(name, spec, seeds, tmp)
            ok = [r for r in rows if "err" in r]
            fails = [r["fail"] for r in rows if "fail" in r]
            if ok:
                e = np.array([r["err"] for r in ok])
                cov = np.mean([abs(r["err"]) <= 2 * r["u"] for r in ok])
                print(
                    f"{name:42s} {len(ok):3d} {100 * np.median(np.abs(e)):7.2f}% {100 * np.abs(e).max():7.2f}% "
                    f"{100 * e.mean():+7.2f}% {100 * np.median(np.abs([r['inv_err'] for r in ok])):8.2f}% "
                    f"{100 * cov:4.0f}% {sum(r['rej'] for r in ok):4d} {np.mean([r['t'] for r in ok]):7.3f}"
                )
            for fmsg in fails[:2]:
                print(f"    failed: {fmsg}")


if __name__ == "__main__":
    args = sys.argv[1:]
    only = None
    if "--only" in args:
        i = args.index("--only")
        only = args[i + 1]
        args = args[:i] + args[i + 2 :]
    main(int(args[0]) if args else 6, only)
