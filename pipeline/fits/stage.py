"""Stage 2's entry point (``python -m pipeline fit``): read the profile file, fit, write the fit file."""

from __future__ import annotations

from pipeline.fits.io import EDGE_NOTE_PREFIX, read_profile, write_fit_h5
from pipeline.fits.profile_fit import fit_power_law
from pipeline.fits.result import FitError


def run_fit(profile_h5, out_h5, *, fit_height=6e-9, S=1.0, tip="", interval="") -> None:
    """Fit the combined profile and each flank of ``profile_h5`` and the paraboloid (n held at 2) of
    the combined profile; write ``out_h5`` (atomic; layout in ``pipeline.fits.io``)."""
    prof, px = read_profile(profile_h5)
    fits = {}
    for name in ("combined", "left", "right"):
        r, z, edge = prof[name]
        try:
            both = name == "combined"
            fits[name] = fit_power_law(
                r,
                z,
                fit_height,
                S,
                pixel_size=px,
                groups=prof["flank"] if both else None,
                flank=prof["flank"] if both else None,
                image_chi2_red=prof["chi2_red"] if both else None,
                image_n_pixels=prof["n_pixels"],
                image_model_error_sd=prof.get("model_error_sd"),
                **(edge or {}),
            )
        except FitError as exc:
            if name == "combined":
                raise FitError(f"{profile_h5}: {exc}") from None
            fits[name] = None
    r, z, edge = prof["combined"]
    try:
        para = fit_power_law(
            r,
            z,
            fit_height,
            S,
            pixel_size=px,
            groups=prof["flank"],
            flank=prof["flank"],
            fixed_n=2.0,
            image_chi2_red=prof["chi2_red"],
            image_n_pixels=prof["n_pixels"],
            image_model_error_sd=prof.get("model_error_sd"),
            **(edge or {}),
        )
    except FitError:
        para = None
    # what stage 1 says about the edge (a faint layer beyond it, a coating it could not identify)
    # travels with the fit, into the inversion's notes of the interval
    fits["combined"].notes = [f"{EDGE_NOTE_PREFIX}{x}" for x in prof.get("edge_flags", [])] + fits["combined"].notes
    if prof.get("edge_is_core"):
        _flag_unusable([fits["combined"], para], "edge_is_core", EDGE_IS_CORE_NOTE)
    if prof.get("edge_not_fitted"):
        _flag_unusable([fits["combined"], para], "edge_not_fitted", EDGE_NOT_FITTED_NOTE)
    write_fit_h5(out_h5, fits, para, source=profile_h5, tip=tip, interval=interval)


EDGE_IS_CORE_NOTE = (
    "edge_is_core: stage 1 saw an outer layer beyond the fitted edge (a faint one on each flank alone, or "
    "one a clipped vacuum hides), so the profile is the core's, not the outer surface that touches the "
    "sample; the shape is not used (the layer's thickness could not be read to move the edge out: see the "
    "stage-1 notes)"
)


EDGE_NOT_FITTED_NOTE = (
    "edge_not_fitted: stage 1's silhouette fit found no sharp edge in its band (its body reached none of "
    "the fitted pixels), so the edge is the smoothed iso-contour it started from, not a fit to the image; "
    "its error is unknown and the shape is not used (on the independent wave-optical images such "
    "profiles were 0.4-2.7 nm off, n off by 1.2-2.5)"
)


def _flag_unusable(fits, flag, note):
    """Add the unusable ``flag`` and its ``note`` to every fit of a profile (``read_profile``)."""
    for fit in fits:
        if fit is not None and flag not in fit.flags:
            fit.flags = [*fit.flags, flag]
            fit.notes = [*fit.notes, note]
