# Stage 2: least-squares power law z = r^n/(nQ) on the profile up to fit_height (pipeline.fits).


rule fits:
    input:
        profile=interval_result("profiles", "h5"),
    output:
        h5=interval_result("fits", "h5"),
    log:
        job_log("{tip}/fits/{interval}"),
    benchmark:
        job_benchmark("{tip}/fits/{interval}")
    conda:
        CONDA_ENV
    params:
        code=RULE_CODE["fits"],
        tip=tip_yaml,
        settings=stage_settings("fits"),
    shell:
        "python -m pipeline fit --tip-config {params.tip} --interval {wildcards.interval}"
        " --profile-h5 {input.profile} --out-h5 {output.h5} > {log} 2>&1"


rule fits_figure:
    input:
        lambda w: intervals_of(w.tip, "fits", "h5"),
    output:
        report(tip_result("fits.png"), caption="report/fits.rst", category="2 Fits", subcategory="{tip}"),
    log:
        job_log("{tip}/fits_figure"),
    benchmark:
        job_benchmark("{tip}/fits_figure")
    conda:
        CONDA_ENV
    params:
        code=RULE_CODE["fits_figure"],
    shell:
        "python -m pipeline fit-figure --out-png {output} {input} > {log} 2>&1"
