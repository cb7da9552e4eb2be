# Reports across tips: results/summary.csv (like the paper's Table 1) and the Fig. 8 comparison.


rule summary:
    input:
        expand(tip_result("adhesion_range.h5"), tip=TIPS),
    output:
        report(result("summary.csv"), caption="report/summary.rst", category="5 Summary"),
    log:
        job_log("summary"),
    benchmark:
        job_benchmark("summary")
    conda:
        CONDA_ENV
    params:
        code=RULE_CODE["summary"],
    shell:
        "python -m pipeline summary --out-csv {output} {input} > {log} 2>&1"


rule rigid_laws_figure:
    output:
        report(result("rigid_laws.png"), caption="report/rigid_laws.rst", category="5 Summary"),
    log:
        job_log("rigid_laws_figure"),
    benchmark:
        job_benchmark("rigid_laws_figure")
    conda:
        CONDA_ENV
    params:
        code=RULE_CODE["rigid_laws_figure"],
    shell:
        "python -m pipeline rigid-laws-figure --out-png {output} > {log} 2>&1"
