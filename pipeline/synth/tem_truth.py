"""Compare an extracted profile with the known truth of a synthetic image (tests, benchmark)."""

from __future__ import annotations

import math

import numpy as np
from scipy.spatial import cKDTree

from pipeline.synth.tem_image import outer_radius

HEIGHTS = np.linspace(1e-9, 6e-9, 11)  # default heights h (m) of the pull-off area errors

__all__ = ["profile_errors", "force_errors", "reported_uncertainty", "coating_decision", "evaluate_case"]


def _true_tip_coords(edge_px, truth):
    px = truth["pixel_size"]
    th = math.radians(truth["rotation_deg"])
    r_a, c_a = truth["apex_px"]
    sgn = 1.0 if truth["orientation"] == "down" else -1.0
    dx = (edge_px[:, 1] - c_a) * px
    dy = sgn * (r_a - edge_px[:, 0]) * px
    return dx * math.cos(th) + dy * math.sin(th), -dx * math.sin(th) + dy * math.cos(th)


def profile_errors(profile, truth, height):
    """Errors (m) of the extracted silhouette against the true outer surface, z <= height.

    Returns dict: rms_normal (RMS shortest distance to the true meridian curve),
    rms_r (RMS of |x| - r_true(z), points with z >= 0.5 nm where r(z) is well
    defined), bias_normal (mean signed distance, + = outside), apex_dz, axis_deg.
    """
    x, z = _true_tip_coords(profile.edge_px, truth)
    sel = z <= height
    x, z = x[sel], z[sel]
    if x.size == 0:
        raise ValueError("no extracted edge points within the fit window")
    # sample the meridian densely in z AND in r (flat apices: r(z) is steep near z = 0)
    zt = np.linspace(0, height * 1.3, 20001)
    rt = outer_radius(zt, truth["n"], truth["Q"], truth.get("cone_above", 25e-9))
    rr = np.linspace(0, rt[-1], 20001)
    zr = rr ** truth["n"] / (truth["n"] * truth["Q"])
    ok = zr <= truth.get("cone_above", 25e-9)
    zt, rt = np.concatenate([zt, zr[ok]]), np.concatenate([rt, rr[ok]])
    o = np.argsort(zt)
    zt, rt = zt[o], rt[o]
    curve = np.concatenate([np.column_stack([-rt[::-1], zt[::-1]]), np.column_stack([rt, zt])])
    d, idx = cKDTree(curve / 1e-9).query(np.column_stack([x, z]) / 1e-9)
    d = d * 1e-9
    rtrue = np.interp(z, zt, rt)
    outside = np.abs(x) > rtrue
    sd = np.where(outside, d, -d)
    m = z >= 0.5e-9
    dr = np.abs(x[m]) - rtrue[m]
    ang = math.degrees(profile.angle)
    return dict(
        rms_normal=float(np.sqrt(np.mean(d**2))),
        bias_normal=float(sd.mean()),
        rms_r=float(np.sqrt(np.mean(dr**2))) if dr.size else float("nan"),
        apex_dz=float(_true_tip_coords(profile.apex_px[None, :], truth)[1][0]),
        axis_deg_err=float(ang - truth["rotation_deg"]),
    )


def force_errors(n_fit, Q_fit, truth, heights=HEIGHTS):
    """Relative error of the rigid Dugdale pull-off area pi (n h Q)^(2/n) (Eq. 12) vs truth, per h."""
    from pipeline.fits.power_law import rigid_dugdale_area

    f_fit = rigid_dugdale_area(n_fit, Q_fit, heights)
    f_true = rigid_dugdale_area(truth["n"], truth["Q"], heights)
    return f_fit / f_true - 1.0


