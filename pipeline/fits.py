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

Fit error (percent): 100 x RMS orthogonal residual / fit_height - the scatter of
the profile about the fit relative to the height of the fit window (the paper
reports < 2 %).  R from Eq. 2 with a given S: Q = S^(n-2) R^(n-1).

Flags: "n_below_1.5", "residual_above_pixel" (RMS residual > 2 pixel sizes),
"few_points" (< 12 points), "not_converged", "n_at_bound".
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


def _model(p, r, h):
    n, lrh, z0 = p
    u = np.abs(r) / np.exp(lrh)
    un = np.power(u, n)
    f = z0 + h * un
    # derivative df/dr for the orthogonal-distance normalisation
    with np.errstate(divide="ignore", invalid="ignore"):
        fp = np.where(u > 0, h * n * un / np.maximum(np.abs(r), 1e-300), 0.0)
    return f, fp


def _residuals(p, r, z, h):
    f, fp = _model(p, r, h)
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


def edge_covariance_of_params(jac, dres_doffset, basis, cov_c):
    """Covariance of the fit parameters from the covariance of the edge itself.

    The points' normal offsets are basis @ c with cov(c) = cov_c; a point moved along
    its normal by d changes its residual by dres_doffset x d; the least-squares
    parameters change by -(J^T J)^-1 J^T of that.  Returns (cov_p, predicted variance
    of each point's normal offset).
    """
    A = np.linalg.solve(jac.T @ jac, jac.T)  # (P, N)
    M = A @ (dres_doffset[:, None] * basis)  # (P, K)
    var_pt = np.einsum("ij,jk,ik->i", basis, cov_c, basis)
    return M @ cov_c @ M.T, var_pt


def fit_power_law(r, z, fit_height=6e-9, S=1.0, pixel_size=None, groups=None, r_scale=1e-9,
                  edge_basis=None, edge_cov=None, normal_rz=None, fixed_n=None) -> PowerLawFit:
    """Least-squares fit of z = z0 + |r|^n/(nQ) (Eq. 1) to points with z <= fit_height.

    r, z in m (r >= 0 measured from the axis, z from the profile's apex);
    ``groups`` labels points of separate flanks (ordered by z within each) for the
    correlation correction; ``pixel_size`` (m) for the residual flag.
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
    ok = np.isfinite(r) & np.isfinite(z) & (z <= fit_height)
    r, z, groups = r[ok], z[ok], groups[ok]
    has_edge_cov = edge_basis is not None and edge_cov is not None and normal_rz is not None
    if has_edge_cov:
        edge_basis, normal_rz = np.asarray(edge_basis)[ok], np.asarray(normal_rz)[ok]
    flank = groups.copy()
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
    p0 = np.array([n0, np.log(max(rh0, 1e-3)), z_min])
    lb = [N_BOUNDS[0], np.log(1e-6), z_min - hs]
    ub = [N_BOUNDS[1], np.log(1e6), z_min + hs]
    p0 = np.clip(p0, np.add(lb, 1e-9), np.subtract(ub, 1e-9))
    free = [0, 1, 2] if fixed_n is None else [1, 2]
    full = (lambda q: q) if fixed_n is None else (lambda q: np.r_[float(fixed_n), q])  # noqa: E731
    res = optimize.least_squares(lambda q: _residuals(full(q), rs, zs, hs), p0[free], bounds=(np.take(lb, free), np.take(ub, free)),
                                 x_scale="jac", method="trf", max_nfev=500)
    n, lrh, z0s = full(res.x)
    e = res.fun
    dof = max(1, e.size - len(free))
    s2 = float(e @ e) / dof
    J = res.jac
    flags = []
    edge_part = None
    cov_p = np.zeros((3, 3))
    try:
        cov_f = np.linalg.inv(J.T @ J) * s2 * _ess_factor(e, groups)
        if has_edge_cov:
            _, fp = _model(full(res.x), rs, hs)
            de = (normal_rz[:, 1] - fp * normal_rz[:, 0]) / np.sqrt(1.0 + fp**2)
            cov_e, var_pt = edge_covariance_of_params(J, de, edge_basis, np.asarray(edge_cov) / sc**2)
            explained = float(np.mean(var_pt)) / max(float(np.mean(e**2)), 1e-300)
            edge_part = float(min(1.0, explained))
            cov_f = cov_e + max(0.0, 1.0 - explained) * cov_f
        cov_p[np.ix_(free, free)] = cov_f
    except np.linalg.LinAlgError:
        cov_p = np.full((3, 3), np.nan)
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
                       flank=flank, edge_noise_fraction=edge_part)


def fit_tip_profile(profile, fit_height=6e-9, S=1.0, which="both") -> PowerLawFit:
    """``fit_power_law`` on a ``pipeline.tem.profiles.TipProfile`` (one flank or both),
    with its edge covariance when the silhouette fit provided one."""
    i = profile.flank_index(which)
    edge = {}
    if profile.offset_basis is not None:
        edge = dict(edge_basis=profile.offset_basis[i], edge_cov=profile.offset_cov, normal_rz=profile.normal_rz[i])
    return fit_power_law(np.abs(profile.x[i]), profile.z[i], fit_height, S, pixel_size=profile.pixel_size,
                         groups=profile.flank[i] if which == "both" else None, **edge)


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
            fits[name] = fit_power_law(r, z, fit_height, S, pixel_size=px,
                                       groups=prof["flank"] if name == "combined" else None, **(edge or {}))
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
            para = fit_power_law(r, z, fit_height, S, pixel_size=px, groups=prof["flank"], fixed_n=2.0, **(edge or {}))
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
    return PowerLawFit(n=float(v["n"]), Q=float(v["Q"]), ln_Q=float(v["ln_Q"]), R=float(v["R"]), S=float(v["S"]),
                       z0=float(v["z0"]), cov_n_lnQ=v["cov_n_lnQ"], rms_residual=float(v["rms_residual"]),
                       fit_error_percent=float(v["fit_error_percent"]), fit_height=float(v["fit_height"]),
                       r=v["r"], z=v["z"], flags=flags, flank=v.get("flank"))


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
        ax.plot(rr * 1e9, (fit.z_model(rr) - fit.z0) * 1e9, "-", color=col,
                label=f"{lab}: n = {fit.n:.2f}, R = {fit.R * 1e9:.1f} nm{flag}")
        ax.plot(-rr * 1e9, (fit.z_model(rr) - fit.z0) * 1e9, "-", color=col)
    ax.set_xlabel("r (nm)")
    ax.set_ylabel("z (nm)")
    ax.set_title("TEM profiles and power-law fits (Eq. 1)")
    ax.legend(fontsize=7, loc="upper center")
    fig.tight_layout()
    with h5io.atomic_output(out_png) as tmp:
        fig.savefig(tmp, dpi=130, format="png")
    plt.close(fig)
