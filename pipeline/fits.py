"""Stage 2: least-squares power-law fit of the apex profile (paper Eq. 1, 2).

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
quarter of the window's points turn back).
"""
from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
from scipy import optimize

from pipeline import h5io

__all__ = ["PowerLawFit", "FitError", "fit_power_law", "fit_tip_profile", "run_fit", "plot_tip_fits", "rigid_dugdale_area",
           "rigid_dugdale_log_gradient"]

N_BOUNDS = (1.05, 20.0)
ASYMMETRY_MAX = 0.3  # |e| of the flank-wise fit (right flank (1 + e) r, left (1 - e) r)


class FitError(ValueError):
    """A fit that cannot be done (no/too few points, unreadable profile file)."""


@dataclass
class PowerLawFit:
    n: float
    Q: float  # m^(n-1)
    ln_Q: float
    R: float  # m, Eq. 2
    S: float
    z0: float  # m
    cov_n_lnQ: np.ndarray  # 2x2
    rms_residual: float  # m
    fit_error_percent: float
    fit_height: float
    r: np.ndarray  # points used (m)
    z: np.ndarray
    flags: list = field(default_factory=list)
    sigma_n: float = float("nan")
    sigma_lnQ: float = float("nan")
    flank: np.ndarray | None = None
    edge_noise_fraction: float | None = None  # share of the residual variance explained by edge noise
    notes: list = field(default_factory=list)  # what the screening left out, in words
    axis_offset: float = 0.0  # m, common axis of the two flanks from the profile's axis (flank-wise fit)
    flank_asymmetry: float = 0.0  # e: right flank (1 + e) r(z), left (1 - e) r(z)
    flank_n: tuple | None = None  # n of the left and right flank fitted separately (flank disagreement)

    def z_model(self, r):
        """Fitted profile z(r) = z0 + |r|^n/(nQ) (m)."""
        return self.z0 + np.abs(r) ** self.n / (self.n * self.Q)


def rigid_dugdale_area(n, Q, h):
    """pi (n h Q)^(2/n): the area factor of the rigid Dugdale pull-off, Eq. 12 (F = W_A/h x this)."""
    return np.pi * np.power(n * h * Q, 2.0 / n)


def rigid_dugdale_log_gradient(n, Q, h):
    """Gradient of ln ``rigid_dugdale_area`` (Eq. 12) w.r.t. (n, ln Q) at heights ``h`` (m):
    (len(h), 2), rows (2 (1 - ln(n h Q)) / n^2, 2 / n); for error propagation from cov(n, ln Q)."""
    h = np.atleast_1d(np.asarray(h, float))
    return np.column_stack([2.0 * (1.0 - np.log(n * h * Q)) / n**2, np.full(h.size, 2.0 / n)])


def _model(p, r, h, side=None):
    """Height f of the model at the points and df/d|x| (for the orthogonal-distance weight).

    p = (n, ln r_h, z0[, x_a, e]): with ``side`` (+1 right, -1 left flank, signed x = side r)
    the flanks are x = x_a + (1 + e) r(z) and x = x_a - (1 - e) r(z) around a common power law
    r(z) of the MEAN radius (module doc, "Asymmetric flanks")."""
    n, lrh, z0 = p[:3]
    if side is None:
        rr, scale = np.abs(r), 1.0
    else:
        xa, e = p[3], p[4]
        scale = 1.0 + side * e
        rr = np.abs(side * r - xa) / scale
    u = rr / np.exp(lrh)
    un = np.power(u, n)
    f = z0 + h * un
    # derivative df/dr for the orthogonal-distance normalisation
    with np.errstate(divide="ignore", invalid="ignore"):
        fp = np.where(u > 0, h * n * un / np.maximum(rr, 1e-300), 0.0) / scale
    return f, fp


def _residuals(p, r, z, h, side=None):
    f, fp = _model(p, r, h, side)
    return (z - f) / np.sqrt(1.0 + fp**2)


