# Stage 2: least-squares power law z = r^n/(nQ) on the profile up to fit_height (pipeline.fits).


rule fits:
    conda:
        CONDA_ENV
    input:
        profile=f"{RESULTS}/{{tip}}/profiles/{{interval}}.h5",
    output:
        h5=f"{RESULTS}/{{tip}}/fits/{{interval}}.h5",
    params:
        tip=tip_yaml,
        settings=stage_settings("fits"),
    log:
        f"{RESULTS}/logs/{{tip}}/fits/{{interval}}.log",
    benchmark:
        f"{RESULTS}/benchmarks/{{tip}}/fits/{{interval}}.tsv"
    shell:
        "python -m pipeline fit --tip-config {params.tip} --interval {wildcards.interval}"
        " --profile-h5 {input.profile} --out-h5 {output.h5} > {log} 2>&1"


rule fits_figure:
    conda:
        CONDA_ENV
    input:
        lambda w: expand(f"{RESULTS}/{w.tip}/fits/{{interval}}.h5", interval=INTERVALS[w.tip]),
    output:
        report(f"{RESULTS}/{{tip}}/fits.png", caption="report/fits.rst", category="2 Fits", subcategory="{tip}"),
    log:
        f"{RESULTS}/logs/{{tip}}/fits_figure.log",
    benchmark:
        f"{RESULTS}/benchmarks/{{tip}}/fits_figure.tsv"
    shell:
        "python -m pipeline fit-figure --out-png {output} {input} > {log} 2>&1"
