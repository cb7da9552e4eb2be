"""Grade what the TEM stage extracts from an independent simulator image
(``pipeline.synth.tem_wave``) against that image's truth.

Metrics (SI units):
- edge: distance of every extracted edge point (``TipProfile.edge_px``) that stage 2 fits
  (within 6 nm of the stage's own apex) to the true OUTER silhouette (coating included,
  contamination excluded), measured in the image
  plane to the nearest segment of the dense true curve: RMS overall and per flank (by the
  side of the true axis a point lies on), signed mean (+ = outside the tip), max; the reported SD
  of that mean (the edge covariance, ``common_offset_sd``) and whether it covers the signed mean
  at 2 sigma;
- apex: distance of the reported apex from the true one, and its component along the true
  axis; the axis angle error (deg);
- shape: n from stage 2 minus the true n; |dn| <= 2 sigma_n (coverage); n of the same
  stage-2 fit on the exact true silhouette (what a perfect edge would give: the floor set
  by the power law, the asymmetry and the 6 nm window);
- pull-off: the rigid Dugdale area factor pi (n h Q)^(2/n) (paper Eq. 12) of the fitted
  shape against the true section area pi r(h)^2 (1 + e^2/2) at h = 1..6 nm: max relative
  error, and whether the reported SD (from cov(n, ln Q)) covers it at 2 sigma, linearly and with
  (n, ln Q) drawn as the inversion draws them (``pulloff_covered_by_samples``);
- chi2_red: the silhouette fit's reduced chi^2 (how far the image is from the edge model); blur_sigma:
  its fitted Gaussian blur (m); start_fold_share, start_level, dim_zone: its starting contour
  (``pipeline.tem.start_contour``: the first level's fold share, the level the fit started from, and
  where the first level folded, its median distance beyond the final edge, m); bright_band: the
  width of the band beyond the edge's blur brighter than the vacuum (``pipeline.tem.faint_layer``, m);
  fringe_shape_steps: the steps of the edge's shape refit to the fringes (``pipeline.tem.fringe_shape``;
  NaN where the fringe correction was not applied);
- lost: the interval cannot be used -- the stage raised (reason: its message), or the
  stage-2 fit carries a flag that makes the inversion drop it
  (``pipeline.inversion.UNUSABLE_FIT_FLAGS``), or the n policy rejects it (``clip_n``).

``evaluate_file`` runs an image file through the workflow's own path: ``read_tem_image``
-> ``extract_profile`` (workflow defaults) -> profile HDF5 -> ``pipeline.fits.stage.run_fit`` ->
the fit HDF5 read back, and grades it.
"""

from __future__ import annotations

import math
import tempfile
import time
from pathlib import Path

import numpy as np
from scipy.spatial import cKDTree

__all__ = [
    "tip_frame",
    "true_section_area",
    "edge_errors",
    "ideal_fit",
    "grade",
    "sigma_n",
    "lost_reason",
    "evaluate_file",
    "plot_comparison",
    "HEIGHTS",
]

HEIGHTS = np.linspace(1e-9, 6e-9, 11)  # m, Eq. 12 pull-off heights h


def tip_frame(points_px, truth):
    """Image (row, col) points -> TRUE tip frame (x, z) in m (x > 0 right flank, z up the tip)."""
    pts = np.atleast_2d(np.asarray(points_px, float))
    px = truth["pixel_size"]
    th = math.radians(truth["rotation_deg"])
    sgn = 1.0 if truth["orientation"] == "down" else -1.0
    r_a, c_a = truth["apex_px"]
    dx = (pts[:, 1] - c_a) * px
    dy = sgn * (r_a - pts[:, 0]) * px
    return dx * math.cos(th) + dy * math.sin(th), -dx * math.sin(th) + dy * math.cos(th)


