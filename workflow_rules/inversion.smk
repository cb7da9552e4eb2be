# Stage 4: W_A(h) for every interval and traction law, with Monte Carlo (pipeline.inversion).


rule inversion:
    conda:
        CONDA_ENV
    input:
        fits=lambda w: expand(f"{RESULTS}/{w.tip}/fits/{{interval}}.h5", interval=INTERVALS[w.tip]),
        forces=lambda w: expand(f"{RESULTS}/{w.tip}/forces/{{interval}}.h5", interval=INTERVALS[w.tip]),
    output:
        h5=f"{RESULTS}/{{tip}}/inversion.h5",
    params:
        tip=tip_yaml,
        settings=stage_settings("inversion"),
        fits_dir=lambda w: f"{RESULTS}/{w.tip}/fits",
        forces_dir=lambda w: f"{RESULTS}/{w.tip}/forces",
        h_min=WF["h_grid"]["min"],
        h_max=WF["h_grid"]["max"],
        h_points=WF["h_grid"]["points"],
        h_spacing=WF["h_grid"]["spacing"],
        laws=",".join(WF["traction_laws"]),
        solver_mode=WF["solver_mode"],
        mc_samples=WF["monte_carlo"]["samples"],
        seed=WF["monte_carlo"]["seed"],
    log:
        f"{RESULTS}/logs/{{tip}}/inversion.log",
    benchmark:
        f"{RESULTS}/benchmarks/{{tip}}/inversion.tsv"
    shell:
        "python -m pipeline inversion --tip-config {params.tip} --fits {params.fits_dir} --forces {params.forces_dir}"
        " --out-h5 {output.h5} --h-min {params.h_min} --h-max {params.h_max} --h-points {params.h_points}"
        " --h-spacing {params.h_spacing} --laws {params.laws} --solver-mode {params.solver_mode}"
        " --mc-samples {params.mc_samples} --seed {params.seed} > {log} 2>&1"
