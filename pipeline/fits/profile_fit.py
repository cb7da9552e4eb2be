"""The public stage-2 fit: screening, the power-law fit and the flanks' disagreement (package doc)."""

from __future__ import annotations

import numpy as np

from pipeline.fits.power_law import _fit_power_law
from pipeline.fits.result import FitError, PowerLawFit
from pipeline.fits.screening import _one_flank_runs, _where
from pipeline.tem.model_error import EDGE_SYSTEMATIC_PX, misfit_gain
from pipeline.tem.turn_back import TURN_BACK_MAX, TURN_BACK_PX, TURN_BACK_TOL
from pipeline.tem.turn_back import turned_back as _turned_back


def _systematic_px(image_chi2_red, image_n_pixels):
    """The smooth edge error (px per flank) the image fit's reduced chi^2 leaves beyond noise
    (``pipeline.tem.model_error``)."""
    return EDGE_SYSTEMATIC_PX * misfit_gain(image_chi2_red, image_n_pixels)


def _screened_out(robust, r, z, side, win, r_scale, pixel_size, notes, flags):
    """The points screened out (contamination on one flank, an edge turning back) against the
    ``robust`` fit; appends to ``notes`` and ``flags``."""
    bump = _one_flank_runs(robust, r, z, side, win, r_scale)
    if bump.any():
        notes.append(
            f"contamination on the {_where(r, z, side, bump)} (stands out of that flank only, "
            f"{bump.sum()} points): left out, the fit rests on the unaffected points"
        )
    back = _turned_back(r, z, side, win & ~bump, tol=max(TURN_BACK_TOL, TURN_BACK_PX * (pixel_size or 0.0)))
    if back.any():
        notes.append(
            f"edge turns back (radius shrinking with height) at {back.sum()} of {win.sum()} points "
            f"({_where(r, z, side, back)}): left out"
        )
        if back.sum() > TURN_BACK_MAX * max(win.sum(), 1):
            flags.append("edge_turns_back")
    return bump, back


def fit_power_law(
    r,
    z,
    fit_height=6e-9,
    S=1.0,
    pixel_size=None,
    groups=None,
    r_scale=1e-9,
    edge_basis=None,
    edge_cov=None,
    normal_rz=None,
    fixed_n=None,
    flank=None,
    screen=True,
    image_chi2_red=None,
    image_n_pixels=None,
    image_model_error_sd=None,
) -> PowerLawFit:
    """``_fit_power_law`` (Eq. 1) on the profile points, screened first where both flanks are given
    (``screen``): points where the edge turns back (the radius shrinks with height) and runs
    that stand out of one flank only (contamination: the flanks' mirror symmetry broken) are
    left out, and the fit's ``notes`` say where; an edge that turns back over more than
    TURN_BACK_MAX of its points is flagged "edge_turns_back" (unusable).  ``image_model_error_sd`` (m):
    the model-error common offset stage 1 put into ``edge_cov`` (None: a file from before it, or no
    silhouette fit); with it, that mode is left out of the smooth edge error here."""
    r = np.abs(np.asarray(r, float))
    z = np.asarray(z, float)
    args = dict(fit_height=fit_height, S=S, pixel_size=pixel_size, r_scale=r_scale, fixed_n=fixed_n)
    sys_px = _systematic_px(image_chi2_red, image_n_pixels)
    common = image_model_error_sd is not None

    pre = []  # notes known before the fit
    if edge_cov is not None and not np.all(np.isfinite(edge_cov)):
        edge_cov = None
        pre.append("the silhouette fit gave no finite edge covariance: sigma_n from the residual scatter")

    def sub(keep):
        out = dict(
            groups=None if groups is None else np.asarray(groups)[keep],
            flank=None if flank is None else np.asarray(flank)[keep],
        )
        if edge_basis is not None and edge_cov is not None and normal_rz is not None:
            out.update(
                edge_basis=np.asarray(edge_basis)[keep], edge_cov=edge_cov, normal_rz=np.asarray(normal_rz)[keep]
            )
        return out

    full = np.ones(r.size, bool)
    if not screen or flank is None:
        fit = _fit_power_law(r, z, **args, **sub(full), systematic_px=sys_px, common_in_edge=common)
        fit.notes = pre + fit.notes
        return fit
    side = np.where(np.asarray(flank) < 0, -1, 1)
    win = np.isfinite(r) & np.isfinite(z) & (z <= fit_height)
    notes, flags = list(pre), []
    # contamination first, against a robust fit (a particle hanging below the face would otherwise
    # make the face above it look turned back)
    scale = max(0.05e-9, 0.25 * (pixel_size or 0.0))
    robust = _fit_power_law(r, z, **args, **sub(full), loss=("soft_l1", scale))
    bump, back = _screened_out(robust, r, z, side, win, r_scale, pixel_size, notes, flags)
    keep = full & ~bump & ~back
    fit = _fit_power_law(r[keep], z[keep], **args, **sub(keep), systematic_px=sys_px, common_in_edge=common)
    if sys_px > 0:
        notes.append(
            f"the image fit leaves more than noise (reduced chi^2 {image_chi2_red:.3g}): a smooth edge error of "
            f"{sys_px:.2f} px per flank is in the covariance"
            + (" (the part common to both flanks as the edge's common offset of stage 1)" if common else "")
        )
    if fixed_n is None and FLANK_DISAGREEMENT:
        _add_flank_disagreement(fit, r, z, side, keep & win, args, notes)
    fit.notes = notes + fit.notes
    fit.flags = flags + fit.flags
    return fit


