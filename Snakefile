# Wear-test adhesion pipeline: TEM images + force curves -> W_A and adhesion range h.
# Run:  snakemake --cores 2        (settings: config/config.yaml, one YAML per tip in config/tips/)
from snakemake.utils import min_version

from pipeline.workflow_support import report_failed_cluster_jobs

min_version("9.0")


configfile: "config/config.yaml"


include: "workflow_rules/common.smk"
include: "workflow_rules/profiles.smk"
include: "workflow_rules/fits.smk"
include: "workflow_rules/forces.smk"
include: "workflow_rules/inversion.smk"
include: "workflow_rules/adhesion_range.smk"
include: "workflow_rules/report.smk"


rule all:
    input:
        f"{RESULTS}/summary.csv",
        f"{RESULTS}/rigid_laws.png",
        expand(f"{RESULTS}/{{tip}}/{{tip}}_report.csv", tip=TIPS),
        expand(f"{RESULTS}/{{tip}}/fits.png", tip=TIPS),
        expand(f"{RESULTS}/{{tip}}/W_A_vs_h.png", tip=TIPS),
        expand(f"{RESULTS}/{{tip}}/adhesion_map.png", tip=TIPS),
        [f"{RESULTS}/{t}/forces/{iv}.png" for t in TIPS for iv in INTERVALS[t]],
    default_target: True


# On a cluster: say for each failed SLURM job why it ended (time, memory, cancelled) and which
# rule, tip and interval it was running (Snakemake names only the group for grouped jobs).
onerror:
    report_failed_cluster_jobs(log)
