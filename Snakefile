# Wear-test adhesion pipeline: TEM images + force curves -> W_A and adhesion range h.
# Run:  snakemake --cores 2        (settings: config/config.yaml, one YAML per tip in config/tips/)
from snakemake.utils import min_version

from pipeline.workflow_support import record_run_end, record_run_start, report_failed_run

min_version("9.0")


configfile: "config/config.yaml"


# `snakemake --report`: the workflow description; each result's caption says what to look for.
report: "workflow_rules/report/workflow.rst"


include: "workflow_rules/common.smk"
include: "workflow_rules/profiles.smk"
include: "workflow_rules/fits.smk"
include: "workflow_rules/forces.smk"
include: "workflow_rules/inversion.smk"
include: "workflow_rules/adhesion_range.smk"
include: "workflow_rules/report.smk"


rule all:
    default_target: True
    input:
        result("summary.csv"),
        result("rigid_laws.png"),
        expand(tip_result("{tip}_report.csv"), tip=TIPS),
        expand(tip_result("fits.png"), tip=TIPS),
        expand(tip_result("W_A_vs_h.png"), tip=TIPS),
        expand(tip_result("adhesion_map.png"), tip=TIPS),
        [png for tip in TIPS for png in intervals_of(tip, "forces", "png")],


# Who holds the lock: `python -m pipeline unlock-stale` (run by `make run`) removes the lock of a
# run that was killed, never that of a live one (pipeline/workflow_support.py).
onstart:
    record_run_start()


onsuccess:
    record_run_end()


# Say on the console why each job failed (the reason from its log) and, on a cluster, why SLURM
# ended it (time, memory, cancelled) and which rule, tip and interval it was running (Snakemake
# names only the group for grouped jobs).  With --keep-going, write the summary of the tips that
# finished, with a row for each tip that failed saying why.
onerror:
    try:
        report_failed_run(workflow, log, results=RESULTS, tips=list(TIPS))
    finally:
        record_run_end()
