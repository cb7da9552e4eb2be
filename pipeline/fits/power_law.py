"""The power-law model z = z0 + |r|^n/(nQ) (Eq. 1) and its least-squares fit with covariance
(package doc); the rigid Dugdale area of Eq. 12 from (n, Q)."""

from __future__ import annotations

import numpy as np
from scipy import optimize

from pipeline.fits.result import FitError, PowerLawFit
from pipeline.tem.model_error import EDGE_SYSTEMATIC_DEGREE

N_BOUNDS = (1.05, 20.0)
ASYMMETRY_MAX = 0.3  # |e| of the flank-wise fit (right flank (1 + e) r, left (1 - e) r)


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


# Edge error the image model does not know (``pipeline.tem.model_error``: constants and gate there): a
# smooth offset of each flank's edge along its normal, Legendre components 1, t, t^2, the flanks
# independent; the mean of the flanks' constant offsets is in the edge covariance of stage 1 when the
# profile says so (``common_in_edge``), and is then left out here.
def _systematic_cov(jac, t, side, sd, common_in_edge=False):
    """Covariance of the fitted parameters from the smooth per-flank edge offsets above: a point
    moved along its normal by d changes its orthogonal residual by -d, the fit absorbs
    -(J^T J)^-1 J^T of that.  ``common_in_edge``: the flanks' common constant offset (SD sd / sqrt 2
    of their mean) is carried by the edge covariance, so of the two constant components only their
    difference is added here (the two together are the same covariance: a rotation of the pair)."""
    t = np.clip(2.0 * t - 1.0, -1.0, 1.0)
    leg = np.polynomial.legendre.legvander(t, EDGE_SYSTEMATIC_DEGREE)  # (N, D+1)
    left, right = leg * (side < 0)[:, None], leg * (side > 0)[:, None]
    if common_in_edge:
        X = np.hstack([(left[:, :1] - right[:, :1]) / np.sqrt(2.0), left[:, 1:], right[:, 1:]])
    else:
        X = np.hstack([left, right])
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


def _r_h(fit):
    """Radius (m) at fit_height above z0 of a PowerLawFit: (n Q h)^(1/n)."""
    return float((fit.n * fit.Q * fit.fit_height) ** (1.0 / fit.n))


def _least_squares(rs, zs, hs, side, fixed_n, loss, sc):
    """The least-squares fit of ``_fit_power_law`` in scaled units (``sc``): scipy's result,
    all model parameters at its optimum, the indices of the free ones."""
    p0, lb, ub = _start(rs, zs, hs)
    free = ([0] if fixed_n is None else []) + [1, 2] + ([3, 4] if side is not None else [])

    def full(q):
        v = p0.copy()
        if fixed_n is not None:
            v[0] = float(fixed_n)
        v[free] = q
        return v

    kw = {} if loss is None else dict(loss=loss[0], f_scale=loss[1] / sc)  # robust: screening only
    res = optimize.least_squares(
        lambda q: _residuals(full(q), rs, zs, hs, side),
        p0[free],
        bounds=(np.take(lb, free), np.take(ub, free)),
        x_scale="jac",
        method="trf",
        max_nfev=500,
        **kw,
    )
    return res, full(res.x), free


