# Shared setup: validate every config before any job runs, list tips and intervals.
from pathlib import Path

import yaml
from snakemake.exceptions import WorkflowError
from snakemake.utils import validate

import pipeline.config as pc
from pipeline.workflow_support import use_this_interpreter_for_jobs

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


def interval_cfg(wildcards):
    for iv in TIPS[wildcards.tip]["intervals"]:
        if iv["name"] == wildcards.interval:
            return iv
    raise WorkflowError(f"{TIP_FILES[wildcards.tip]}: no interval {wildcards.interval!r}")


def tip_yaml(wildcards):
    return TIP_FILES[wildcards.tip]
