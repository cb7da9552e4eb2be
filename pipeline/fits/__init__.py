"""Stage 2: least-squares power-law fit of the apex profile (paper Eq. 1, 2).

Modules: ``result`` (:class:`PowerLawFit`, :class:`FitError`), ``power_law`` (the model and its
least-squares fit with covariance; the rigid Dugdale area of Eq. 12), ``screening`` (turned-back
edge, contamination on one flank), ``profile_fit`` (the public fit :func:`fit_power_law`: screening,
fit, flank disagreement), ``io`` (the fit HDF5: writer and readers, the only place its layout is
spelled), ``figures`` and ``stage`` (the Snakemake entry point :func:`pipeline.fits.stage.run_fit`).

Model: z = z0 + |r|^n / (n Q), r measured from the tip axis, apex offset z0 free,
fitted to the profile points with z <= fit_height (default 6 nm, as in the
paper).  Well-conditioned parameters: (n, ln r_h, z0) with r_h the radius at
height fit_height above z0, i.e. z - z0 = h (r / r_h)^n; then
ln Q = n ln r_h - ln n - ln h (Q in SI, m^(n-1)).  Residuals are orthogonal
distances to first order, (z - f(r)) / sqrt(1 + f'(r)^2), so steep flanks are not
over-weighted.  Covariance: (J^T J)^-1 s^2 with s^2 the residual variance,
inflated by the effective-sample-size factor of the residual autocorrelation
along each flank (neighbouring edge points share pixels), then mapped to
(n, ln Q) by the Jacobian.

Asymmetric flanks: a worn tip need not be a body of revolution.  The combined fit gives each
flank its own scale around a common axis, x = x_a + (1 + e) r(z) right and x_a - (1 - e) r(z)
left (a section r (1 + e cos phi)), so r(z), the fitted power law, is the mean of the two
flank radii at every height: the radius of the circle with the section's width, whose area
differs from the section's by e^2/2 (0.1 % at e = 0.05).  One curve for both flanks mixes two
scales: on the exact silhouette of a wave-optical tip with e = 0.045 it gave n 4.87 for 5.77.

Fit error (percent): 100 x RMS orthogonal residual / fit_height - the scatter of
the profile about the fit relative to the height of the fit window (the paper
reports < 2 %).  R from Eq. 2 with a given S: Q = S^(n-2) R^(n-1).

Screening (both flanks given): points where the edge turns back (a point at least 0.4 nm, or
1.5 px, lower lies as much further out on the same flank: an undercut, never the power law) and runs of at least
4 points that stand > 4 robust SD (and 0.15 nm) out of one flank while the other flank at the
same heights does not (contamination stuck to one flank: the flanks' mirror symmetry broken)
are left out, and the fit's notes say where.

Flags: "n_below_1.5", "residual_above_pixel" (RMS residual > 2 pixel sizes),
"few_points" (< 12 points), "not_converged", "n_at_bound", "edge_turns_back" (more than a
quarter of the window's points turn back), "edge_is_core" (stage 1 saw a faint outer layer beyond
the fitted edge on each flank and could not read its thickness at the apex: the profile is the core's,
``pipeline.tem.faint_layer``; where it could, the edge was moved out by it, ``pipeline.tem.outer_layer``; or
saw the edge inside material whose end a clipped vacuum hides, ``pipeline.tem.clipped_layer``),
"edge_not_fitted" (stage 1's silhouette fit found no sharp edge in its band: the edge is its starting
iso-contour, not a fit to the image).
"""

from pipeline.fits.result import FitError, PowerLawFit

__all__ = ["FitError", "PowerLawFit"]
