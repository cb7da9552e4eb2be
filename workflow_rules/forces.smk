# Stage 3: force curves -> calibrated pull-off forces F_p = k * Delta (pipeline.forces.stage).


rule forces:
    conda:
        CONDA_ENV
    input:
        curves=lambda w: [str(p) for p in interval_cfg(w)["curve_paths"]],
        calibration=lambda w: [str(p) for p in interval_cfg(w).get("calibration_paths", [])],
    output:
        h5=f"{RESULTS}/{{tip}}/forces/{{interval}}.h5",
        png=report(f"{RESULTS}/{{tip}}/forces/{{interval}}.png", caption="report/forces.rst", category="3 Forces", subcategory="{tip}"),
    params:
        tip=tip_yaml,
        settings=stage_settings("forces"),
    log:
        f"{RESULTS}/logs/{{tip}}/forces/{{interval}}.log",
    benchmark:
        f"{RESULTS}/benchmarks/{{tip}}/forces/{{interval}}.tsv"
    shell:
        "python -m pipeline forces --tip-config {params.tip} --interval {wildcards.interval}"
        " --out-h5 {output.h5} --out-png {output.png} > {log} 2>&1"
