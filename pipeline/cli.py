"""Command line for running one pipeline stage (what each Snakemake rule calls).

    python -m pipeline profiles  --tip-config config/tips/tipA.yaml --interval scan000 --out-h5 ... --out-png ...
    python -m pipeline fit       --tip-config ... --interval ... --profile-h5 ... --out-h5 ...
    python -m pipeline fit-figure --out-png ... FIT_H5...
    python -m pipeline forces    --tip-config ... --interval ... --out-h5 ... --out-png ...
    python -m pipeline inversion --tip-config ... [--workflow-config config/config.yaml] --fits DIR --forces DIR --out-h5 ...
    python -m pipeline adhesion-range --tip-config ... --inversion-h5 ... --out-h5 ... --report-csv ...
    python -m pipeline adhesion-figures --tip NAME --range-h5 ... --w-of-h-png ... --adhesion-map-png ...
    python -m pipeline summary   --out-csv results/summary.csv RANGE_H5...
    python -m pipeline rigid-laws-figure --out-png ...
    python -m pipeline validate  [--workflow-config config/config.yaml]
    python -m pipeline make-samples [--out data_samples] [--config-dir config/tips]
    python -m pipeline mechanics-figure --out fig7.png [--n 2,5] [--fast]
    python -m pipeline unlock-stale [--directory .]

Each stage loads and validates the tip YAML (units -> SI), then calls one function of the
science package.  Errors print one line naming the file and the reason and exit with
status 1.  `python -m pipeline <command> --help` lists a command's options.
"""  # noqa: E501 (the usage lines are the --help text)

from __future__ import annotations

import argparse
import sys
from pathlib import Path


def _interval(tip: dict, name: str) -> dict:
    for iv in tip["intervals"]:
        if iv["name"] == name:
            return iv
    from pipeline.config import ConfigError

    raise ConfigError(f"{tip['source']}: no interval named {name!r}")


def cmd_profiles(a):
    from pipeline.config import load_tip_config
    from pipeline.tem.stage import run_profiles

    tip = load_tip_config(a.tip_config)
    iv = _interval(tip, a.interval)
    run_profiles(
        iv["image_path"],
        a.out_h5,
        a.out_png,
        pixel_size=tip["tem"].get("pixel_size"),
        orientation=tip["tem"]["orientation"],
        profile_height=tip["tem"]["profile_height"],
        coating=tip["tem"]["coating"],
        refine=tip["tem"]["refine"],
        fringe_correction=tip["tem"]["fringe_correction"],
        defocus=iv.get("defocus", tip["tem"]["defocus"]),
        tip=tip["name"],
        interval=iv["name"],
    )


def cmd_fit(a):
    from pipeline.config import load_tip_config
    from pipeline.fits.stage import run_fit

    tip = load_tip_config(a.tip_config)
    iv = _interval(tip, a.interval)
    run_fit(
        a.profile_h5,
        a.out_h5,
        fit_height=tip["tem"]["fit_height"],
        S=tip["tem"]["S"],
        tip=tip["name"],
        interval=iv["name"],
    )


def cmd_fit_figure(a):
    from pipeline.fits.figures import plot_tip_fits

    plot_tip_fits(a.fit_h5, a.out_png, labels=[Path(p).stem for p in a.fit_h5])


def cmd_forces(a):
    from pipeline.config import load_tip_config
    from pipeline.forces.stage import run_forces

    tip = load_tip_config(a.tip_config)
    iv = _interval(tip, a.interval)
    run_forces(
        [str(p) for p in iv["curve_paths"]],
        a.out_h5,
        a.out_png,
        cantilever=tip["cantilever"],
        reader=tip["force_curves"],
        tip=tip["name"],
        interval=iv["name"],
        interval_cfg=iv,
    )


def cmd_inversion(a):
    from pipeline.config import inversion_settings, load_tip_config, load_workflow_config
    from pipeline.inversion.stage import run_inversion

    tip = load_tip_config(a.tip_config)
    settings = inversion_settings(load_workflow_config(a.workflow_config))  # h grid, laws, solver mode, Monte Carlo
    names = [iv["name"] for iv in tip["intervals"]]
    run_inversion(
        {n: str(Path(a.fits) / f"{n}.h5") for n in names},
        {n: str(Path(a.forces) / f"{n}.h5") for n in names},
        a.out_h5,
        intervals=[{"name": iv["name"], "scans": iv["scans"], "reference": iv["reference"]} for iv in tip["intervals"]],
        E_star=tip["materials"]["E_star"],
        u_E_star=tip["materials"]["u_E_star"],
        tip=tip["name"],
        **settings,
    )


