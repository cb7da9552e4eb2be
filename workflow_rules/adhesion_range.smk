# Stage 5: where the worn tips' W_A(h) meet the paraboloidal reference (pipeline.adhesion_range).


rule adhesion_range:
    conda:
        CONDA_ENV
    input:
        inversion=f"{RESULTS}/{{tip}}/inversion.h5",
    output:
        h5=f"{RESULTS}/{{tip}}/adhesion_range.h5",
        csv=f"{RESULTS}/{{tip}}/{{tip}}_report.csv",
        wa_h=report(f"{RESULTS}/{{tip}}/W_A_vs_h.png", category="4 Adhesion range", subcategory="{tip}"),
        amap=report(f"{RESULTS}/{{tip}}/adhesion_map.png", category="4 Adhesion range", subcategory="{tip}"),
    params:
        tip=tip_yaml,
        fig_dir=lambda w: f"{RESULTS}/{w.tip}",
    log:
        f"{RESULTS}/logs/{{tip}}/adhesion_range.log",
    benchmark:
        f"{RESULTS}/benchmarks/{{tip}}/adhesion_range.tsv"
    shell:
        "python -m pipeline adhesion-range --tip-config {params.tip} --inversion-h5 {input.inversion}"
        " --out-h5 {output.h5} --report-csv {output.csv} --fig-dir {params.fig_dir} > {log} 2>&1"