def _flank_radii(truth, z):
    zf = np.asarray(truth["flank_z"])
    return (
        np.interp(z, zf, np.asarray(truth["flank_r_left"]), left=np.nan),
        np.interp(z, zf, np.asarray(truth["flank_r_right"]), left=np.nan),
    )


def true_section_area(truth, h):
    """True outer section area (m^2) at heights h: pi r^2 (1 + e^2/2), r the mean flank radius."""
    rl, rr = _flank_radii(truth, np.asarray(h, float))
    return np.pi * (0.5 * (rl + rr)) ** 2 * (1.0 + 0.5 * truth["asymmetry"] ** 2)


def _segment_distance(curve, q):
    """Distance of points q (N, 2) to the polyline ``curve`` (M, 2), via the nearest vertex's
    two segments."""
    _, j = cKDTree(curve).query(q)
    best = np.full(len(q), np.inf)
    for a_idx, b_idx in ((j - 1, j), (j, j + 1)):
        ok = (a_idx >= 0) & (b_idx < len(curve))
        a = curve[np.clip(a_idx, 0, len(curve) - 1)]
        b = curve[np.clip(b_idx, 0, len(curve) - 1)]
        ab = b - a
        L2 = np.maximum(np.einsum("ij,ij->i", ab, ab), 1e-300)
        t = np.clip(np.einsum("ij,ij->i", q - a, ab) / L2, 0.0, 1.0)
        d = np.hypot(*(q - a - t[:, None] * ab).T)
        best = np.where(ok, np.minimum(best, d), best)
    return best


def edge_errors(edge_px, truth, select=None):
    """Distances (m) of edge points (image (row, col); ``select``: boolean mask of the points
    to grade, e.g. those stage 2 fits) to the true outer silhouette (see module doc).
    Returns dict rms, rms_left, rms_right, bias, max, n_points."""
    x, z = tip_frame(edge_px, truth)
    if select is not None:
        x, z = x[select], z[select]
    if x.size == 0:
        return dict(rms=np.nan, rms_left=np.nan, rms_right=np.nan, bias=np.nan, max=np.nan, n_points=0)
    curve = np.asarray(truth["silhouette_tip"]) / 1e-9
    d = _segment_distance(curve, np.column_stack([x, z]) / 1e-9) * 1e-9
    rl, rr = _flank_radii(truth, z)
    inside = (z > 0) & (x < np.nan_to_num(rr, nan=-np.inf)) & (x > -np.nan_to_num(rl, nan=-np.inf))
    sd = np.where(inside, -d, d)

    def rms(v):
        return float(np.sqrt(np.mean(v**2))) if v.size else float("nan")

    return dict(
        rms=rms(d),
        rms_left=rms(d[x < 0]),
        rms_right=rms(d[x >= 0]),
        bias=float(sd.mean()),
        max=float(d.max()),
        n_points=int(x.size),
    )


def ideal_fit(truth, fit_height=6e-9, spacing=0.05e-9):
    """Stage-2 fit (``pipeline.fits.profile_fit.fit_power_law``) of the exact true silhouette, both flanks,
    points evenly spaced along the curve (as edge points are) up to ``fit_height``."""
    from pipeline.fits.profile_fit import fit_power_law

    xz = np.asarray(truth["silhouette_tip"], float)
    xz = xz[xz[:, 1] <= fit_height * 1.05]
    s = np.concatenate([[0.0], np.cumsum(np.hypot(*np.diff(xz, axis=0).T))])
    si = np.arange(0.0, s[-1], spacing)
    x, z = np.interp(si, s, xz[:, 0]), np.interp(si, s, xz[:, 1])
    side = np.where(x < 0, -1, 1)
    return fit_power_law(np.abs(x), z, fit_height, groups=side, flank=side)


