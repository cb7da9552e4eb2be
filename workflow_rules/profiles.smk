# Stage 1: side-view TEM image -> sub-pixel apex profile z(r) (pipeline.tem.stage.run_profiles).


rule profiles:
    conda:
        CONDA_ENV
    input:
        image=lambda w: str(interval_cfg(w)["image_path"]),
    output:
        h5=f"{RESULTS}/{{tip}}/profiles/{{interval}}.h5",
        png=report(f"{RESULTS}/{{tip}}/profiles/{{interval}}.png", caption="report/profiles.rst", category="1 Profiles", subcategory="{tip}"),
    params:
        tip=tip_yaml,
        settings=stage_settings("profiles"),
    log:
        f"{RESULTS}/logs/{{tip}}/profiles/{{interval}}.log",
    benchmark:
        f"{RESULTS}/benchmarks/{{tip}}/profiles/{{interval}}.tsv"
    shell:
        "python -m pipeline profiles --tip-config {params.tip} --interval {wildcards.interval}"
        " --out-h5 {output.h5} --out-png {output.png} > {log} 2>&1"
