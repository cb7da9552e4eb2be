"""Stage 3: AFM force-distance curves -> calibrated pull-off forces F_p = k * Delta.

Modules: ``curve`` (the ForceCurve container), ``read_csv`` / ``read_afmformats`` /
``reading`` (input), ``baseline`` and ``pulloff`` (detection), ``contact_slope``,
``reference_lever``, ``thermal`` and ``calibration`` (k and InvOLS with
uncertainties), ``contact_compliance`` (the tip's contact stiffness in a contact-slope InvOLS),
``statistics`` (per-interval mean, outliers), ``io`` (the forces HDF5: its writer and
:func:`~pipeline.forces.io.load_forces`, the only place its layout is spelled), ``figures`` and
``stage`` (the Snakemake entry point :func:`pipeline.forces.stage.run_forces`).

Conventions (SI inside): ``z`` is the piezo extension towards the sample (m,
increases on approach); deflection is positive when the lever bends away from
the sample (repulsive), in volts (``"V"``) or metres (``"m"``).
"""

from pipeline.forces.errors import ForceCurveError, ForcesStageError

__all__ = ["ForceCurveError", "ForcesStageError"]
