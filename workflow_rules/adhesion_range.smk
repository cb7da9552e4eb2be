# Stage 5: where the worn tips' W_A(h) meet the paraboloidal reference (pipeline.adhesion_range),
# and its figures (pipeline.figures_adhesion) as a separate job so the numbers never wait on plotting.


rule adhesion_range:
    conda:
        CONDA_ENV
    input:
        inversion=f"{RESULTS}/{{tip}}/inversion.h5",
    output:
        h5=f"{RESULTS}/{{tip}}/adhesion_range.h5",
        csv=report(f"{RESULTS}/{{tip}}/{{tip}}_report.csv", caption="report/tip_report.rst", category="4 Adhesion range", subcategory="{tip}"),
    params:
        tip=tip_yaml,
    log:
        f"{RESULTS}/logs/{{tip}}/adhesion_range.log",
    benchmark:
        f"{RESULTS}/benchmarks/{{tip}}/adhesion_range.tsv"
    shell:
        "python -m pipeline adhesion-range --tip-config {params.tip} --inversion-h5 {input.inversion}"
        " --out-h5 {output.h5} --report-csv {output.csv} > {log} 2>&1"


rule adhesion_figures:
    conda:
        CONDA_ENV
    input:
        f"{RESULTS}/{{tip}}/adhesion_range.h5",
    output:
        wa_h=report(f"{RESULTS}/{{tip}}/W_A_vs_h.png", caption="report/w_of_h.rst", category="4 Adhesion range", subcategory="{tip}"),
        amap=report(f"{RESULTS}/{{tip}}/adhesion_map.png", caption="report/adhesion_map.rst", category="4 Adhesion range", subcategory="{tip}"),
    log:
        f"{RESULTS}/logs/{{tip}}/adhesion_figures.log",
    benchmark:
        f"{RESULTS}/benchmarks/{{tip}}/adhesion_figures.tsv"
    shell:
        "python -m pipeline adhesion-figures --tip {wildcards.tip} --range-h5 {input}"
        " --w-of-h-png {output.wa_h} --adhesion-map-png {output.amap} > {log} 2>&1"