def pulloff_covered_by_samples(fit, truth, heights=HEIGHTS, size=4000, seed=0):
    """Is the true area factor inside the central 95.4 % (2 sigma) of the rigid Dugdale area factors
    (Eq. 12) of (n, ln Q) drawn from the fit's covariance as the inversion draws them
    (``inversion.montecarlo.draw_interval``: normal, then the n < 2 policy ``clip_samples``), at every
    height?  The linear 2-SD test (``pulloff_covered``) misreads a skewed spread at large sigma_n."""
    from pipeline.fits.power_law import rigid_dugdale_area
    from pipeline.inversion.shape import clip_samples

    cov = np.asarray(fit.cov_n_lnQ, float)
    if not np.all(np.isfinite(cov)):
        return False
    nl = np.random.default_rng(seed).multivariate_normal([fit.n, fit.ln_Q], cov, size, method="eigh")
    n, ln_q = clip_samples(nl[:, 0], nl[:, 1], fit.S)
    ok = np.isfinite(n) & np.isfinite(ln_q)
    if ok.sum() < size // 2:
        return False
    h = np.asarray(heights, float)
    ratio = rigid_dugdale_area(n[ok, None], np.exp(ln_q[ok, None]), h[None, :]) / true_section_area(truth, h)
    lo, hi = np.percentile(ratio, [2.275, 97.725], axis=0)
    return bool(np.all((lo <= 1.0) & (1.0 <= hi)))


def common_offset_sd(profile, select):
    """Reported SD (m) of the mean normal offset of the edge points ``select``: sqrt(a C a^T), a the mean
    of the points' rows of ``offset_basis`` and C ``offset_cov`` (the edge covariance of stage 1, its
    common terms included: fringe, saturation, model error); NaN without a covariance (then
    ``edge_bias_covered`` is False: no claim is no cover)."""
    cov, basis = getattr(profile, "offset_cov", None), getattr(profile, "offset_basis", None)
    if cov is None or basis is None or not np.any(select):
        return float("nan")
    a = np.asarray(basis)[select].mean(axis=0)
    return float(math.sqrt(max(float(a @ np.asarray(cov) @ a), 0.0)))


def sigma_n(fit):
    """Reported SD of n: sqrt(cov(n, ln Q)[0, 0]) (``read_fit`` leaves ``fit.sigma_n`` NaN)."""
    c = np.asarray(fit.cov_n_lnQ, float)
    return float(math.sqrt(c[0, 0])) if np.isfinite(c[0, 0]) and c[0, 0] >= 0 else float("nan")


def lost_reason(fit):
    """Why the inversion would drop this interval ("" if it is used): stage-2 flags that make
    it unusable, or the n policy (n far below 2, above 20, not finite)."""
    from pipeline.inversion import UNUSABLE_FIT_FLAGS, clip_n

    bad = sorted(set(fit.flags) & UNUSABLE_FIT_FLAGS)
    if bad:
        return "fit flagged " + ",".join(bad)
    _, _, flag = clip_n(fit.n, fit.ln_Q, fit.S, sigma_n(fit))
    return "" if flag in ("ok", "n_clipped_to_2") else flag


