# Stage 5: where the worn tips' W_A(h) meet the paraboloidal reference (pipeline.adhesion_range.stage),
# and its figures (pipeline.adhesion_range.figures) as a separate job so the numbers never wait on plotting.


rule adhesion_range:
    input:
        inversion=tip_result("inversion.h5"),
    output:
        h5=tip_result("adhesion_range.h5"),
        csv=report(
            tip_result("{tip}_report.csv"),
            caption="report/tip_report.rst",
            category="4 Adhesion range",
            subcategory="{tip}",
        ),
    log:
        job_log("{tip}/adhesion_range"),
    benchmark:
        job_benchmark("{tip}/adhesion_range")
    conda:
        CONDA_ENV
    params:
        code=RULE_CODE["adhesion_range"],
        tip=tip_yaml,
    shell:
        "python -m pipeline adhesion-range --tip-config {params.tip} --inversion-h5 {input.inversion}"
        " --out-h5 {output.h5} --report-csv {output.csv} > {log} 2>&1"


rule adhesion_figures:
    input:
        tip_result("adhesion_range.h5"),
    output:
        wa_h=report(
            tip_result("W_A_vs_h.png"), caption="report/w_of_h.rst", category="4 Adhesion range", subcategory="{tip}"
        ),
        amap=report(
            tip_result("adhesion_map.png"),
            caption="report/adhesion_map.rst",
            category="4 Adhesion range",
            subcategory="{tip}",
        ),
    log:
        job_log("{tip}/adhesion_figures"),
    benchmark:
        job_benchmark("{tip}/adhesion_figures")
    conda:
        CONDA_ENV
    params:
        code=RULE_CODE["adhesion_figures"],
    shell:
        "python -m pipeline adhesion-figures --tip {wildcards.tip} --range-h5 {input}"
        " --w-of-h-png {output.wa_h} --adhesion-map-png {output.amap} > {log} 2>&1"