def _ess_factor(res, groups):
    """Variance inflation 1 + 2 sum rho_k (Bartlett, lags up to 20) of residuals along each flank."""
    facs, wts = [], []
    for g in np.unique(groups):
        e = res[groups == g]
        if e.size < 8:
            continue
        e = e - e.mean()
        v = float(e @ e)
        if v <= 0:
            continue
        s = 0.0
        for k in range(1, min(20, e.size // 4)):
            rho = float(e[:-k] @ e[k:]) / v
            if rho <= 0.05:
                break
            s += rho
        facs.append(1.0 + 2.0 * s)
        wts.append(e.size)
    return float(np.average(facs, weights=wts)) if facs else 1.0


# Edge error the image model does not know (Fresnel fringes, a layer, the detector): where the
# silhouette fit's reduced chi^2 says the image is not the model's (chi2_red > 1 + 3 sqrt(2/N), N
# its pixels), a smooth offset of each flank's edge along its normal, of SD EDGE_SYSTEMATIC_PX x
# min(1, sqrt(chi2_red - 1 - 3 sqrt(2/N))) pixels in each of the Legendre components 1, t, t^2
# (t = 2 z / h - 1) over the fit window, the two flanks independent.  On wave-optical images
# (benchmarks/bench_tem_independent.py) the Beer-Lambert edge lies a median 0.5 nm (1-5 px) off the
# true silhouette; of 0.5, 0.75 and 1 px (83, 87, 92 % of n within 2 sigma_n) 1 px is the smallest
# that reaches 90 % (set on that grid, not derived).  An image the model describes keeps the
# noise-only covariance.
EDGE_SYSTEMATIC_PX = 1.0
EDGE_SYSTEMATIC_DEGREE = 2


def _systematic_cov(jac, t, side, sd):
    """Covariance of the fitted parameters from the smooth per-flank edge offsets above: a point
    moved along its normal by d changes its orthogonal residual by -d, the fit absorbs
    -(J^T J)^-1 J^T of that."""
    t = np.clip(2.0 * t - 1.0, -1.0, 1.0)
    leg = np.polynomial.legendre.legvander(t, EDGE_SYSTEMATIC_DEGREE)  # (N, D+1)
    X = np.hstack([leg * (side < 0)[:, None], leg * (side > 0)[:, None]])
    M = np.linalg.solve(jac.T @ jac, jac.T @ X)
    return sd**2 * (M @ M.T)


def edge_covariance_of_params(jac, dres_doffset, basis, cov_c):
    """Covariance of the fit parameters from the covariance of the edge itself.

    The points' normal offsets are basis @ c with cov(c) = cov_c; a point moved along
    its normal by d changes its residual by dres_doffset x d; the least-squares
    parameters change by -(J^T J)^-1 J^T of that.  Returns (cov_p, predicted variance
    of each point's residual about the fit): the part of the edge noise that the fitted
    parameters do not absorb (a common offset of the edge moves z0, not the scatter).
    """
    A = np.linalg.solve(jac.T @ jac, jac.T)  # (P, N)
    X = dres_doffset[:, None] * basis  # (N, K): residuals per unit c_k
    M = A @ X  # (P, K)
    R = X - jac @ M  # residuals left after the refit
    var_res = np.einsum("ij,jk,ik->i", R, cov_c, R)
    return M @ cov_c @ M.T, var_res


def fit_power_law(r, z, fit_height=6e-9, S=1.0, pixel_size=None, groups=None, r_scale=1e-9,
                  edge_basis=None, edge_cov=None, normal_rz=None, fixed_n=None, flank=None, screen=True,
                  image_chi2_red=None, image_n_pixels=None) -> PowerLawFit:
    """``_fit_power_law`` (Eq. 1) on the profile points, screened first where both flanks are given
    (``screen``): points where the edge turns back (the radius shrinks with height) and runs
    that stand out of one flank only (contamination: the flanks' mirror symmetry broken) are
    left out, and the fit's ``notes`` say where; an edge that turns back over more than
    TURN_BACK_MAX of its points is flagged "edge_turns_back" (unusable)."""
    r = np.abs(np.asarray(r, float))
    z = np.asarray(z, float)
    args = dict(fit_height=fit_height, S=S, pixel_size=pixel_size, r_scale=r_scale, fixed_n=fixed_n)
    sys_px = 0.0
    if image_chi2_red is not None and np.isfinite(image_chi2_red):
        # chi2_red of a model-true image scatters by sqrt(2 / N) about 1: 3 SD of that are noise
        allow = 3.0 * np.sqrt(2.0 / image_n_pixels) if image_n_pixels else 0.0
        sys_px = EDGE_SYSTEMATIC_PX * min(1.0, float(np.sqrt(max(float(image_chi2_red) - 1.0 - allow, 0.0))))

    pre = []  # notes known before the fit
    if edge_cov is not None and not np.all(np.isfinite(edge_cov)):
        edge_cov = None
        pre.append("the silhouette fit gave no finite edge covariance: sigma_n from the residual scatter")

    def sub(keep):
        out = dict(groups=None if groups is None else np.asarray(groups)[keep],
                   flank=None if flank is None else np.asarray(flank)[keep])
        if edge_basis is not None and edge_cov is not None and normal_rz is not None:
            out.update(edge_basis=np.asarray(edge_basis)[keep], edge_cov=edge_cov, normal_rz=np.asarray(normal_rz)[keep])
        return out

    full = np.ones(r.size, bool)
    if not screen or flank is None:
        fit = _fit_power_law(r, z, **args, **sub(full), systematic_px=sys_px)
        fit.notes = pre + fit.notes
        return fit
    side = np.where(np.asarray(flank) < 0, -1, 1)
    win = np.isfinite(r) & np.isfinite(z) & (z <= fit_height)
    notes, flags = list(pre), []
    # contamination first, against a robust fit (a particle hanging below the face would otherwise
    # make the face above it look turned back)
    scale = max(0.05e-9, 0.25 * (pixel_size or 0.0))
    robust = _fit_power_law(r, z, **args, **sub(full), loss=("soft_l1", scale))
    bump = _one_flank_runs(robust, r, z, side, win, r_scale)
    if bump.any():
        notes.append(f"contamination on the {_where(r, z, side, bump)} (stands out of that flank only, "
                     f"{bump.sum()} points): left out, the fit rests on the unaffected points")
    back = _turned_back(r, z, side, win & ~bump, tol=max(TURN_BACK_TOL, TURN_BACK_PX * (pixel_size or 0.0)))
    if back.any():
        notes.append(f"edge turns back (radius shrinking with height) at {back.sum()} of {win.sum()} points "
                     f"({_where(r, z, side, back)}): left out")
        if back.sum() > TURN_BACK_MAX * max(win.sum(), 1):
            flags.append("edge_turns_back")
    keep = full & ~bump & ~back
    fit = _fit_power_law(r[keep], z[keep], **args, **sub(keep), systematic_px=sys_px)
    if sys_px > 0:
        notes.append(f"the image fit leaves more than noise (reduced chi^2 {image_chi2_red:.3g}): a smooth edge error of "
                     f"{sys_px:.2f} px per flank is in the covariance")
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
        vs.append(f1.sigma_n ** 2)
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
        notes.append(f"the flanks disagree: n = {ns[0]:.2f} (left) and {ns[1]:.2f} (right) fitted separately; "
                     f"sigma_n {before:.3f} -> {fit.sigma_n:.3f} with their half-difference")


TURN_BACK_MAX = 0.25  # share of the window's points where the edge turns back that makes it unusable
# a point turns back where a point of its flank at least this much lower lies this much further
# out (m, or TURN_BACK_PX pixels if more): a flat face's edge wanders by +-0.3 nm at 0.5 nm pixels
TURN_BACK_TOL = 0.4e-9
TURN_BACK_PX = 1.5
RUN_SIGMA = 4.0  # contamination: a run of residuals this many robust SD outwards ...
RUN_MIN = 0.15e-9  # ... and at least this far (m) ...
RUN_POINTS = 4  # ... over at least this many consecutive points of one flank


def _where(r, z, side, mask):
    """Words for where ``mask`` lies: flank(s) and height range (nm)."""
    parts = []
    for s_, name in ((-1, "left"), (1, "right")):
        m = mask & (side == s_)
        if m.any():
            parts.append(f"{name} flank, z {z[m].min() * 1e9:.1f}-{z[m].max() * 1e9:.1f} nm")
    return "; ".join(parts)


def _turned_back(r, z, side, win, tol=TURN_BACK_TOL):
    """Points (in the window) with a point of the same flank at least ``tol`` lower and ``tol``
    further out: the radius of a worn tip grows with height, an edge that turns back is an
    undercut (contamination, a notch) or a failed edge, never the power law."""
    out = np.zeros(r.size, bool)
    for s_ in (-1, 1):
        i = np.nonzero(win & (side == s_))[0]
        if i.size < 3:
            continue
        o = i[np.argsort(z[i], kind="stable")]
        zz, rr = z[o], r[o]
        # largest radius among the points at least tol lower
        j = np.searchsorted(zz, zz - tol, side="right")
        runmax = np.concatenate([[-np.inf], np.maximum.accumulate(rr)])[j]
        out[o] = rr < runmax - tol
    return out


def _one_flank_runs(fit, r, z, side, use, r_scale):
    """Runs of points of one flank that stand outwards of the flank-wise fit (module doc) while
    the other flank at the same heights does not: contamination stuck to one flank."""
    f, fp = _model(np.r_[fit.n, np.log(_r_h(fit) / r_scale), fit.z0 / r_scale, fit.axis_offset / r_scale,
                         fit.flank_asymmetry], r / r_scale, fit.fit_height / r_scale, side)
    e = (z / r_scale - f) / np.sqrt(1.0 + fp**2) * r_scale  # m, < 0 outwards
    if use.sum() < 10:
        return np.zeros(r.size, bool)
    s = 1.4826 * float(np.median(np.abs(e[use] - np.median(e[use])))) + 1e-15
    out = use & (e < -max(RUN_SIGMA * s, RUN_MIN))
    runs = np.zeros(r.size, bool)
    for s_ in (-1, 1):
        i = np.nonzero(use & (side == s_))[0]
        o = i[np.argsort(z[i], kind="stable")]
        flagged = out[o]
        k = 0
        while k < o.size:
            if not flagged[k]:
                k += 1
                continue
            j = k
            while j < o.size and flagged[j]:
                j += 1
            if j - k >= RUN_POINTS:
                z1, z2 = z[o[k]], z[o[j - 1]]
                other = use & (side == -s_) & (z >= z1) & (z <= z2)
                if not other.any() or np.median(e[other]) > -2.0 * s:
                    # with its flanks: where the run's residuals return through zero
                    a, b = k, j
                    while a > 0 and e[o[a - 1]] < 0:
                        a -= 1
                    while b < o.size and e[o[b]] < 0:
                        b += 1
                    runs[o[a:b]] = True
            k = j
    return runs


def _r_h(fit):
    """Radius (m) at fit_height above z0 of a PowerLawFit: (n Q h)^(1/n)."""
    return float((fit.n * fit.Q * fit.fit_height) ** (1.0 / fit.n))


def _fit_power_law(r, z, fit_height=6e-9, S=1.0, pixel_size=None, groups=None, r_scale=1e-9,
                   edge_basis=None, edge_cov=None, normal_rz=None, fixed_n=None, flank=None, loss=None,
                   systematic_px=0.0) -> PowerLawFit:
    """Least-squares fit of z = z0 + |r|^n/(nQ) (Eq. 1) to points with z <= fit_height.

    r, z in m (r >= 0 measured from the axis, z from the profile's apex);
    ``groups`` labels points of separate flanks (ordered by z within each) for the
    correlation correction; ``pixel_size`` (m) for the residual flag.
    ``flank`` (-1 left, +1 right per point): both flanks are fitted with their own scale around
    a common axis (``_model``: x = x_a +- (1 +- e) r(z)), so that r(z), the power law, is the
    mean radius of the section; without it one curve |r|(z) is fitted to all points.
    Edge uncertainty (from the silhouette fit, optional): point i's normal offset is
    edge_basis[i] @ c, cov(c) = edge_cov (m^2), normal_rz[i] its outward normal.  Then
    cov(n, ln Q) = the propagated edge covariance + the residual covariance scaled by
    the fraction of the residual variance the edge noise does not explain (shape
    misfit).  Without it: residual covariance inflated by the residual autocorrelation.
    ``fixed_n``: fit only Q and z0 with n held at this value (the paraboloid fit of a
    reference, n = 2: R then comes from the curvature alone); var(n) = 0 in the covariance.
    """
    r = np.abs(np.asarray(r, float))
    z = np.asarray(z, float)
    groups = np.zeros(r.size, int) if groups is None else np.asarray(groups)
    side = None if flank is None else np.where(np.asarray(flank) < 0, -1.0, 1.0)
    ok = np.isfinite(r) & np.isfinite(z) & (z <= fit_height)
    r, z, groups = r[ok], z[ok], groups[ok]
    if side is not None:
        side = side[ok]
        if min((side < 0).sum(), (side > 0).sum()) < 3:
            side = None  # one flank only: no asymmetry to fit
    has_edge_cov = edge_basis is not None and edge_cov is not None and normal_rz is not None
    if has_edge_cov:
        edge_basis, normal_rz = np.asarray(edge_basis)[ok], np.asarray(normal_rz)[ok]
    flank_out = groups.copy() if side is None else side.astype(int)
    if r.size < 5:
        raise FitError(f"only {r.size} profile points below fit_height = {fit_height:.3g} m; cannot fit")
    h = float(fit_height)
    # work in nm-ish scaled units for conditioning
    sc = r_scale
    rs, zs, hs = r / sc, z / sc, h / sc
    # start: log-log line through points above the lowest 10 % of the window
    z_min = float(np.min(zs))
    sel = (zs - z_min > 0.1 * hs) & (rs > 0)
    if sel.sum() >= 3:
        slope, icpt = np.polyfit(np.log(rs[sel]), np.log(zs[sel] - z_min), 1)
        n0 = float(np.clip(slope, 1.5, 8.0))
    else:
        n0 = 2.0
    rh0 = float(np.interp(hs, np.sort(zs - z_min), rs[np.argsort(zs)])) if rs.size else 1.0
    p0 = np.array([n0, np.log(max(rh0, 1e-3)), z_min, 0.0, 0.0])
    lb = [N_BOUNDS[0], np.log(1e-6), z_min - hs, -0.5 * rh0, -ASYMMETRY_MAX]
    ub = [N_BOUNDS[1], np.log(1e6), z_min + hs, 0.5 * rh0, ASYMMETRY_MAX]
    p0 = np.clip(p0, np.add(lb, 1e-9), np.subtract(ub, 1e-9))
    free = ([0] if fixed_n is None else []) + [1, 2] + ([3, 4] if side is not None else [])

    def full(q):
        v = p0.copy()
        if fixed_n is not None:
            v[0] = float(fixed_n)
        v[free] = q
        return v

    kw = {} if loss is None else dict(loss=loss[0], f_scale=loss[1] / sc)  # robust: screening only
    res = optimize.least_squares(lambda q: _residuals(full(q), rs, zs, hs, side), p0[free],
                                 bounds=(np.take(lb, free), np.take(ub, free)), x_scale="jac", method="trf",
                                 max_nfev=500, **kw)
    pf = full(res.x)
    n, lrh, z0s = pf[:3]
    e = res.fun
    dof = max(1, e.size - len(free))
    s2 = float(e @ e) / dof
    J = res.jac
    flags = []
    edge_part = None
    cov_p = np.zeros((5, 5))
    try:
        cov_f = np.linalg.inv(J.T @ J) * s2 * _ess_factor(e, groups)
        if has_edge_cov:
            _, fp = _model(pf, rs, hs, side)
            de = (normal_rz[:, 1] - fp * normal_rz[:, 0]) / np.sqrt(1.0 + fp**2)
            cov_e, var_pt = edge_covariance_of_params(J, de, edge_basis, np.asarray(edge_cov) / sc**2)
            explained = float(np.mean(var_pt)) / max(float(np.mean(e**2)), 1e-300)
            edge_part = float(min(1.0, explained))
            cov_f = cov_e + max(0.0, 1.0 - explained) * cov_f
        if side is not None and systematic_px > 0 and pixel_size:
            cov_f = cov_f + _systematic_cov(J, zs / hs, side, systematic_px * pixel_size / sc)
        cov_p[np.ix_(free, free)] = cov_f
    except np.linalg.LinAlgError:
        cov_p = np.full((5, 5), np.nan)
        flags.append("singular_covariance")
    # (n, ln r_h) -> (n, ln Q) in SI:  ln Q = n ln r_h - ln n - ln h  (lengths in m)
    lrh_si = lrh + np.log(sc)
    ln_Q = n * lrh_si - np.log(n) - np.log(h)
    T = np.array([[1.0, 0.0], [lrh_si - 1.0 / n, n]])
    cov2 = T @ cov_p[:2, :2] @ T.T
    Q = float(np.exp(ln_Q))
    R = float((Q / S ** (n - 2)) ** (1.0 / (n - 1)))
    rms = float(np.sqrt(np.mean(e**2))) * sc
    if n < 1.5:
        flags.append("n_below_1.5")
    if not res.success:
        flags.append("not_converged")
    if fixed_n is None and (n <= N_BOUNDS[0] + 1e-6 or n >= N_BOUNDS[1] - 1e-6):
        flags.append("n_at_bound")
    if pixel_size is not None and rms > 2.0 * pixel_size:
        flags.append("residual_above_pixel")
    if r.size < 12:
        flags.append("few_points")
    return PowerLawFit(n=float(n), Q=Q, ln_Q=float(ln_Q), R=R, S=float(S), z0=float(z0s * sc),
                       cov_n_lnQ=cov2, rms_residual=rms, fit_error_percent=100.0 * rms / h,
                       fit_height=h, r=r, z=z, flags=flags,
                       sigma_n=float(np.sqrt(cov2[0, 0])), sigma_lnQ=float(np.sqrt(cov2[1, 1])),
                       flank=flank_out, edge_noise_fraction=edge_part,
                       axis_offset=float(pf[3] * sc) if side is not None else 0.0,
                       flank_asymmetry=float(pf[4]) if side is not None else 0.0)


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
    return fit_power_law(np.abs(profile.x[i]), profile.z[i], fit_height, S, pixel_size=profile.pixel_size,
                         groups=profile.flank[i] if both else None, flank=profile.flank[i] if both else None,
                         image_chi2_red=chi2 if both else None, image_n_pixels=npx, **edge)


# ----------------------------------------------------------------------------- stage

def _read_profile(profile_h5):
    import h5py

    path = Path(profile_h5)
    try:
        with h5py.File(path, "r") as f:
            g = f["profile"]
            out = {}
            cov = g["offset_cov"][()] if "offset_cov" in g else None
            for name in ("left", "right", "combined"):
                sg = g[name]
                edge = None
                if cov is not None and "offset_basis" in sg:
                    edge = dict(edge_basis=sg["offset_basis"][()], edge_cov=cov, normal_rz=sg["normal_rz"][()])
                out[name] = (sg["r"][()], sg["z"][()], edge)
            out["flank"] = g["combined"]["flank"][()]
            em = f.get("edge_model")
            out["chi2_red"] = float(em["chi2_reduced"][()]) if em is not None and "chi2_reduced" in em else None
            out["n_pixels"] = float(em["n_pixels"][()]) if em is not None and "n_pixels" in em else None
            px = float(f["image"]["pixel_size"][()])
            return out, px
    except FileNotFoundError:
        raise FitError(f"{path}: profile file not found") from None
    except (OSError, KeyError) as exc:
        raise FitError(f"{path}: unreadable or incomplete profile file ({exc})") from None


def _write_fit(group, fit: PowerLawFit):
    w = h5io.write_dataset
    w(group, "n", fit.n, "1", "power index n (Eq. 1)")
    w(group, "Q", fit.Q, f"m^{fit.n - 1:.4g}", "Q of Eq. 1 in SI, units m^(n-1)")
    w(group, "ln_Q", fit.ln_Q, "1", "natural log of Q in SI units")
    w(group, "R", fit.R, "m", "R of Eq. 2, Q = S^(n-2) R^(n-1)")
    w(group, "S", fit.S, "1", "steepness S of Eq. 2")
    w(group, "z0", fit.z0, "m", "fitted apex offset")
    w(group, "cov_n_lnQ", fit.cov_n_lnQ, "1", "covariance of (n, ln Q)")
    w(group, "axis_offset", fit.axis_offset, "m", "common axis of the two flanks from the profile's axis")
    w(group, "flank_asymmetry", fit.flank_asymmetry, "1",
      "e of the flank-wise fit: right flank (1 + e) r(z), left (1 - e) r(z), r(z) the power law (Eq. 1)")
    if fit.edge_noise_fraction is not None:
        w(group, "edge_noise_fraction", fit.edge_noise_fraction, "1",
          "share of the residual variance explained by the silhouette fit's edge noise "
          "(cov = propagated edge covariance + (1 - share) x residual covariance)")
    w(group, "rms_residual", fit.rms_residual, "m", "RMS orthogonal residual")
    w(group, "fit_error_percent", fit.fit_error_percent, "%", "100 x RMS residual / fit_height")
    w(group, "fit_height", fit.fit_height, "m", "fit window above the apex")
    w(group, "r", fit.r, "m", "radial coordinate of the points used")
    w(group, "z", fit.z, "m", "height of the points used")
    if fit.flank is not None:
        w(group, "flank", fit.flank.astype(np.int8), "1", "-1 left, +1 right flank of each point")
    w(group, "flags", np.array(fit.flags, dtype=object) if fit.flags else np.array([], dtype=object), "1",
      "quality flags; empty = usable")
    w(group, "notes", np.array(fit.notes, dtype=object) if fit.notes else np.array([], dtype=object), "1",
      "what the screening of the profile left out (turned-back edge, contamination on one flank), in words")
    group.attrs["flagged"] = bool(fit.flags)


def run_fit(profile_h5, out_h5, *, fit_height=6e-9, S=1.0, tip="", interval="") -> None:
    """Fit the combined profile and each flank of ``profile_h5``; write ``out_h5`` (atomic).

    Layout: /fit (combined) and /fit_left, /fit_right with datasets n, Q, ln_Q, R,
    S, z0, cov_n_lnQ, rms_residual, fit_error_percent, fit_height, r, z, flags; /fit_n2 the
    paraboloid fit (n held at 2) of the combined profile, used for a reference interval
    whose n is consistent with 2 (``pipeline.inversion.shape_for_inversion``).
    """
    prof, px = _read_profile(profile_h5)
    fits = {}
    for name in ("combined", "left", "right"):
        r, z, edge = prof[name]
        try:
            both = name == "combined"
            fits[name] = fit_power_law(r, z, fit_height, S, pixel_size=px, groups=prof["flank"] if both else None,
                                       flank=prof["flank"] if both else None,
                                       image_chi2_red=prof["chi2_red"] if both else None,
                                       image_n_pixels=prof["n_pixels"], **(edge or {}))
        except FitError as exc:
            if name == "combined":
                raise FitError(f"{profile_h5}: {exc}") from None
            fits[name] = None
    with h5io.atomic_h5(out_h5, stage="fit", tip=tip, interval=interval, source=str(profile_h5),
                        model="z = z0 + |r|^n/(nQ) (Eq. 1); R from Eq. 2") as f:
        for name, gname in (("combined", "fit"), ("left", "fit_left"), ("right", "fit_right")):
            if fits[name] is None:
                g = h5io.create_group(f, gname, failed=True)
                continue
            g = h5io.create_group(f, gname)
            _write_fit(g, fits[name])
        c = fits["combined"]
        f.attrs["flagged"] = bool(c.flags)
        r, z, edge = prof["combined"]
        try:
            para = fit_power_law(r, z, fit_height, S, pixel_size=px, groups=prof["flank"], flank=prof["flank"],
                                 fixed_n=2.0, image_chi2_red=prof["chi2_red"], image_n_pixels=prof["n_pixels"],
                                 **(edge or {}))
            _write_fit(h5io.create_group(f, "fit_n2", model="paraboloid z = z0 + r^2/(2R): n held at 2, Q = R"), para)
        except FitError:
            h5io.create_group(f, "fit_n2", failed=True)


def read_fit(fit_h5, group="fit"):
    """Read a fit group back as a PowerLawFit."""
    import h5py

    with h5py.File(fit_h5, "r") as f:
        g = f[group]
        v = {k: g[k][()] for k in g}
    flags = [x.decode() if isinstance(x, bytes) else str(x) for x in np.atleast_1d(v["flags"])] if v["flags"].size else []
    nts = np.atleast_1d(v.get("notes", np.array([], dtype=object)))
    notes = [x.decode() if isinstance(x, bytes) else str(x) for x in nts] if nts.size else []
    cov = np.asarray(v["cov_n_lnQ"], float)
    sd = np.sqrt(np.where(np.isfinite(np.diag(cov)) & (np.diag(cov) >= 0), np.diag(cov), np.nan))
    enf = v.get("edge_noise_fraction")
    return PowerLawFit(n=float(v["n"]), Q=float(v["Q"]), ln_Q=float(v["ln_Q"]), R=float(v["R"]), S=float(v["S"]),
                       z0=float(v["z0"]), cov_n_lnQ=cov, rms_residual=float(v["rms_residual"]),
                       fit_error_percent=float(v["fit_error_percent"]), fit_height=float(v["fit_height"]),
                       r=v["r"], z=v["z"], flags=flags, notes=notes, flank=v.get("flank"), sigma_n=float(sd[0]),
                       sigma_lnQ=float(sd[1]), edge_noise_fraction=None if enf is None else float(enf),
                       axis_offset=float(v.get("axis_offset", 0.0)), flank_asymmetry=float(v.get("flank_asymmetry", 0.0)))


def plot_tip_fits(fit_h5_paths, out_png, labels=None) -> None:
    """Profiles (points) and fits (lines) of all intervals of a tip on one plot (like Fig. 3a/c), nm axes."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(5.5, 4.2))
    labels = labels or [Path(p).stem for p in fit_h5_paths]
    cmap = plt.get_cmap("viridis")
    for i, (p, lab) in enumerate(zip(fit_h5_paths, labels)):
        fit = read_fit(p)
        col = cmap(i / max(1, len(fit_h5_paths) - 1))
        sgn = np.where(fit.flank < 0, -1.0, 1.0) if fit.flank is not None else 1.0
        ax.plot(sgn * fit.r * 1e9, (fit.z - fit.z0) * 1e9, "s", ms=2.5, mfc="none", color=col, alpha=0.6)
        rr = np.linspace(0, max(fit.r.max(), 1e-12), 200)
        flag = " (flagged)" if fit.flags else ""
        zm, e, xa = (fit.z_model(rr) - fit.z0) * 1e9, fit.flank_asymmetry, fit.axis_offset
        ax.plot((xa + (1 + e) * rr) * 1e9, zm, "-", color=col,
                label=f"{lab}: n = {fit.n:.2f}, R = {fit.R * 1e9:.1f} nm{flag}")
        ax.plot((xa - (1 - e) * rr) * 1e9, zm, "-", color=col)
    ax.set_xlabel("r (nm)")
    ax.set_ylabel("z (nm)")
    ax.set_title("TEM profiles and power-law fits (Eq. 1)")
    ax.legend(fontsize=7, loc="upper center")
    fig.tight_layout()
    with h5io.atomic_output(out_png) as tmp:
        fig.savefig(tmp, dpi=130, format="png")
    plt.close(fig)