def reported_uncertainty(profile, fit, heights=HEIGHTS, fit_height=6e-9):
    """What the pipeline reports as its own uncertainty (SI), to judge an error against.

    Returns dict: sigma_n; sigma_force (largest relative SD over ``heights`` of the rigid
    Dugdale pull-off area, Eq. 12, from cov(n, ln Q)); edge_sd (RMS over the points of the
    fit window of the predicted SD of each point's normal offset, from the edge covariance;
    NaN without one).
    """
    from pipeline.fits.power_law import rigid_dugdale_log_gradient

    g = rigid_dugdale_log_gradient(fit.n, fit.Q, heights)
    sd_f = np.sqrt(np.einsum("hi,ij,hj->h", g, np.asarray(fit.cov_n_lnQ), g))
    edge_sd = float("nan")
    if profile.offset_basis is not None and profile.offset_cov is not None:
        m = profile.z <= fit_height
        B = profile.offset_basis[m]
        edge_sd = float(np.sqrt(np.mean(np.einsum("ij,jk,ik->i", B, profile.offset_cov, B))))
    return dict(sigma_n=float(fit.sigma_n), sigma_force=float(np.max(sd_f)), edge_sd=edge_sd)


def coating_decision(profile):
    """The edge model's light-layer decision: "found" (coated model kept), "flagged" (coating
    ambiguous: neither found nor excluded) or "single" (no layer, unflagged)."""
    ct = profile.edge_model.get("coating_test") or {}
    if ct.get("model") == "coated":
        return "found"
    return "flagged" if ct.get("ambiguous") else "single"


TIP_SHAPES = {2: 10e-9, 3: 15e-9, 4: 20e-9, 5: 22e-9, 6: 25e-9}  # n -> R (m), S = 1


def evaluate_case(
    n,
    pixel_size,
    blur_sigma_px=1.0,
    edge_snr=20.0,
    rotation_deg=3.0,
    coating_thickness=0.0,
    orientation="down",
    seed=0,
    R=None,
    fit_height=6e-9,
    profile_height=20e-9,
    shape=None,
    coating="auto",
    **kw,
):
    """Render a synthetic image with known truth, extract + fit; return the error metrics (SI)
    and the pipeline's own reported uncertainty (``reported``, see ``reported_uncertainty``).
    ``coating``: what the extraction is told ("auto", "none" or a thickness in m)."""
    import time

    from pipeline.fits.profile_fit import fit_tip_profile
    from pipeline.synth.tem_image import render_tem_image
    from pipeline.tem.profiles import extract_profile
    from pipeline.tem.reading import TemImage

    R = R or TIP_SHAPES.get(int(round(n)), 20e-9)
    Q = R ** (n - 1)
    if shape is None:
        side = int(np.clip(np.ceil(95e-9 / pixel_size / 32) * 32, 384, 1024))
        shape = (side, side)
    img, truth = render_tem_image(
        n,
        Q,
        pixel_size,
        shape=shape,
        blur_sigma_px=blur_sigma_px,
        edge_snr=edge_snr,
        rotation_deg=rotation_deg,
        coating_thickness=coating_thickness,
        orientation=orientation,
        seed=seed,
        **kw,
    )
    t0 = time.perf_counter()
    prof = extract_profile(
        TemImage(img.astype(np.float64), pixel_size, "synthetic"), profile_height=profile_height, coating=coating
    )
    t_prof = time.perf_counter() - t0
    fit = fit_tip_profile(prof, fit_height)
    pe = profile_errors(prof, truth, fit_height)
    fe = force_errors(fit.n, fit.Q, truth)
    return dict(
        truth=truth,
        profile=prof,
        fit=fit,
        t_profile=t_prof,
        rms_normal=pe["rms_normal"],
        rms_r=pe["rms_r"],
        bias=pe["bias_normal"],
        apex_dz=pe["apex_dz"],
        axis_deg_err=pe["axis_deg_err"],
        dn=fit.n - n,
        force_err_max=float(np.max(np.abs(fe))),
        sigma_n=fit.sigma_n,
        flags=fit.flags,
        edge_flags=list(prof.edge_model.get("global_flags", [])),
        coating_ambiguous=bool((prof.edge_model.get("coating_test") or {}).get("ambiguous", False)),
        reported=reported_uncertainty(prof, fit, fit_height=fit_height),
    )