FLANK_DISAGREEMENT = True  # add ((n_left - n_right) / 2)^2 beyond noise to var(n) (``_add_flank_disagreement``)
FLANK_MIN_POINTS = 12


def _add_flank_disagreement(fit, r, z, side, use, args, notes):
    """The two flanks are two measurements of one n; the half-difference of their separate fits
    estimates the error of the combined n also where the edge model is wrong on one flank or
    both (a Fresnel fringe, a particle, a layer, wear the flank-wise scale does not describe),
    which the edge covariance does not know.  Its square, less what the flanks' own sigma_n
    explain, is added to var(n) (with the ln Q it drags along at fixed r_h), and the notes say so
    where it dominates."""
    ns, vs = [], []
    for s_ in (-1, 1):
        m = use & (side == s_)
        if m.sum() < FLANK_MIN_POINTS:
            return
        try:
            f1 = _fit_power_law(r[m], z[m], **args)
        except FitError:
            return
        if f1.flags:
            return
        ns.append(f1.n)
        vs.append(f1.sigma_n**2)
    d2 = 0.25 * (ns[0] - ns[1]) ** 2
    d2 = max(0.0, d2 - 0.25 * (vs[0] + vs[1]))  # only what the flanks' own noise does not explain
    n = fit.n
    a = (fit.ln_Q + np.log(n) + np.log(fit.fit_height)) / n - 1.0 / n  # d ln Q / d n at fixed r_h
    t = np.array([1.0, a])
    fit.cov_n_lnQ = fit.cov_n_lnQ + d2 * np.outer(t, t)
    before = fit.sigma_n
    fit.sigma_n = float(np.sqrt(fit.cov_n_lnQ[0, 0]))
    fit.sigma_lnQ = float(np.sqrt(fit.cov_n_lnQ[1, 1]))
    fit.flank_n = (float(ns[0]), float(ns[1]))
    if np.sqrt(d2) > before:
        notes.append(
            f"the flanks disagree: n = {ns[0]:.2f} (left) and {ns[1]:.2f} (right) fitted separately; "
            f"sigma_n {before:.3f} -> {fit.sigma_n:.3f} with their half-difference"
        )


def fit_tip_profile(profile, fit_height=6e-9, S=1.0, which="both") -> PowerLawFit:
    """``fit_power_law`` on a ``pipeline.tem.profiles.TipProfile`` (one flank or both),
    with its edge covariance when the silhouette fit provided one."""
    i = profile.flank_index(which)
    edge = {}
    if profile.offset_basis is not None:
        edge = dict(edge_basis=profile.offset_basis[i], edge_cov=profile.offset_cov, normal_rz=profile.normal_rz[i])
    both = which == "both"
    em = profile.edge_model or {}
    chi2, npx = em.get("global_chi2_red"), em.get("global_n_pixels")
    me = em.get("global_model_error_px")
    return fit_power_law(
        np.abs(profile.x[i]),
        profile.z[i],
        fit_height,
        S,
        pixel_size=profile.pixel_size,
        groups=profile.flank[i] if both else None,
        flank=profile.flank[i] if both else None,
        image_chi2_red=chi2 if both else None,
        image_n_pixels=npx,
        image_model_error_sd=None if me is None or not edge else me * profile.pixel_size,
        **edge,
    )