def grade(profile, fit, truth, fit_height=6e-9, heights=HEIGHTS):
    """All metrics of the module doc for one extracted profile and its stage-2 fit."""
    from pipeline.fits.power_law import rigid_dugdale_area, rigid_dugdale_log_gradient

    e = edge_errors(profile.edge_px, truth, profile.z <= fit_height)  # the points stage 2 fits
    ax, az = tip_frame(profile.apex_px[None, :], truth)
    dn = fit.n - truth["n"]
    sn = sigma_n(fit)
    f_err = rigid_dugdale_area(fit.n, fit.Q, heights) / true_section_area(truth, heights) - 1.0
    g = rigid_dugdale_log_gradient(fit.n, fit.Q, heights)
    sd_f = np.sqrt(np.maximum(np.einsum("hi,ij,hj->h", g, np.asarray(fit.cov_n_lnQ), g), 0.0))
    ideal = ideal_fit(truth, fit_height)
    sd_bias = common_offset_sd(profile, profile.z <= fit_height)
    em = profile.edge_model
    ct = em.get("coating_test") or {}
    return dict(
        edge_rms=e["rms"],
        edge_rms_left=e["rms_left"],
        edge_rms_right=e["rms_right"],
        edge_bias=e["bias"],
        edge_max=e["max"],
        edge_bias_sd=sd_bias,
        edge_bias_covered=bool(abs(e["bias"]) <= 2 * sd_bias),
        edge_points=e["n_points"],
        apex_error=float(math.hypot(ax[0], az[0])),
        apex_dz=float(az[0]),
        axis_error_deg=float(math.degrees(profile.angle) - truth["rotation_deg"]),
        n_fit=float(fit.n),
        sigma_n=sn,
        dn=float(dn),
        n_covered=bool(abs(dn) <= 2 * sn),
        n_ideal=float(ideal.n),
        dn_ideal=float(ideal.n - truth["n"]),
        pulloff_error=float(np.max(np.abs(f_err))),
        pulloff_error_signed=float(f_err[np.argmax(np.abs(f_err))]),
        pulloff_covered=bool(np.all(np.abs(f_err) <= 2 * sd_f)),
        pulloff_covered_mc=pulloff_covered_by_samples(fit, truth, heights),
        fit_flags=list(fit.flags),
        edge_flags=list(em.get("global_flags", [])),
        coating_model=ct.get("model", ""),
        coating_ambiguous=bool(ct.get("ambiguous", False)),
        coating_found=float(em.get("coating_thickness", 0.0)),
        chi2_red=float(em.get("global_chi2_red", float("nan"))),
        blur_sigma=float(em.get("blur_sigma", float("nan"))),
        start_fold_share=float((em.get("start_contour") or {}).get("fold_share", float("nan"))),
        start_level=float((em.get("start_contour") or {}).get("start_level", float("nan"))),
        dim_zone=float((em.get("start_contour") or {}).get("dim_zone", float("nan"))),
        bright_band=float((em.get("faint_layer") or {}).get("bright_band", float("nan"))),
        fringe_shape_steps=float((em.get("global_fringe") or {}).get("shape_iterations", float("nan"))),
        lost=bool(lost_reason(fit)),
        lost_reason=lost_reason(fit),
    )


def lost_record(reason):
    """The record of an interval lost before grading (the stage raised)."""
    return dict(lost=True, lost_reason=reason)


def evaluate_file(
    image_path, truth, pixel_size=None, workdir=None, fit_height=6e-9, S=1.0, figure=None, defocus="auto"
):
    """Run ``image_path`` through the workflow path (module doc) and grade it.

    ``pixel_size`` (m) is what a tip YAML would give (used only for files without a
    calibration), and ``defocus`` its ``tem.defocus``; ``figure``: a PNG path for ``plot_comparison``.
    Returns the ``grade`` dict (or a lost record) plus ``t_stage`` (s: read, profile, fit) and ``t_profile``
    (s: extract_profile alone)."""
    from pipeline.fits import FitError
    from pipeline.fits.io import read_fit
    from pipeline.fits.stage import run_fit
    from pipeline.tem.io import write_profile_h5
    from pipeline.tem.profiles import extract_profile
    from pipeline.tem.reading import read_tem_image

    t0 = time.perf_counter()
    with tempfile.TemporaryDirectory(dir=workdir) as tmp:
        try:
            image = read_tem_image(image_path, pixel_size)
            t1 = time.perf_counter()
            profile = extract_profile(image, defocus=defocus)
            t_prof = time.perf_counter() - t1
            h5p, h5f = Path(tmp) / "profile.h5", Path(tmp) / "fit.h5"
            write_profile_h5(h5p, image, profile)
            run_fit(h5p, h5f, fit_height=fit_height, S=S)
            fit = read_fit(h5f)
        except (ValueError, FitError, np.linalg.LinAlgError) as exc:
            out = lost_record(f"{type(exc).__name__}: {exc}")
            out.update(t_stage=time.perf_counter() - t0, t_profile=float("nan"))
            if figure:
                plot_comparison(read_tem_image(image_path, pixel_size).data, truth, None, out, figure)
            return out
    out = grade(profile, fit, truth, fit_height)
    out.update(t_stage=time.perf_counter() - t0, t_profile=t_prof)
    if figure:
        plot_comparison(image.data, truth, profile, out, figure)
    return out


