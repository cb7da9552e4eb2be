# Stage 3: force curves -> calibrated pull-off forces F_p = k * Delta (pipeline.forces.stage).


rule forces:
    input:
        curves=lambda w: [str(p) for p in interval_cfg(w)["curve_paths"]],
        calibration=lambda w: [str(p) for p in interval_cfg(w).get("calibration_paths", [])],
    output:
        h5=interval_result("forces", "h5"),
        png=report(
            interval_result("forces", "png"), caption="report/forces.rst", category="3 Forces", subcategory="{tip}"
        ),
    log:
        job_log("{tip}/forces/{interval}"),
    benchmark:
        job_benchmark("{tip}/forces/{interval}")
    conda:
        CONDA_ENV
    params:
        code=RULE_CODE["forces"],
        tip=tip_yaml,
        settings=stage_settings("forces"),
    shell:
        "python -m pipeline forces --tip-config {params.tip} --interval {wildcards.interval}"
        " --out-h5 {output.h5} --out-png {output.png} > {log} 2>&1"
