"""Global model fit of the tip silhouette: every pixel near the edge at once.

Starts from the iso-contour just below the background (``edges.initial_contour``,
which lies outside the surface by ~2 blur sigma) and its symmetry frame; no
per-normal fitting is needed.

Model (same physics as ``pipeline.synth.tem_image``), tip frame, pixels:
- outer meridian = the smoothed reference curve C0(S) (S = signed arc length,
  apex at 0, left flank negative) moved along its outward normal by
  delta(S) = sum_k c_k phi(S/D - k), cubic B-splines with knots every D ~ 1.2 nm
  (no power law presupposed; both flanks free, so asymmetry is measured);
- cross-section at height z: the disk spanning the two flanks (exact for a body of
  revolution), minus a hole where the curve rises above z between them (a dimple in a
  flat face, ``_Body``); a lighter coating of normal thickness c lies inside the outer
  surface, core = erosion of the outer section by c (``projection.core_radius_sq_table``,
  tabulated from its own apex so that it is continuous in c and in the shape);
- T = exp(-k_o t_outer - (k_c - k_o) t_core) with the exact chords, evaluated at
  pixel centres and 4 x 4 supersampled in pixels within ~1.5 px of a silhouette;
- image = G_sigma * T x (a + b_r row + b_c col): Gaussian blur, linear illumination
  (a, b_r, b_c eliminated by linear least squares).
Residual pixels: a band from 3 sigma + 4 px outside to 3 sigma + 14 px inside the
initial edge, up to 1.02 x the profile height; Poisson weights; a weak
second-difference penalty on c_k and a soft hinge towards a monotone z(S) on each
flank (``MONOTONE_WEIGHT``).

Levenberg-Marquardt.  Jacobian: the spline columns use the local-translation
approximation d model / d c_k = phi_k(S_i) x d model / d(uniform offset), with S_i
the arc position of the curve point nearest to pixel i (exact for a uniform
offset, relative error ~(3 sigma / D)^2 / 2 otherwise: one extra rendering for all
c_k); blur, attenuations and coating thickness by finite differences (re-blurring
or re-exponentiating cached chords, only the coating re-renders the core).

Coating: "auto" fits the single-layer model, then searches the coated one
(``_coating_search``: starts on a grid of thicknesses that the single-layer blur
leaves room for, the two best taken a few LM steps, the better one converged) and
keeps it only if it lowers chi^2 by more than ``COAT_DCHI2`` (likelihood ratio, 2
extra parameters) with physical values (0.04 < k_o/k_c < 0.8, thickness >= MIN_COAT_PX).
A layered fit within +-``COAT_DCHI2`` of the single layer is neither found nor
excluded (thin light oxide at coarse pixels, heavy blur or low SNR: the image cannot
say whether it is there): the single-layer edge is kept, flagged "coating
ambiguous", and its covariance widened by a common offset of half the largest outward
shift among such layered fits (the SD of a 50/50 mixture of the two edges).  A coated fit whose
thickness has a relative standard error > 30 % is flagged "coating not
identifiable".  A given thickness (``coat_hint``) starts the coated fit there and
keeps it.

Defocus fringes (``fringe_correction``): where the fit leaves a reduced chi^2 above
``fringe_correction.MIN_CHI2_RED``, a coherent (Fresnel) rendering of the fitted body fits one
uniform offset of the edge with the defocus, the phase, the blur and a common scale of the
attenuations; the offset is applied (flag
"defocus fringes: edge moved ...", its standard error added to the edge covariance as a common
offset, and half the move as the correction's own model error: the sign of the defocus is not
always identified) if it lowers chi^2 enough and is no larger than a fringe can shift the edge.

A layer read as a fringe: on a defocused image phase contrast sharpens the edge, the fitted blur sits
at its floor and the coating search, which tries only layers the blur leaves room for, tries none;
a coated tip is then fitted as one material with its edge on the outer surface, and the correction
can explain the layer as the dark fringe of an overfocus (the wrong sign: grid 119 of
``bench_tem_independent``, 4.4 nm DLC in underfocus, moved 1.6 nm inwards).  Where the correction of
such a fit (one material, blur at the floor, applied) takes lambda x df < 0, or an overfocus came
within ``OVERFOCUS_MARGIN`` (1 %) of its best start in chi^2 after the screen's steps (the sign is then not
told by the one-material body: grid 119, 0.2 % apart, now fitted in underfocus), the coated model is
searched over every layer thickness, polished and rendered coherently as well, and taken if its
coherent chi^2 is lower (``_coated_alternative``; the edge's flags say so).  Trying every
thickness on every image instead (by the Beer-Lambert chi^2) read the dark fringe of coated tips in
overfocus as more layer (grid 56: 2.2 nm outward) and cost ~4x; the coherent chi^2 keeps those
one-material (README, issue 16).

A layer only the coherent rendering sees (``held_layer``): where the correction of a one-material fit
is applied and no coated alternative above was taken, the same outer curve is rendered coherently with
a held light layer of 0.8-2.4 nm (a native oxide) under it, and taken where that fits better by more
than 10 % of chi^2: on a blunt tip the phase step between an oxide and the core makes a fringe at the
flat face that one material places by moving the face out (n low by a median 0.31 on the oxides with
n > 4.5 of ``bench_tem_independent``'s three sets).  Not taken, the fit goes on as if none had been tried.

The sign of the defocus given (``defocus_sign``, the tip YAML's ``tem.defocus``): chi^2 does not
identify the sign (``fringe_correction``, "Why chi^2 cannot tell the sign"), the microscope's
operator knows it.  The correction is fitted at both signs as without it; where that takes the
other sign than the one given, it is fitted again at the given sign (the flag says so).  The coated
alternative runs where it runs without the sign (the fit of both signs took lambda x df < 0), and
then compares the two bodies rendered at the given sign.  Run also where that fit took underfocus
against an overfocus given, it put the edge of a 15.7 nm DLC layer (DLC set 39 of
``bench_tem_independent``) 6.0 nm inside instead of 2.6 nm outside: not done.  Where the fit of both
signs agrees with the one given, nothing more is done and the edge is the same (the coated
alternative's rendering, where it runs, keeps to the given sign).
With an overfocus given, a coated fit whose light layer is thinner than
``fringe_correction.LAYER_AS_FRINGE_MAX`` may have read the dark fringe just outside an uncoated edge
as that layer (grid 60: a 0.93 nm layer, the edge 0.44 nm out, its chi^2 under the correction's gate):
the fitted outer curve rendered as one material at that sign is compared with the coated body's
rendering, whatever the chi^2, and taken where it fits better by more than ``MIN_DCHI2``
(``_layer_as_fringe``; flag "a fringe, not a light layer").  Without the sign this took real oxides'
layers off at the wrong sign and cost 1.4-2.6x on every thin oxide (README, issue 16).

Saturated detector (``censored``): where the beam is above the detector's full scale (8- or
16-bit images of an over-exposed vacuum), the clipped pixels read the full scale instead of the
image, and fitting them as data pulls the model's vacuum down to it and the edge inwards (by up to
2.5 nm on the independent simulator's saturated images).  A clipped pixel says only that the
image is at least its value: its residual is (value - model) where the model is below it and 0
where it is above (a censored observation), the illumination is solved on the unclipped pixels,
and the noise is read from unclipped pixel pairs (``edges.flatten_background``).  The fit's
flags say how many of its pixels were clipped.

Model error (``model_error``): where the reduced chi^2 says the image is not the model (Fresnel
fringes and phase contrast, a detector tail, a layer the model reads wrongly) the fitted edge as a whole
is off by more than the noise covariance says: on the independent wave-optical simulator its mean
signed error was within 2 of its reported SD in 39 % of the 109 used grid images (43 % of 51 held-out),
typically 0.1-0.4 nm against a reported 0.02-0.05 nm.  The covariance gains the common offset of
``model_error.common_offset_sd_px`` (in the image's pixels, after any binning), flag "edge model
misfit ...".  What it does not cover: edges placed inside a faint DLC layer (1.5-4 nm, up to the
core), oxides hidden by a clipped vacuum (beyond the saturation term), misses of 0.3-0.9 nm.

The result carries, for every output edge point, its B-spline row and the
covariance of the c_k (marginal over all other parameters, px^2; from finite-
difference spline columns at the solution, ``_Fitter.polish``): the fit stage
propagates it into the covariance of (n, Q) (neighbouring edge points are strongly
correlated, so a point-wise residual scatter would understate it).

Modules: ``silhouette_model`` (the forward model: body, image, binning), ``silhouette_solver``
(Levenberg-Marquardt, Jacobians, polish), ``coating_search`` (the coated model's starts and the
layer decision), ``held_layer`` (a layer only the coherent rendering sees) and this one (the public
fit :func:`fit_silhouette` and its result).
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from pipeline.tem.coating_search import BLUR_FLOOR_PX, COAT_DCHI2, _coating_search
from pipeline.tem.edges import TipFrame
from pipeline.tem.fringe_correction import LAYER_AS_FRINGE_MAX, MOVE_SD_SHARE, fringe_offset
from pipeline.tem.fringe_correction import MIN_CHI2_RED as FRINGE_MIN_CHI2_RED
from pipeline.tem.fringe_correction import MIN_DCHI2 as FRINGE_MIN_DCHI2
from pipeline.tem.fringe_shape import fringe_shape
from pipeline.tem.held_layer import held_layer
from pipeline.tem.model_error import LAYER_SD, common_offset_sd_px
from pipeline.tem.silhouette_model import (
    KNOT_NM,
    _axis_attenuation,
    _bin,
    _Body,
    _bspline,
    _Problem,
    bin_factor,
    reference_curve,
)
from pipeline.tem.silhouette_solver import _Fitter

# a layer read as a fringe (module doc): the coated alternative is tried also where the fit of both signs
# took underfocus but an overfocus came this close in chi^2 after the screen's steps (grid 119 of
# ``bench_tem_independent``, 4.4 nm DLC in underfocus: 0.2 % apart; with the best start of each sign in
# the 2-D fit its one-material correction took underfocus, and the alternative was not tried)
OVERFOCUS_MARGIN = 0.01

# a saturated detector (module doc): where at least this share of the fitted vacuum beside the edge
# is clipped, the edge gets a common offset SD of SATURATED_EDGE_SD_NM (nm): the RMS of the edge bias
# on the independent simulator's images whose vacuum is clipped (bench_tem_independent, 120-image grid)
SATURATED_VACUUM_SHARE = 0.5
SATURATED_EDGE_SD_NM = 1.0

__all__ = ["GlobalFit", "fit_silhouette", "reference_curve", "bin_factor", "COAT_DCHI2", "_Body", "_Fitter", "_bspline"]


@dataclass
class GlobalFit:
    points: np.ndarray  # (N, 2) outer silhouette (row, col) in window px, left -> apex -> right
    normals: np.ndarray  # (N, 2) outward unit normals (row, col)
    basis: np.ndarray  # (N, K) d(normal offset of point)/d c_k
    cov_c: np.ndarray  # (K, K) covariance of the c_k (px^2), marginal
    frame: TipFrame
    sigma_px: float
    k_outer: float  # 1/px
    k_core: float
    coat_px: float
    rms_intensity: float  # RMS residual relative to the background
    chi2_red: float
    n_pixels: int
    n_iter: int
    stderr: dict = field(default_factory=dict)
    flags: list = field(default_factory=list)
    coating_test: dict = field(default_factory=dict)
    binning: int = 1
    fringe: dict = field(default_factory=dict)  # defocus-fringe correction (``fringe_correction``)
    model_error_px: float = 0.0  # SD of the common edge offset for the model's error, in cov_c (px)


def fit_silhouette(
    flat,
    contour,
    frame: TipFrame,
    hpx,
    noise,
    pixel_size=None,
    coat_hint=None,
    knot_nm=None,
    max_iter=25,
    binning=None,
    fringe_correction=True,
    censored=None,
    defocus_sign=0,
) -> GlobalFit:
    """Fit the silhouette model (module doc) to ``flat`` (window with the background
    flattened to 1, tip pointing down), starting from ``contour`` (iso-line outside the
    surface, window px) in ``frame``; ``hpx`` profile height (px), ``noise`` background
    noise (relative); ``coat_hint`` None (auto), 0 (none) or a thickness (px).
    ``binning``: block size (default ``bin_factor(pixel_size)``); results are in the
    pixels of ``flat``; ``fringe_correction``: the defocus-fringe correction (module doc) on/off;
    ``censored`` (bool, ``flat``'s shape, or None): pixels a saturated detector clipped, whose true
    value is at least the one read (module doc, "Saturated detector"); ``defocus_sign``: the sign of the
    defocus if the operator knows it (+1 underfocus, -1 overfocus; 0 not given; module doc, "The sign
    of the defocus given")."""
    b = int(binning or bin_factor(pixel_size))
    args = (flat, contour, frame, hpx, noise, pixel_size, coat_hint, knot_nm, max_iter)
    options = (fringe_correction, censored, defocus_sign)
    gf = _fit_binned(*args, b, *options) if b > 1 else _fit_pixels(*args, *options)
    return _with_model_error(gf, pixel_size)


def _with_model_error(gf, pixel_size):
    """``gf`` with the model-error common offset (module doc) in its edge covariance and flags; in the
    image's pixels (after any binning)."""
    sd = common_offset_sd_px(gf.chi2_red, gf.n_pixels, gf.coat_px)
    if sd > 0:
        gf.cov_c = gf.cov_c + sd**2 * np.ones_like(gf.cov_c)
        gf.model_error_px = sd
        nm = 1e9 * (pixel_size or float("nan"))
        layer = (
            f" and {LAYER_SD:g} x the light layer found ({gf.coat_px * nm:.2f} nm: phase contrast can read as one)"
            if gf.coat_px > 0
            else ""
        )
        gf.flags.append(
            f"edge model misfit (reduced chi^2 {gf.chi2_red:.3g}): the image is not the fitted Beer-Lambert "
            f"model, so the whole edge carries a common uncertainty of {sd * nm:.2f} nm (the model's error "
            f"measured on independent wave-optical images{layer})"
        )
    return gf


def _fit_pixels(
    flat, contour, frame, hpx, noise, pixel_size, coat_hint, knot_nm, max_iter, fringe_correction, censored, sign=0
):
    """``fit_silhouette`` on the pixels of ``flat`` as they are (no binning, no model-error term)."""
    flat = np.asarray(flat, float)
    knot_nm = knot_nm if knot_nm is not None else KNOT_NM
    knot = float(np.clip(knot_nm * 1e-9 / pixel_size if pixel_size else 6.0, 4.0, 16.0))
    # the reference must be smooth on the knot scale: its finer wiggles (contour noise)
    # would pass straight into the result, the spline offsets correct the large scales
    curve = reference_curve(frame.to_tip(contour), smooth_px=1.5 * knot)
    # noise floor 0.2 % of the background: model error of the forward model (noise-free images)
    prob = _Problem(flat, frame, curve, hpx, max(float(noise or 0.0), 2e-3), knot, censored=censored)
    k_ax = _axis_attenuation(flat, frame, curve)
    k0 = k_ax if np.isfinite(k_ax) and k_ax > 0 else 0.02
    max_coat = 12.0
    f1, st1, n_it = _single_layer_fit(prob, k0, max_coat, max_iter)
    fitter, st = f1, st1
    coat_test = {"model": "single"}
    if coat_hint and coat_hint > 0.95 * max_coat:
        # a given layer thicker than the fitted band: its core is outside the fitted pixels,
        # where the outer layer alone is seen (a thick DLC coating); a coated model would put
        # a core edge where the image has none
        coat_test["note"] = (
            f"the given layer ({coat_hint:.1f} px) is thicker than the fitted band "
            f"({max_coat:.0f} px inside the edge): the outer layer is fitted alone"
        )
        coat_hint = 0.0
    if coat_hint is None or coat_hint > 0:
        # 3) coated model: search over the layer thickness, then LM from the best start
        f2 = _Fitter(prob, coated=True)
        lim2 = _bounds(prob.K, k0, max_coat, True)
        st2, it, coat_test = _coating_search(f1, st1, f2, lim2, coat_hint, max_coat, max_iter)
        n_it += it
        if coat_test["model"] == "coated":
            fitter, st = f2, st2
    lim = _bounds(prob.K, k0, max_coat, fitter.coated)
    st, JTJ, names = fitter.polish(st, *lim)
    fringe = {}
    if fringe_correction and float(st.res @ st.res) / max(1, prob.n_data(st.B, st.lin)) > FRINGE_MIN_CHI2_RED:
        fit = (fitter, st, JTJ, names, coat_test)
        fitter, st, JTJ, names, coat_test, fringe = _defocus_fringes(
            prob, fit, (f1, st1, k0, max_coat, max_iter), pixel_size, coat_hint, sign
        )
    held = coat_test.get("held_layer", False)  # it already beat the one material ``_layer_as_fringe`` renders
    if fringe_correction and coat_hint is None and sign < 0 and not held and _thin_layer(fitter, st, pixel_size):
        coat_test, fringe = _layer_as_fringe(prob, fitter, st, coat_test, fringe, pixel_size)
    prob.map_c = None
    return _result(prob, fitter, st, JTJ, names, n_it, hpx, coat_test, pixel_size, fringe)


def _defocus_fringes(prob, fit, single, pixel_size, coat_hint, sign):
    """The fringe correction of the polished ``fit`` (fitter, state, J^T J, names, coating test) and the
    coated alternative where a layer may have been read as a fringe (module doc); returned as (fitter,
    state, J^T J, names, coating test, fringe).  With the defocus's sign given (``sign``), the correction
    is fitted at both signs first, as without it, and again at the given sign only where it took the
    other one (``free_A_px2`` keeps what it took then; module doc, "The sign of the defocus given")."""
    fitter, st, JTJ, names, coat_test = fit
    fringe = fringe_offset(prob, fitter, st, pixel_size)
    free = fringe
    if sign and fringe["A_px2"] * sign < 0:
        signed = fringe_offset(prob, fitter, st, pixel_size, sign=sign)
        # the sign given and the fit of both signs disagree: either may be wrong (a wrong sign given moved
        # the grid's median edge 0.30 -> 0.54 nm), so the edge carries half the two edges' distance
        moved = (signed["offset_px"] if signed["applied"] else 0.0) - (free["offset_px"] if free["applied"] else 0.0)
        fringe = dict(signed, free_A_px2=free["A_px2"], conflict_sd_px=0.5 * abs(moved))
    elif sign:
        fringe["sign"] = int(sign)
    if coat_hint is None and _layer_may_be_read_as_fringe(fitter, st, free):
        alt = _coated_alternative(prob, single, st, fringe, pixel_size, sign)
        if alt is not None:
            return alt
    if coat_hint is None and not fitter.coated and fringe.get("applied"):  # a layer only the rendering sees
        _, _, k0, max_coat, _ = single
        lim2 = _bounds(prob.K, k0, max_coat, True)
        alt = held_layer(prob, fitter, st, fringe, pixel_size, lim2, sign)
        if alt is not None:
            return alt
    return fitter, st, JTJ, names, coat_test, fringe


def _thin_layer(fitter, st, pixel_size):
    """Whether ``fitter`` is the coated model with a layer thinner than ``LAYER_AS_FRINGE_MAX``."""
    return bool(fitter.coated and fitter.unpack(st.v)[4] * (pixel_size or 0.25e-9) < LAYER_AS_FRINGE_MAX)


def _layer_as_fringe(prob, fitter, st, coat_test, fringe, pixel_size):
    """With an overfocus given, the thin light layer of a coated fit may be the dark fringe just
    outside an uncoated edge (module doc, "A light layer that is the dark fringe"): the fitted outer
    curve rendered as one material at that sign is taken where its chi^2 is below the coated body's
    rendering (``fringe``, or rendered now at that sign where the fit's chi^2 left it out) by more
    than ``MIN_DCHI2``.  Returns (coating test, fringe): as they were, or with ``layer_as_fringe``."""
    coated = fringe or fringe_offset(prob, fitter, st, pixel_size, sign=-1)
    cost = coated["chi2"] if coated["applied"] else coated["chi2_beer_lambert"]
    one = fringe_offset(prob, fitter, st, pixel_size, sign=-1, one_material=True)
    if not (one["applied"] and one["chi2"] < cost - FRINGE_MIN_DCHI2):
        return coat_test, fringe
    one.update(layer_as_fringe_dchi2=cost - one["chi2"], layer_px=float(fitter.unpack(st.v)[4]))
    if "free_A_px2" in fringe:
        one.update(free_A_px2=fringe["free_A_px2"], conflict_sd_px=fringe["conflict_sd_px"])
    return dict(coat_test, layer_as_fringe=True), one


def _layer_may_be_read_as_fringe(fitter, st, fringe):
    """Whether the fringe correction (of both signs, ``fringe``) of a one-material fit may have read a
    light layer as the dark fringe of an overfocus (module doc, "A layer read as a fringe"): applied, at
    lambda x df < 0 or with an overfocus within ``OVERFOCUS_MARGIN`` of the best start after the screen's
    steps, on a fit with no layer whose blur sits at its floor (so the coating search left no room for a
    layer)."""
    overfocus = fringe["A_px2"] < 0 or fringe["screen_chi2_overfocus"] <= (1 + OVERFOCUS_MARGIN) * fringe["screen_chi2"]
    return bool(
        not fitter.coated and fringe.get("applied") and overfocus and fitter.unpack(st.v)[1] <= 1.05 * BLUR_FLOOR_PX
    )


def _coated_alternative(prob, single, st, fringe, pixel_size, sign=0):
    """The coated model with every layer thickness tried, polished and rendered coherently
    (``fringe_offset``, at the defocus's sign if given); returned as (fitter, state, J^T J, names,
    coating test, fringe) where its chi^2 is below that of the one-material fit's rendering (``st``,
    ``fringe``: coherent where applied, else Beer-Lambert), else None.  With the sign of the defocus given
    against the fit of both signs, the one-material correction's conflict term (``free_A_px2``,
    ``conflict_sd_px``) is carried over, as ``held_layer`` and ``_layer_as_fringe`` do: the coated body's
    own fit of both signs is not made, so whether the sign given is right is as open as before."""
    f1, st1, k0, max_coat, max_iter = single
    f2 = _Fitter(prob, coated=True)
    lim2 = _bounds(prob.K, k0, max_coat, True)
    st2, _, test = _coating_search(f1, st1, f2, lim2, None, max_coat, max_iter, blur_room=False)
    if st2 is None or test["model"] != "coated":
        return None
    prob.map_c = None
    st2, JTJ2, names2 = f2.polish(st2, *lim2)
    fr2 = fringe_offset(prob, f2, st2, pixel_size, sign=sign)
    cost1 = fringe["chi2"] if fringe["applied"] else fringe["chi2_beer_lambert"]  # the one-material fit's
    cost2 = fr2["chi2"] if fr2["applied"] else fr2["chi2_beer_lambert"]
    if cost2 >= cost1:
        return None
    if "free_A_px2" in fringe:  # the sign given against the fit of both signs: its conflict term stays
        fr2.update(free_A_px2=fringe["free_A_px2"], conflict_sd_px=fringe["conflict_sd_px"])
    nm = 1e9 * (pixel_size or float("nan"))
    test["layer_not_fringe"] = True
    test["note"] = (
        f"a light layer, not a fringe: the one-material fit's fringe correction took lambda x defocus "
        f"{fringe.get('free_A_px2', fringe['A_px2']) * nm**2:+.1f} nm^2 "
        f"({_free_sign_words(fringe)}) and moved the edge "
        f"{fringe['offset_px'] * nm:+.2f} nm; "
        f"the coated model ({test['thickness_px'] * nm:.2f} nm layer), rendered coherently too, fits the image "
        f"better (chi^2 {cost2:.0f} against {cost1:.0f})"
    )
    return f2, st2, JTJ2, names2, test, fr2


def _free_sign_words(fringe):
    """What the one-material fit's correction (of both signs, ``fringe``) said about the sign, in words, for
    the coated alternative's note."""
    if "free_A_px2" in fringe:
        return "against the sign given"
    if fringe["A_px2"] < 0:
        return "overfocus"
    return f"underfocus, with an overfocus within {100 * OVERFOCUS_MARGIN:g} % of it in chi^2"


def _fit_binned(
    flat,
    contour,
    frame,
    hpx,
    noise,
    pixel_size,
    coat_hint,
    knot_nm,
    max_iter,
    b,
    fringe_correction=True,
    censored=None,
    sign=0,
):
    """``fit_silhouette`` on b x b blocks, its result in the pixels of ``flat`` (a block with a
    clipped pixel is censored: its mean is a lower bound too)."""
    off = 0.5 * (b - 1)
    gf = _fit_pixels(
        _bin(np.asarray(flat, float), b),
        (np.asarray(contour) - off) / b,
        TipFrame((frame.apex - off) / b, frame.angle),
        hpx / b,
        noise / b,
        pixel_size * b,
        None if coat_hint is None else coat_hint / b,
        knot_nm,
        max_iter,
        fringe_correction,
        None if censored is None else _bin(np.asarray(censored, float), b) > 0,
        sign,
    )
    gf.points = gf.points * b + off
    gf.frame = TipFrame(gf.frame.apex * b + off, gf.frame.angle)
    gf.cov_c = gf.cov_c * b**2
    gf.sigma_px, gf.coat_px = gf.sigma_px * b, gf.coat_px * b
    gf.k_outer, gf.k_core = gf.k_outer / b, gf.k_core / b
    gf.binning = b
    ct = gf.coating_test
    for key in ("thickness_px", "outer_shift_px", "ambiguous_shift_px", "ambiguous_thickness_px"):
        if key in ct:
            ct[key] *= b
    fr = gf.fringe
    for key in ("offset_px", "offset_sd_px", "model_sd_px", "sigma_px", "layer_px", "conflict_sd_px", "shape_move_px"):
        if key in fr:
            fr[key] = fr[key] * b
    if "A_px2" in fr:
        fr["A_px2"] *= b**2
        fr["eta"] /= b
    if "shape_A_px2" in fr:
        fr["shape_A_px2"] *= b**2
    if "free_A_px2" in fr:
        fr["free_A_px2"] *= b**2
    if "candidates_px" in ct:
        ct["candidates_px"] = [t * b for t in ct["candidates_px"]]
    return gf


def _bounds(K, k0, max_coat, coated):
    """(lower, upper bounds, maximum steps) of (c_1..c_K, log sigma, log k_o[, log k_c, log coat])."""
    lb = [-6.0] * K + [np.log(BLUR_FLOOR_PX), np.log(k0 * 0.05)]
    ub = [6.0] * K + [np.log(4.0), np.log(k0 * 20)]
    ms = [0.6] * K + [0.25, 0.3]
    if coated:
        lb += [np.log(k0 * 0.05), np.log(0.5)]
        ub += [np.log(k0 * 20), np.log(max_coat)]
        ms += [0.3, 0.25]
    return np.array(lb), np.array(ub), np.array(ms)


def _single_layer_fit(prob, k0, max_coat, max_iter):
    """(fitter, state, iterations) of the single-layer model (steps 1 and 2 of ``fit_silhouette``);
    ``prob`` is rebased on the fitted shape."""
    K = prob.K
    n_it = 0
    # 1) single layer, uniform offset from the contour + globals, two blur starts
    f1 = _Fitter(prob, coated=False)
    lim1 = _bounds(K, k0, max_coat, False)
    best = None
    for sg in (0.8, 2.0):  # two blur starts, 2 iterations each; the better one goes on
        v = np.concatenate([np.full(K, -1.0), [np.log(sg), np.log(k0)]])
        st, _, _, it = f1.run(v, "uniform", 2, *lim1, tol=1e-4)
        n_it += it
        if best is None or st.cost < best.cost:
            best = st
    best, _, _, it = f1.run(best.v, "uniform", 6, *lim1, tol=1e-4)
    n_it += it
    prob.set_weights(prob.model(best.B, best.lin))
    # 2) single layer, full shape; then again relative to the fitted shape (the penalty
    #    on the offsets' curvature would otherwise keep the contour's rounded corners)
    st1, _, _, it = f1.run(best.v, "full", max_iter, *lim1)
    n_it += it
    prob.rebase(st1.v[:K])
    glob = st1.v[K:]
    K = prob.K
    f1 = _Fitter(prob, coated=False)
    lim1 = _bounds(K, k0, max_coat, False)
    st1, _, _, it = f1.run(np.concatenate([np.zeros(K), glob]), "full", max_iter, *lim1)
    n_it += it
    return f1, st1, n_it


def _saturation(prob, st, pixel_size):
    """(words, common edge-offset SD in px) of a fit with censored (clipped) pixels.  Where most of
    the fitted vacuum beside the edge is clipped, the vacuum level is only known to be above full
    scale, and the outermost part of the tip (a light oxide, the thin rim) that transmits more than
    full scale / vacuum is not seen: its width is not in the image.  The edge then carries a common
    offset of ``SATURATED_EDGE_SD_NM`` (measured on the independent simulator, module doc)."""
    n_cens = int(np.count_nonzero(prob.cens))
    vac = st.T[prob.res_in_need] >= 0.999  # fitted pixels outside the body (the model's vacuum)
    share = float(np.mean(prob.cens[vac])) if vac.any() else 0.0
    words = (
        f"saturated detector: {n_cens} of the {prob.idx.size} fitted pixels "
        f"({100.0 * n_cens / prob.idx.size:.0f} %) read full scale and were fitted as lower bounds"
    )
    if share < SATURATED_VACUUM_SHARE:
        return words + f" ({100 * share:.0f} % of the vacuum beside the edge)", 0.0
    px = float(pixel_size or 0.25e-9)
    return (
        words + f"; the vacuum beside the edge is clipped ({100 * share:.0f} %), so a light layer or the "
        "tip's outer rim brighter than full scale is not seen: the edge carries a common uncertainty of "
        f"{SATURATED_EDGE_SD_NM:.1f} nm for it",
        SATURATED_EDGE_SD_NM * 1e-9 / px,
    )


def _result(prob, fitter, st, JTJ, names, n_it, hpx, coat_test, pixel_size=None, fringe=None):
    c, sigma, k_o, k_c, coat = fitter.unpack(st.v)
    K = prob.K
    chi2, stderr, cov_c, flags = _covariances(prob, fitter, st, JTJ, names, coat_test, pixel_size)
    if coat_test.get("layer_not_fringe"):
        flags.append(coat_test["note"])
    fringe = fringe or {}
    if "free_A_px2" in fringe:
        flags.append(_against_the_sign_words(fringe, pixel_size))
        cov_c = cov_c + fringe["conflict_sd_px"] ** 2 * np.ones((K, K))
    if "layer_as_fringe_dchi2" in fringe:
        flags.append(_layer_as_fringe_words(fringe, pixel_size))
    hit = np.nonzero(np.abs(c) >= 5.99)[0]
    if hit.size:
        flags.append(f"edge offset hit its bound (+-6 px) at {hit.size} of {K} knots")
    if prob.cens is not None:
        words, sd_px = _saturation(prob, st, pixel_size)
        flags.append(words)
        cov_c = cov_c + sd_px**2 * np.ones((K, K))
    if fringe.get("applied"):
        # the coherent rendering moves the edge (a uniform offset, then its shape refitted): the offset's
        # standard error is a common offset of the whole edge, and the model error of the move
        # (``fringe_correction.MOVE_SD_SHARE`` of it) a mode along the move's own shape (``fringe_shape``)
        shape = fringe_shape(prob, fitter, st, fringe, pixel_size, hpx)
        fringe.update(_shape_record(shape))
        mode = MOVE_SD_SHARE * shape["move_px"]
        cov_c = cov_c + fringe["offset_sd_px"] ** 2 * np.ones((K, K)) + np.outer(mode, mode)
        flags.append(_fringe_words(fringe, pixel_size))
        c = shape["c"]
    pts, nrm, basis = _outer_silhouette(prob, c, hpx)
    rms = float(np.sqrt(np.sum((st.res / prob.w) ** 2) / max(1, prob.n_data(st.B, st.lin))))
    return GlobalFit(
        pts,
        nrm,
        basis,
        cov_c,
        prob.frame,
        float(sigma),
        float(k_o),
        float(k_c),
        float(coat),
        rms,
        chi2,
        int(prob.idx.size),
        int(n_it),
        stderr,
        flags,
        coat_test,
        fringe=fringe,
    )


def _fringe_words(fr, pixel_size):
    """The flag of an applied defocus-fringe correction (its uniform offset, then its shape refitted)."""
    nm = 1e9 * (pixel_size or float("nan"))
    if fr.get("sign"):
        why = f"the sign of the defocus was given ({_FOCUS[fr['sign']]}); the rendering's own model error is taken as"
    else:
        why = (
            "the sign of the defocus is not always identified (a light layer can read as a fringe), so the edge "
            "carries an uncertainty of"
        )
    shape = ""
    if fr.get("shape_dchi2", 0.0) <= 0.0 and "shape_move_px" in fr:
        shape = "; its shape refitted with that rendering: no step lowered chi^2, the uniform offset is kept"
    elif "shape_move_px" in fr:
        beyond = np.asarray(fr["shape_move_px"]) - fr["offset_px"]
        shape = (
            f"; then the edge's shape refitted with that rendering (chi^2 -{fr['shape_dchi2']:.0f} more; beyond the "
            f"uniform offset the edge moved by up to {np.max(np.abs(beyond)) * nm:.2f} nm"
            + ("" if fr["shape_converged"] else f", not converged in {fr['shape_iterations']} steps")
            + ")"
        )
    return (
        f"defocus fringes: edge moved {fr['offset_px'] * nm:+.2f} +- {fr['offset_sd_px'] * nm:.2f} nm (noise) by a "
        f"coherent rendering of the fitted body (lambda x defocus {fr['A_px2'] * nm**2:+.1f} nm^2, i.e. "
        f"{fr['A_px2'] * nm**2 / 2.51:+.2f} um at 200 kV; chi^2 -{fr['dchi2']:.0f}){shape}; {why} "
        f"half the move, up to {MOVE_SD_SHARE * np.max(np.abs(fr.get('shape_move_px', fr['offset_px']))) * nm:.2f} nm"
    )


def _shape_record(shape):
    """What ``fringe_shape`` adds to the fringe record (``fringe`` of the fit)."""
    return dict(
        shape_move_px=shape["move_px"],
        shape_dchi2=shape["chi2_uniform"] - shape["chi2"],
        shape_A_px2=shape["A_px2"],
        shape_iterations=shape["iterations"],
        shape_converged=shape["converged"],
    )


_FOCUS = {1: "underfocus", -1: "overfocus"}


def _layer_as_fringe_words(fr, pixel_size):
    """The flag of a thin light layer read as the dark fringe of the overfocus given."""
    nm = 1e9 * (pixel_size or float("nan"))
    return (
        f"a fringe, not a light layer: the light layer the fit found ({fr['layer_px'] * nm:.2f} nm) is read as the "
        f"dark fringe of the overfocus given; the outer curve rendered as one material at that sign fits better "
        f"(chi^2 -{fr['layer_as_fringe_dchi2']:.0f} against the coated body rendered), so the edge is that body's"
    )


def _against_the_sign_words(fr, pixel_size):
    """The flag of a fringe fit of both signs that took the other sign than the one given."""
    nm2 = (1e9 * (pixel_size or float("nan"))) ** 2
    return (
        f"defocus given as {_FOCUS[fr['sign']]}: the fringe fit of both signs took lambda x defocus "
        f"{fr['free_A_px2'] * nm2:+.1f} nm^2 ({_FOCUS[-fr['sign']]}; a light layer or the edge model's error can "
        f"read as the fringe of the other sign), so the fringes were fitted at the given sign "
        f"({fr['A_px2'] * nm2:+.1f} nm^2{'' if fr['applied'] else ', not applied: no better than no fringe'}); "
        f"as the given sign may be the wrong one, the edge carries half the distance between the two fits' "
        f"edges, {fr['conflict_sd_px'] * nm2**0.5:.2f} nm, as a common uncertainty (check the sign if most "
        f"intervals say this)"
    )


def _covariances(prob, fitter, st, JTJ, names, coat_test, pixel_size):
    """chi^2 per degree of freedom, the standard errors of the non-edge parameters, the edge
    offsets' covariance (widened where the coating is ambiguous) and the flags."""
    K = prob.K
    dof = max(1, prob.n_data(st.B, st.lin) - len(names))
    chi2 = float(st.res @ st.res) / dof
    flags, stderr = [], {}
    try:
        cov = np.linalg.inv(JTJ) * max(chi2, 1.0)
    except np.linalg.LinAlgError:
        cov = np.full(JTJ.shape, np.nan)
        flags.append("singular silhouette covariance" + _flat_model_words(st))
    sd = np.sqrt(np.clip(np.diag(cov), 0, None))
    for nm, s in zip(names, sd):
        if not nm.startswith("c"):
            stderr[nm] = float(s)
    cov_c = cov[:K, :K]
    if coat_test.get("ambiguous"):
        # the outer edge is either the single layer's or ~outer_shift further out: widen the
        # edge covariance by a common offset of half that shift (SD of a 50/50 mixture)
        shift = coat_test["ambiguous_shift_px"]
        cov_c = cov_c + (0.5 * shift) ** 2 * np.ones((K, K))
        nm = 1e9 * (pixel_size or float("nan"))
        flags.append(
            f"coating ambiguous: a light layer {coat_test['ambiguous_thickness_px'] * nm:.2f} nm thick changes "
            f"chi^2 by {-coat_test['ambiguous_dchi2']:+.1f} (accepted below -{COAT_DCHI2:g}, excluded above "
            f"+{COAT_DCHI2:g}); "
            f"the edge may lie up to {shift * nm:.2f} nm further out; edge covariance widened "
            f"(set tem.coating if the layer is known)"
        )
    if fitter.coated:
        if stderr.get("log_coat", 0) > 0.3 or stderr.get("log_k_c", 0) > 0.3:
            flags.append(f"coating not identifiable (rel. s.e. thickness {stderr.get('log_coat', np.nan):.2f})")
    return chi2, stderr, cov_c, flags


EDGE_NOT_FITTED_WORDS = "the edge is the starting contour, not fitted"


def edge_not_fitted(flags) -> bool:
    """True where the silhouette fit's flags say its body reached none of the fitted pixels, so the
    edge is the starting contour (``_flat_model_words``), not a fit to the image."""
    return any(EDGE_NOT_FITTED_WORDS in f for f in flags)


def _flat_model_words(st):
    """Why J^T J is singular where the model body reaches none of the fitted pixels (T = 1 everywhere:
    blur and attenuation change nothing; grid image 35 of bench_tem_independent, a 16.6 nm DLC layer
    of contrast 0.09 at 0.1 nm px, whose band holds only the layer's slow intensity ramp, fitted by
    the illumination gradient), else nothing."""
    if np.ptp(st.T) > 1e-9:
        return ""
    return (
        ": the fitted body reaches none of the fitted pixels (no sharp edge in the band; the illumination "
        f"gradient took the intensity ramp): {EDGE_NOT_FITTED_WORDS}"
    )


def _outer_silhouette(prob, c, hpx):
    """Outer silhouette at 1 px spacing in arc length, z <= 1.3 x profile height: points and
    normals in the image, the edge offsets' basis there."""
    x, z = prob.curve(c)
    S = prob.S
    sel = z <= 1.3 * hpx
    i = np.nonzero(sel)[0]
    i = np.arange(i.min(), i.max() + 1)
    s_arc = np.concatenate([[0.0], np.cumsum(np.hypot(np.diff(x[i]), np.diff(z[i])))])
    so = np.arange(0.0, s_arc[-1], 1.0)
    xo, zo = np.interp(so, s_arc, x[i]), np.interp(so, s_arc, z[i])
    Sg = np.interp(so, s_arc, S[i])
    basis = _bspline(Sg[:, None] / prob.knot - prob.kc[None, :])
    nxo, nzo = np.interp(Sg, S, prob.nx), np.interp(Sg, S, prob.nz)
    pts = prob.frame.to_image(xo, zo)
    nrm = np.column_stack(
        [nxo * prob.frame.v[0] + nzo * prob.frame.u[0], nxo * prob.frame.v[1] + nzo * prob.frame.u[1]]
    )
    return pts, nrm, basis