def _fit_power_law(
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
    loss=None,
    systematic_px=0.0,
    common_in_edge=False,
) -> PowerLawFit:
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
    r, z, groups, side, edge = _window(r, z, fit_height, groups, flank, edge_basis, edge_cov, normal_rz)
    flank_out = groups.copy() if side is None else side.astype(int)
    if r.size < 5:
        raise FitError(
            f"only {r.size} profile points below fit_height = {fit_height:.3g} m; cannot fit: the edge "
            "stage 1 extracted has no tip apex here (an edge that missed a faint thick coating or ran "
            "off the tip, or a tip larger than the field); see the profile figure, and check "
            "tem.orientation and that the tip fits in the image"
        )
    h = float(fit_height)
    # work in nm-ish scaled units for conditioning
    sc = r_scale
    rs, zs, hs = r / sc, z / sc, h / sc
    res, pf, free = _least_squares(rs, zs, hs, side, fixed_n, loss, sc)
    n, lrh, z0s = pf[:3]
    e = res.fun
    flags = []
    cov_p, edge_part = _param_covariance(
        res, pf, free, groups, side, edge, (rs, zs, hs, sc), pixel_size, systematic_px, flags, common_in_edge
    )
    # (n, ln r_h) -> (n, ln Q) in SI:  ln Q = n ln r_h - ln n - ln h  (lengths in m)
    lrh_si = lrh + np.log(sc)
    ln_Q = n * lrh_si - np.log(n) - np.log(h)
    T = np.array([[1.0, 0.0], [lrh_si - 1.0 / n, n]])
    cov2 = T @ cov_p[:2, :2] @ T.T
    Q = float(np.exp(ln_Q))
    R = float((Q / S ** (n - 2)) ** (1.0 / (n - 1)))
    rms = float(np.sqrt(np.mean(e**2))) * sc
    flags += _quality_flags(n, res.success, fixed_n, rms, pixel_size, r.size)
    return PowerLawFit(
        n=float(n),
        Q=Q,
        ln_Q=float(ln_Q),
        R=R,
        S=float(S),
        z0=float(z0s * sc),
        cov_n_lnQ=cov2,
        rms_residual=rms,
        fit_error_percent=100.0 * rms / h,
        fit_height=h,
        r=r,
        z=z,
        flags=flags,
        sigma_n=float(np.sqrt(cov2[0, 0])),
        sigma_lnQ=float(np.sqrt(cov2[1, 1])),
        flank=flank_out,
        edge_noise_fraction=edge_part,
        axis_offset=float(pf[3] * sc) if side is not None else 0.0,
        flank_asymmetry=float(pf[4]) if side is not None else 0.0,
    )


def _window(r, z, fit_height, groups, flank, edge_basis, edge_cov, normal_rz):
    """The finite points with z <= fit_height: (r, z, groups, side or None, (edge_basis, edge_cov,
    normal_rz) or None); side None where fewer than 3 points lie on one flank."""
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
    edge = None
    if edge_basis is not None and edge_cov is not None and normal_rz is not None:
        edge = (np.asarray(edge_basis)[ok], edge_cov, np.asarray(normal_rz)[ok])
    return r, z, groups, side, edge


def _start(rs, zs, hs):
    """Start (n, ln r_h, z0, x_a, e) and bounds in scaled units: a log-log line through the points
    above the lowest 10 % of the window."""
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
    return p0, lb, ub


def _param_covariance(res, pf, free, groups, side, edge, scaled, pixel_size, systematic_px, flags, common_in_edge):
    """(5x5 covariance of the parameters in scaled units, share of the residual variance the edge
    noise explains or None): residual covariance inflated by the autocorrelation, or the propagated
    edge covariance plus the unexplained share of it, plus the systematic edge term; NaN and the
    flag "singular_covariance" where J^T J is singular."""
    rs, zs, hs, sc = scaled
    e = res.fun
    dof = max(1, e.size - len(free))
    s2 = float(e @ e) / dof
    J = res.jac
    edge_part = None
    cov_p = np.zeros((5, 5))
    try:
        cov_f = np.linalg.inv(J.T @ J) * s2 * _ess_factor(e, groups)
        if edge is not None:
            edge_basis, edge_cov, normal_rz = edge
            _, fp = _model(pf, rs, hs, side)
            de = (normal_rz[:, 1] - fp * normal_rz[:, 0]) / np.sqrt(1.0 + fp**2)
            cov_e, var_pt = edge_covariance_of_params(J, de, edge_basis, np.asarray(edge_cov) / sc**2)
            explained = float(np.mean(var_pt)) / max(float(np.mean(e**2)), 1e-300)
            edge_part = float(min(1.0, explained))
            cov_f = cov_e + max(0.0, 1.0 - explained) * cov_f
        if side is not None and systematic_px > 0 and pixel_size:
            common = common_in_edge and edge is not None
            cov_f = cov_f + _systematic_cov(J, zs / hs, side, systematic_px * pixel_size / sc, common)
        cov_p[np.ix_(free, free)] = cov_f
    except np.linalg.LinAlgError:
        cov_p = np.full((5, 5), np.nan)
        flags.append("singular_covariance")
    return cov_p, edge_part


def _quality_flags(n, converged, fixed_n, rms, pixel_size, n_points):
    """The fit's flags after "singular_covariance" (package doc, "Flags")."""
    flags = []
    if n < 1.5:
        flags.append("n_below_1.5")
    if not converged:
        flags.append("not_converged")
    if fixed_n is None and (n <= N_BOUNDS[0] + 1e-6 or n >= N_BOUNDS[1] - 1e-6):
        flags.append("n_at_bound")
    if pixel_size is not None and rms > 2.0 * pixel_size:
        flags.append("residual_above_pixel")
    if n_points < 12:
        flags.append("few_points")
    return flags
