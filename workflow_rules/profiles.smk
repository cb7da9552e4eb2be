# Stage 1: side-view TEM image -> sub-pixel apex profile z(r) (pipeline.tem.stage.run_profiles).


rule profiles:
    input:
        image=lambda w: str(interval_cfg(w)["image_path"]),
    output:
        h5=interval_result("profiles", "h5"),
        png=report(
            interval_result("profiles", "png"),
            caption="report/profiles.rst",
            category="1 Profiles",
            subcategory="{tip}",
        ),
    log:
        job_log("{tip}/profiles/{interval}"),
    benchmark:
        job_benchmark("{tip}/profiles/{interval}")
    conda:
        CONDA_ENV
    params:
        code=RULE_CODE["profiles"],
        tip=tip_yaml,
        settings=stage_settings("profiles"),
    shell:
        "python -m pipeline profiles --tip-config {params.tip} --interval {wildcards.interval}"
        " --out-h5 {output.h5} --out-png {output.png} > {log} 2>&1"
