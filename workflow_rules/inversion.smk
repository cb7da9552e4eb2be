# Stage 4: W_A(h) for every interval and traction law, with Monte Carlo (pipeline.inversion.stage);
# the h grid, the laws, the solver mode and the Monte Carlo settings come from the workflow config.


rule inversion:
    input:
        fits=lambda w: intervals_of(w.tip, "fits", "h5"),
        forces=lambda w: intervals_of(w.tip, "forces", "h5"),
    output:
        h5=tip_result("inversion.h5"),
    log:
        job_log("{tip}/inversion"),
    benchmark:
        job_benchmark("{tip}/inversion")
    conda:
        CONDA_ENV
    params:
        code=RULE_CODE["inversion"],
        tip=tip_yaml,
        settings=stage_settings("inversion"),
        workflow_config=WORKFLOW_CONFIG,
        fits_dir=lambda w: result(w.tip, "fits"),
        forces_dir=lambda w: result(w.tip, "forces"),
    shell:
        "python -m pipeline inversion --tip-config {params.tip} --workflow-config {params.workflow_config}"
        " --fits {params.fits_dir} --forces {params.forces_dir} --out-h5 {output.h5} > {log} 2>&1"
