# Shared setup: validate every config before any job runs, list tips and intervals.
import json
from pathlib import Path

import yaml
from snakemake.exceptions import WorkflowError
from snakemake.utils import validate

import pipeline.config as pc
from pipeline.code_version import code_version
from pipeline.workflow_support import config_file_for_jobs, use_this_interpreter_for_jobs

# Validate everything before any job runs: our loader first (one clear line per problem,
# naming file and key; units -> SI), then Snakemake's own schema check (fills defaults).
try:
    WF = pc.load_workflow_config(config)
    TIP_FILES = {name: str(path) for name, path in pc.discover_tips(WF).items()}
    TIPS = {}
    for _name, _path in TIP_FILES.items():
        TIPS[_name] = pc.load_tip_config(_path)  # concise errors naming file and key
        with open(_path) as _fh:
            validate(yaml.safe_load(_fh), "../pipeline/schemas/tip.schema.yaml")
    # the inversion reads its settings (h grid, laws, solver mode, Monte Carlo) from this file itself
    WORKFLOW_CONFIG = config_file_for_jobs(workflow.configfiles, WF, pc.INVERSION_KEYS)
except pc.ConfigError as exc:
    raise WorkflowError(f"Configuration error: {exc}") from None
validate(config, "../pipeline/schemas/config.schema.yaml")

RESULTS = WF["results_dir"].rstrip("/")
INTERVALS = {t: [iv["name"] for iv in tip["intervals"]] for t, tip in TIPS.items()}
# Jobs call `python -m pipeline ...` with the interpreter that runs Snakemake.
use_this_interpreter_for_jobs()
CONDA_ENV = "envs/pipeline.yaml"


wildcard_constraints:
    tip="[A-Za-z0-9_.-]+",
    interval="[A-Za-z0-9_.-]+",


# Paths of the results, below results_dir; "{tip}" and "{interval}" stay wildcards.
def result(*parts):
    """results_dir/<parts>."""
    return "/".join((RESULTS, *parts))


def tip_result(name):
    """A file of a tip: results_dir/<tip>/<name>."""
    return result("{tip}", name)


def interval_result(stage, ext):
    """A file of an interval: results_dir/<tip>/<stage>/<interval>.<ext>."""
    return result("{tip}", stage, f"{{interval}}.{ext}")


def intervals_of(tip, stage, ext):
    """The files of every interval of ``tip`` (interval_result)."""
    return expand(interval_result(stage, ext), tip=tip, interval=INTERVALS[tip])


def job_log(job):
    """A job's log: results_dir/logs/<job>.log, ``job`` e.g. "{tip}/forces/{interval}"."""
    return result("logs", f"{job}.log")


def job_benchmark(job):
    """A job's Snakemake benchmark (run time, memory): results_dir/benchmarks/<job>.tsv."""
    return result("benchmarks", f"{job}.tsv")


def interval_cfg(wildcards):
    for iv in TIPS[wildcards.tip]["intervals"]:
        if iv["name"] == wildcards.interval:
            return iv
    raise WorkflowError(f"{TIP_FILES[wildcards.tip]}: no interval {wildcards.interval!r}")


def tip_yaml(wildcards):
    return TIP_FILES[wildcards.tip]


# The code of each job, a hash of its modules (pipeline.code_version).  Rules carry it as a `code`
# param, so Snakemake's params trigger reruns a stage whose code changed (a pipeline upgrade) and what
# follows it; a comment or a reformatting changes nothing.  `pipeline.config` (the YAML -> SI loader)
# is part of every stage that reads a tip's YAML.
RULE_MODULES = {
    "profiles": ("pipeline.tem.stage", "pipeline.config"),
    "fits": ("pipeline.fits.stage", "pipeline.config"),
    "fits_figure": ("pipeline.fits.figures",),
    "forces": ("pipeline.forces.stage", "pipeline.config"),
    "inversion": ("pipeline.inversion.stage", "pipeline.config"),
    "adhesion_range": ("pipeline.adhesion_range.stage", "pipeline.config"),
    "adhesion_figures": ("pipeline.adhesion_range.figures",),
    "summary": ("pipeline.adhesion_range.report",),
    "rigid_laws_figure": ("pipeline.mechanics.figures",),
}
RULE_CODE = {name: code_version(*modules) for name, modules in RULE_MODULES.items()}


# What each stage reads from a tip's YAML (after unit conversion), and the inversion from the
# workflow config.  Rules carry it as a `settings` param instead of taking the YAML as an input:
# Snakemake's params trigger then reruns exactly the stages whose settings changed (editing
# `cantilever:` reruns forces -> inversion -> range, not profiles or fits, and other tips not at
# all; editing the h grid, the laws, the solver mode or the Monte Carlo reruns every inversion).
STAGE_KEYS = {
    "profiles": (
        "tem",
        ("pixel_size", "orientation", "profile_height", "coating", "refine", "fringe_correction", "defocus"),
    ),
    "fits": ("tem", ("fit_height", "S")),
    "forces": (None, ("cantilever", "force_curves")),
    "inversion": (None, ("materials", "reference_intervals")),
}


INTERVAL_FORCE_KEYS = ("deflection_sensitivity", "deflection_sensitivity_uncertainty", "calibration_curves")


def stage_settings(stage):
    def settings(wildcards):
        tip = TIPS[wildcards.tip]
        section, keys = STAGE_KEYS[stage]
        src = tip[section] if section else tip
        picked = {k: src.get(k) for k in keys}
        if stage == "inversion":
            picked["intervals"] = [(iv["name"], iv["scans"]) for iv in tip["intervals"]]
            picked["workflow"] = {k: WF[k] for k in pc.INVERSION_KEYS}
        if stage == "forces":  # the interval's own InvOLS settings
            iv = interval_cfg(wildcards)
            picked["interval"] = {k: iv.get(k) for k in INTERVAL_FORCE_KEYS}
        if stage == "profiles" and interval_cfg(wildcards).get("defocus"):  # the interval's own defocus
            picked["interval_defocus"] = interval_cfg(wildcards)["defocus"]
        return json.dumps(picked, sort_keys=True, default=str)

    return settings