def cmd_adhesion_range(a):
    from pipeline.adhesion_range.stage import run_adhesion_range
    from pipeline.config import load_tip_config

    tip = load_tip_config(a.tip_config)
    run_adhesion_range(a.inversion_h5, a.out_h5, a.report_csv, a.fig_dir, tip=tip["name"])


def cmd_adhesion_figures(a):
    from pipeline.adhesion_range.figures import plot_adhesion_map, plot_w_of_h

    plot_w_of_h(a.range_h5, a.w_of_h_png, tip=a.tip)
    plot_adhesion_map(a.range_h5, a.adhesion_map_png, tip=a.tip)


def cmd_summary(a):
    from pipeline.adhesion_range.report import write_summary

    write_summary({Path(p).parent.name: p for p in a.range_h5}, a.out_csv)


def cmd_rigid_laws_figure(a):
    from pipeline.mechanics.figures import plot_rigid_laws

    plot_rigid_laws(a.out_png)


def cmd_mechanics_figure(a):
    from pipeline.mechanics.figures import plot_fig7

    ns = tuple(float(v) for v in a.n.split(","))
    if not 1 <= len(ns) <= 4:
        raise ValueError(f"--n: give 1 to 4 comma-separated power indices (got {a.n!r})")
    plot_fig7(a.out, ns=ns, direct=not a.fast)


def cmd_validate(a):
    from pipeline.config import discover_tips, load_tip_config, load_workflow_config

    wf = load_workflow_config(a.workflow_config)
    for path in discover_tips(wf).values():
        tip = load_tip_config(path)
        print(f"{path}: ok ({len(tip['intervals'])} intervals, E* = {tip['materials']['E_star'] / 1e9:.4g} GPa)")


def cmd_make_samples(a):
    from pipeline.synth.wear_test import write_sample_bundle

    write_sample_bundle(a.out, config_dir=a.config_dir)


COMMAND_HELP = {  # one line each (argparse prints them beside the names)
    "profiles": "stage 1: TEM image -> apex profile z(r), figure",
    "fit": "stage 2: power-law fit z = r^n/(nQ) of one profile",
    "fit-figure": "a tip's profiles and fits in one figure (Fig. 3a/c)",
    "forces": "stage 3: force curves -> pull-off forces F_p, figure",
    "inversion": "stage 4: W_A(h) per interval and law, Monte Carlo",
    "adhesion-range": "stage 5: a tip's h and W_A, per-interval CSV",
    "adhesion-figures": "W_A(h) (Fig. 3b/d) and adhesion map (Fig. 5) of a tip",
    "summary": "summary CSV, one row per tip and traction law",
    "rigid-laws-figure": "rigid pull-off of the 4 traction laws vs n (Fig. 8)",
    "mechanics-figure": "pull-off vs h for the 4 laws, elastic and rigid (Fig. 7)",
    "validate": "check config.yaml and every tip YAML, no run",
    "make-samples": "write the seeded synthetic sample wear test",
    "unlock-stale": "remove a killed run's Snakemake lock (not a live one's)",
}


def cmd_unlock_stale(a):
    import subprocess

    from pipeline.workflow_support import stale_lock

    state, message = stale_lock(a.directory)
    if message:
        print(f"{message}{'; unlocking it' if state == 'stale' else ''}", file=sys.stderr)
    if state == "stale":
        proc = subprocess.run(
            [sys.executable, "-m", "snakemake", "--unlock", "--cores", "1"],
            cwd=a.directory,
            capture_output=True,
            text=True,
        )
        if proc.returncode != 0:
            raise RuntimeError(f"snakemake --unlock in {a.directory} failed: {proc.stderr.strip().splitlines()[-1:]}")