def plot_comparison(data, truth, profile, metrics, path, half_height=25e-9):
    """PNG: the image around the true apex with the true outer silhouette (red), the
    particles (cyan +), the extracted edge (yellow dots; the points stage 2 fits in green)
    and the stage's apex and axis, titled with the main metrics."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    px = truth["pixel_size"]
    r_a, c_a = truth["apex_px"]
    h = half_height / px
    H, W = data.shape
    up = truth["orientation"] == "up"
    r0, r1 = (r_a - 0.4 * h, r_a + 1.6 * h) if up else (r_a - 1.6 * h, r_a + 0.4 * h)
    r0, r1 = int(max(0, r0)), int(min(H, r1))
    c0, c1 = int(max(0, c_a - h)), int(min(W, c_a + h))
    crop = data[r0:r1, c0:c1]
    lo, hi = np.percentile(crop, [0.5, 99.5])
    fig, ax = plt.subplots(figsize=(6, 6 * (r1 - r0) / max(c1 - c0, 1)))
    ax.imshow(
        crop, cmap="gray", vmin=lo, vmax=hi, extent=(c0 - 0.5, c1 - 0.5, r1 - 0.5, r0 - 0.5), interpolation="nearest"
    )
    s = np.asarray(truth["silhouette_px"])
    ax.plot(s[:, 1], s[:, 0], "r-", lw=0.8, label="true outer silhouette")
    for q in truth["particles"]:
        ax.plot(q["centre_px"][1], q["centre_px"][0], "c+", ms=8)
    if profile is not None:
        e = profile.edge_px
        used = profile.z <= 6e-9
        ax.plot(e[:, 1], e[:, 0], ".", color="y", ms=1.5, label="extracted edge")
        ax.plot(e[used, 1], e[used, 0], ".", color="lime", ms=2, label="fitted by stage 2")
        a, u = profile.apex_px, profile.axis_px
        ax.plot([a[1], a[1] + u[1] * h], [a[0], a[0] + u[0] * h], "b-", lw=0.6, label="stage axis")
    ax.set_xlim(c0 - 0.5, c1 - 0.5)
    ax.set_ylim(r1 - 0.5, r0 - 0.5)
    ax.legend(fontsize=6, loc="lower right" if not up else "upper right")
    if metrics.get("lost") and "dn" not in metrics:
        title = f"LOST: {metrics['lost_reason'][:90]}"
    else:
        title = (
            f"n {truth['n']:.2f}: dn {metrics['dn']:+.3f} (sigma_n {metrics['sigma_n']:.3f}), edge RMS "
            f"{metrics['edge_rms'] * 1e9:.2f} nm (bias {metrics['edge_bias'] * 1e9:+.2f}), pull-off "
            f"{100 * metrics['pulloff_error_signed']:+.1f} %" + ("  LOST" if metrics.get("lost") else "")
        )
    p = truth["params"]
    sub = (
        f"{p['layer']} {p['layer_thickness'] * 1e9:.1f} nm, e {p['asymmetry']:+.3f}, "
        f"df {p['defocus'] * 1e6:+.2f} um, "
        f"{p['kv']:.0f} kV, px {p['pixel_size'] * 1e9:.2f} nm, SNR {p['snr']:.0f}, {p['bits'] or 'float'} bit, "
        f"saturated {truth['saturated_fraction']:.0%}"
    )
    ax.set_title(title + "\n" + sub, fontsize=7)
    ax.axis("off")
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)
