# Reports across tips: results/summary.csv (like the paper's Table 1) and the Fig. 8 comparison.


rule summary:
    conda:
        CONDA_ENV
    input:
        expand(f"{RESULTS}/{{tip}}/adhesion_range.h5", tip=TIPS),
    output:
        report(f"{RESULTS}/summary.csv", caption="report/summary.rst", category="5 Summary"),
    log:
        f"{RESULTS}/logs/summary.log",
    benchmark:
        f"{RESULTS}/benchmarks/summary.tsv"
    shell:
        "python -m pipeline summary --out-csv {output} {input} > {log} 2>&1"


rule rigid_laws_figure:
    conda:
        CONDA_ENV
    output:
        report(f"{RESULTS}/rigid_laws.png", caption="report/rigid_laws.rst", category="5 Summary"),
    log:
        f"{RESULTS}/logs/rigid_laws_figure.log",
    benchmark:
        f"{RESULTS}/benchmarks/rigid_laws_figure.tsv"
    shell:
        "python -m pipeline rigid-laws-figure --out-png {output} > {log} 2>&1"