def build_parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(
        prog="python -m pipeline", description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    sub = p.add_subparsers(dest="cmd", required=True, metavar="<command>")
    _add_job_commands(sub)
    _add_tool_commands(sub)
    return p


def _command(sub, name, func, tip=True, interval=False):
    """A subcommand (help from COMMAND_HELP) with --tip-config and --interval where it takes them."""
    s = sub.add_parser(name, help=COMMAND_HELP[name], description=COMMAND_HELP[name])
    if tip:
        s.add_argument("--tip-config", required=True, help="the tip's YAML (config/tips/<tip>.yaml)")
    if interval:
        s.add_argument("--interval", required=True, help="interval name as in the tip YAML")
    s.set_defaults(func=func)
    return s


def _add_job_commands(sub):
    """The commands the workflow's jobs run (one per rule)."""
    s = _command(sub, "profiles", cmd_profiles, interval=True)
    s.add_argument("--out-h5", required=True, help="profile HDF5 to write")
    s.add_argument("--out-png", required=True, help="figure: the image with the detected edge and axis")

    s = _command(sub, "fit", cmd_fit, interval=True)
    s.add_argument("--profile-h5", required=True, help="the interval's profile HDF5 (stage 1)")
    s.add_argument("--out-h5", required=True, help="fit HDF5 to write")

    s = _command(sub, "fit-figure", cmd_fit_figure, tip=False)
    s.add_argument("--out-png", required=True, help="figure to write")
    s.add_argument("fit_h5", nargs="+", help="fit HDF5 files (stage 2), one per interval")

    s = _command(sub, "forces", cmd_forces, interval=True)
    s.add_argument("--out-h5", required=True, help="forces HDF5 to write")
    s.add_argument("--out-png", required=True, help="figure: retract curves, baselines and pull-offs")

    s = _command(sub, "inversion", cmd_inversion)
    s.add_argument(
        "--workflow-config",
        default="config/config.yaml",
        help="the workflow config whose h_grid, traction_laws, solver_mode and monte_carlo (samples, seed) "
        "the inversion uses (default: config/config.yaml)",
    )
    s.add_argument("--fits", required=True, help="folder of per-interval fit HDF5 files")
    s.add_argument("--forces", required=True, help="folder of per-interval forces HDF5 files")
    s.add_argument("--out-h5", required=True, help="inversion HDF5 to write")

    s = _command(sub, "adhesion-range", cmd_adhesion_range)
    s.add_argument("--inversion-h5", required=True, help="the tip's inversion HDF5 (stage 4)")
    s.add_argument("--out-h5", required=True, help="adhesion-range HDF5 to write")
    s.add_argument("--report-csv", required=True, help="per-interval CSV to write")
    s.add_argument("--fig-dir", help="also draw W_A_vs_h.png and adhesion_map.png here")

    s = _command(sub, "adhesion-figures", cmd_adhesion_figures, tip=False)
    s.add_argument("--tip", default="", help="tip name for the titles")
    s.add_argument("--range-h5", required=True, help="the tip's adhesion-range HDF5 (stage 5)")
    s.add_argument("--w-of-h-png", required=True, help="W_A(h) figure to write")
    s.add_argument("--adhesion-map-png", required=True, help="adhesion-map figure to write")

    s = _command(sub, "summary", cmd_summary, tip=False)
    s.add_argument("--out-csv", required=True, help="summary CSV to write")
    s.add_argument("range_h5", nargs="+", help="adhesion-range HDF5 files (stage 5), one per tip in <tip>/")

    s = _command(sub, "rigid-laws-figure", cmd_rigid_laws_figure, tip=False)
    s.add_argument("--out-png", required=True, help="figure to write")


def _add_tool_commands(sub):
    """The commands run by hand (figures of the mechanics, checks, samples, the lock)."""
    s = _command(sub, "mechanics-figure", cmd_mechanics_figure, tip=False)
    s.add_argument(
        "--out", required=True, help="PNG: pull-off vs h for the four laws, elastic and rigid (paper Fig. 7)"
    )
    s.add_argument("--n", default="2,5", help="comma-separated power indices (default 2,5)")
    s.add_argument("--fast", action="store_true", help="elastic values from the table instead of direct solves")

    s = _command(sub, "validate", cmd_validate, tip=False)
    s.add_argument("--workflow-config", default="config/config.yaml", help="default: config/config.yaml")

    s = _command(sub, "make-samples", cmd_make_samples, tip=False)
    s.add_argument("--out", default="data_samples", help="folder for the data (default: data_samples)")
    s.add_argument("--config-dir", default="config/tips", help="where to write the sample tips' YAMLs")

    s = _command(sub, "unlock-stale", cmd_unlock_stale, tip=False)
    s.add_argument("--directory", default=".", help="Snakemake's working directory (default: .)")


def main(argv=None) -> int:
    import logging

    args = build_parser().parse_args(argv)
    logging.basicConfig(level=logging.INFO, format="%(levelname)s %(name)s: %(message)s")
    try:
        args.func(args)
    except (ValueError, OSError, RuntimeError) as exc:  # our errors name the file and the reason
        print(f"error ({args.cmd}): {exc}", file=sys.stderr)
        return 1
    return 0
