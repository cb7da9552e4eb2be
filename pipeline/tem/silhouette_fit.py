"""Global model fit of the tip silhouette: all edge pixels at once (opt-in refinement).

Runs AFTER ``edges.refine_edges`` (per-normal fits), which supplies a good
initial silhouette, axis/apex frame, attenuation(s), blur and coating.

Model (same physics as ``pipeline.synth.tem_image``): a body of revolution whose
OUTER meridian is the reference meridian C0(s) of the per-normal result
(symmetrised over both flanks, s = arc length from the apex, px) moved along its
outward normal n0(s) by a smooth offset

    delta(s) = sum_k c_k phi_k(s),  phi_k = cubic B-spline centred at k*D, even in s,

with knots every D ~ 1.2 nm (no power law presupposed; the flat bottom of a blunt
tip is represented as well as a paraboloid).  The axis (lateral offset, angle)
is free; the apex height is delta(0).  Transmission
T = exp(-k_o t_outer - (k_c - k_o) t_core) with the exact chords (core = erosion
of the outer body by the coating thickness c), evaluated at pixel centres and
5 x 5 supersampled near the outer/core silhouettes, times a linear illumination
(a + b_r row + b_c col), then a 2-D Gaussian blur (sigma) on the pixel grid.
Only pixels in a band of a few blur widths around the outer (and core) edge
within the profile window enter the fit.  Linear parameters (a, b_r, b_c) are
part of each Gauss-Newton step in closed form; the nonlinear ones (c_k, axis
offset and angle, log sigma, log k_o[, log k_c, log c]) use a finite-difference
Jacobian with the B-spline coefficients grouped by non-overlapping influence
(a pixel at height z depends on r(z') for |z' - z| <= 4 sigma + c + 1 only).
Weights: Poisson, 1/sqrt(model), scaled by the background noise estimate.
Levenberg-Marquardt with a weak second-difference penalty on c_k.

Parameters the data cannot support (coating thickness or core attenuation with a
relative standard error > 30 %, or hitting a bound) are reported in ``flags``
and the coating is then held at the per-normal value instead of being forced.
"""
from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
from scipy import ndimage
from scipy.spatial import cKDTree

from pipeline.tem.edges import BodyModel, EdgeFit, TipFrame
from pipeline.tem.projection import chord

__all__ = ["GlobalFit", "refine_global"]

_SS = 5
_SUB = (np.arange(_SS) + 0.5) / _SS - 0.5


def _bspline(u):
    """Cardinal cubic B-spline (support |u| < 2)."""
    a = np.abs(u)
    out = np.where(a < 1, 2 / 3 - a**2 + 0.5 * a**3, 0.0)
    return np.where((a >= 1) & (a < 2), (2 - a) ** 3 / 6, out)


@dataclass
class GlobalFit:
    edge: EdgeFit
    frame: TipFrame
    params: dict
    stderr: dict
    flags: list = field(default_factory=list)
    n_pixels: int = 0
    n_iter: int = 0
    chi2_red: float = float("nan")


def _reference_meridian(pts, frame, step=0.25):
    """Symmetrised meridian (r, z) vs arc length s from the apex (px), with outward normals."""
    x, z = frame.to_tip(pts)
    i0 = int(np.argmin(np.abs(x) + 1e-3 * z))  # point on the axis
    flanks = []
    for seg in ((x[: i0 + 1][::-1], z[: i0 + 1][::-1]), (x[i0:], z[i0:])):
        r, zz = np.abs(seg[0]), seg[1]
        r = np.concatenate([[0.0], r])
        zz = np.concatenate([[zz[0]], zz])
        s = np.concatenate([[0.0], np.cumsum(np.hypot(np.diff(r), np.diff(zz)))])
        keep = np.concatenate([[True], np.diff(s) > 1e-9])
        flanks.append((s[keep], r[keep], zz[keep]))
    smax = min(f[0][-1] for f in flanks)
    s = np.arange(0.0, smax, step)
    r = 0.5 * sum(np.interp(s, f[0], f[1]) for f in flanks)
    zz = 0.5 * sum(np.interp(s, f[0], f[2]) for f in flanks)
    # smooth (even extension keeps the apex symmetric), then re-parametrise by arc length
    rr = np.concatenate([-r[:0:-1], r])
    z2 = np.concatenate([zz[:0:-1], zz])
    rr = ndimage.gaussian_filter1d(rr, 2.0 / step, mode="nearest")
    z2 = ndimage.gaussian_filter1d(z2, 2.0 / step, mode="nearest")
    r, zz = rr[s.size - 1:], z2[s.size - 1:]
    r = r - r[0]
    zz = np.maximum.accumulate(zz)
    sa = np.concatenate([[0.0], np.cumsum(np.hypot(np.diff(r), np.diff(zz)))])
    s = np.arange(0.0, sa[-1], step)
    r, zz = np.interp(s, sa, r), np.interp(s, sa, zz)
    tr, tz = np.gradient(r, step), np.gradient(zz, step)
    tr[0], tz[0] = 1.0, 0.0
    nn = np.hypot(tr, tz) + 1e-12
    return s, r, zz, tz / nn, -tr / nn  # normal (n_r, n_z) outward


class _Model:
    def __init__(self, frame0, s, r0, z0, nr, nz, knot, hz_top, coat_on):
        self.frame0 = frame0
        self.s, self.r0, self.z0, self.nr, self.nz = s, r0, z0, nr, nz
        self.knot = knot
        self.coat_on = coat_on
        ktop = int(np.floor(np.interp(hz_top, z0, s) / knot)) + 1
        self.K = min(ktop, int(s[-1] / knot) - 1) + 1
        self.basis = np.stack([_bspline(s / knot - k) + (_bspline(s / knot + k) if k > 0 else 0.0)
                               for k in range(self.K)], axis=1)

    def curve(self, c):
        d = self.basis @ c
        return self.r0 + d * self.nr, self.z0 + d * self.nz

    def frame(self, p):
        f0 = self.frame0
        return TipFrame(f0.apex + p["x0"] * f0.v, f0.angle + p["dth"])

    def body(self, p):
        r, z = self.curve(p["c"])
        z = np.maximum.accumulate(z)
        fr = self.frame(p)
        poly = np.concatenate([fr.to_image(-r[::-1], z[::-1]), fr.to_image(r[1:], z[1:])])
        return BodyModel(fr, poly, p["coat"] if self.coat_on else 0.0), fr, r, z


def _unpack(v, K, coat_on):
    p = dict(c=v[:K], x0=v[K], dth=v[K + 1], sigma=np.exp(v[K + 2]), k_o=np.exp(v[K + 3]))
    if coat_on:
        p["k_c"], p["coat"] = np.exp(v[K + 4]), np.exp(v[K + 5])
    else:
        p["k_c"], p["coat"] = p["k_o"], 0.0
    return p


def refine_global(win, fit: EdgeFit, frame: TipFrame, hpx, noise=None, knot_nm=1.2, pixel_size=None,
                  max_iter=12, smooth_weight=2.0):
    """Global refinement of ``fit`` (see module doc); ``win`` raw window, ``frame`` the
    symmetry frame of ``fit.points[fit.good]``, ``hpx`` profile height (px).
    Returns GlobalFit with an EdgeFit of the refined outer silhouette (both flanks,
    ~1 px apart, ordered left -> apex -> right)."""
    win = np.asarray(win, float)
    pts = fit.points[fit.good]
    s, r0, z0, nr, nz = _reference_meridian(pts, frame)
    knot = float(np.clip(knot_nm * 1e-9 / pixel_size if pixel_size else 6.0, 4.0, 16.0))
    coat_on = fit.coat_px > 0
    ztop = 1.02 * hpx
    model = _Model(frame, s, r0, z0, nr, nz, knot, ztop, coat_on)
    K = model.K
    v = np.concatenate([np.zeros(K), [0.0, 0.0, np.log(fit.sigma_px), np.log(fit.k_outer)]])
    if coat_on:
        v = np.concatenate([v, [np.log(fit.k_core), np.log(fit.coat_px)]])
    names = [f"c{k}" for k in range(K)] + ["x0", "dth", "log_sigma", "log_k_o"] + (
        ["log_k_c", "log_coat"] if coat_on else [])
    steps = np.array([0.02] * K + [0.02, 2e-4 * 50 / max(50.0, hpx), 0.01, 0.01] + ([0.01, 0.005] if coat_on else []))

    # ---- residual pixel set (fixed): band around the initial outer (and core) edge
    H, W = win.shape
    p0 = _unpack(v, K, coat_on)
    rc, zc = model.curve(p0["c"])
    sig0 = fit.sigma_px
    out_m = 3.0 * sig0 + 3.0
    in_m = (fit.coat_px if coat_on else 0.0) + 3.0 * sig0 + 3.0
    mrg = int(np.ceil(4 * max(sig0 * 1.6, 1.0) + out_m + 3))
    ctr_img = np.concatenate([frame.to_image(-rc[::-1], zc[::-1]), frame.to_image(rc[1:], zc[1:])])
    tree = cKDTree(np.column_stack([np.concatenate([-rc[::-1], rc[1:]]), np.concatenate([zc[::-1], zc[1:]])]))
    sel_c = zc <= ztop + mrg
    rows_c, cols_c = ctr_img[:, 0], ctr_img[:, 1]
    selc2 = np.concatenate([sel_c[::-1], sel_c[1:]])
    r_lo = int(max(0, np.floor(rows_c[selc2].min()) - mrg))
    r_hi = int(min(H, np.ceil(rows_c[selc2].max()) + mrg + 1))
    c_lo = int(max(0, np.floor(cols_c[selc2].min()) - mrg))
    c_hi = int(min(W, np.ceil(cols_c[selc2].max()) + mrg + 1))
    RR, CC = np.mgrid[r_lo:r_hi, c_lo:c_hi].astype(float)
    P = np.column_stack([RR.ravel(), CC.ravel()])
    px_x, px_z = frame.to_tip(P)
    dist, _ = tree.query(np.column_stack([px_x, px_z]))
    inside = (np.abs(px_x) < np.interp(px_z, zc, rc, left=-1.0)) & (px_z > zc[0])
    sd = np.where(inside, -dist, dist)
    use = (sd <= out_m) & (sd >= -in_m) & (px_z <= ztop)
    # keep residual pixels away from the region border (blur support)
    bm = int(np.ceil(4 * 1.6 * sig0 + 1))  # sigma <= 1.6 x its start (bounds)
    rloc, cloc = RR.ravel() - r_lo, CC.ravel() - c_lo
    use &= ((rloc >= bm) | (r_lo == 0)) & ((rloc < r_hi - r_lo - bm) | (r_hi == H))
    use &= ((cloc >= bm) | (c_lo == 0)) & ((cloc < c_hi - c_lo - bm) | (c_hi == W))
    idx = np.nonzero(use)[0]
    I = win[r_lo:r_hi, c_lo:c_hi].ravel()[idx]
    shape = (r_hi - r_lo, c_hi - c_lo)
    rn = (RR - 0.5 * (r_lo + r_hi)) / max(H, 1)
    cn = (CC - 0.5 * (c_lo + c_hi)) / max(W, 1)
    pz_use = px_z[idx]
    rn_i, cn_i = rn.ravel()[idx], cn.ravel()[idx]

    # pixels whose transmission reaches a residual pixel through the blur
    need_img = np.zeros(shape, bool)
    need_img.ravel()[idx] = True
    need_img = ndimage.binary_dilation(need_img, np.ones((3, 3), bool), int(np.ceil(4 * 1.6 * sig0)) + 2)
    need = need_img.ravel()
    geo = {}

    def tip_xz(p, ss_mask):
        """Tip-frame coordinates of the needed pixel centres and of the 5x5 sub-samples
        (cached: the frame only changes with the axis parameters)."""
        key = (float(p["x0"]), float(p["dth"]), id(ss_mask))
        if key not in geo:
            if len(geo) > 8:
                geo.clear()
            fr = model.frame(p)
            xc, zc_ = fr.to_tip(P[need])
            q = P[ss_mask & need]
            qq = np.stack([q[:, None, None, 0] + _SUB[None, :, None] + 0 * _SUB[None, None, :],
                           q[:, None, None, 1] + 0 * _SUB[None, :, None] + _SUB[None, None, :]], axis=-1)
            xs, zs = fr.to_tip(qq.reshape(-1, 2))
            geo[key] = (xc, zc_, xs, zs, ss_mask[need])
        return geo[key]

    def chords_xz(body, x, z):
        tabs = (body.rho, body.cen, body.rho_core) if body.coat > 0 else (body.rho, body.cen)
        vals, below = body._lookup(z, tabs)
        t_o = chord(np.where(below, -1.0, vals[0]), x - vals[1])
        if body.coat > 0:
            return t_o, chord(np.where(below, -1.0, vals[2]), x - vals[1])
        return t_o, t_o

    def render(vv, ss_mask):
        """Basis images (Npix, 3): blur(T), blur(T row), blur(T col) at the residual pixels."""
        p = _unpack(vv, K, coat_on)
        body, _, _, _ = model.body(p)
        xc, zc_, xs, zs, ssn = tip_xz(p, ss_mask)
        t_o, t_c = chords_xz(body, xc, zc_)
        Tn = np.exp(-(p["k_o"] * t_o + (p["k_c"] - p["k_o"]) * t_c))
        if xs.size:
            a, b = chords_xz(body, xs, zs)
            Tn[ssn] = np.exp(-(p["k_o"] * a + (p["k_c"] - p["k_o"]) * b)).reshape(-1, _SS * _SS).mean(1)
        T = np.ones(P.shape[0])
        T[need] = Tn
        T = T.reshape(shape)
        sg = p["sigma"]
        # blur(T x linear illumination) = illumination x blur(T) up to sigma^2/size: one filter
        bt = (ndimage.gaussian_filter(T, sg, mode="nearest") if sg > 0.05 else T).ravel()[idx]
        return np.column_stack([bt, bt * rn_i, bt * cn_i])

    def ss_band(vv):
        p = _unpack(vv, K, coat_on)
        r, z = model.curve(p["c"])
        fr = model.frame(p)
        x, zz = fr.to_tip(P)
        pts_c = [np.column_stack([np.concatenate([-r[::-1], r[1:]]), np.concatenate([z[::-1], z[1:]])])]
        if coat_on:
            nr_, nz_ = model.nr, model.nz
            rcr, zcr = r - p["coat"] * nr_, z - p["coat"] * nz_
            ok = rcr >= 0
            pts_c.append(np.column_stack([np.concatenate([-rcr[ok][::-1], rcr[ok]]),
                                          np.concatenate([zcr[ok][::-1], zcr[ok]])]))
        m = np.zeros(P.shape[0], bool)
        for c_ in pts_c:
            d, _ = cKDTree(c_).query(np.column_stack([x, zz]), distance_upper_bound=2.0)
            m |= np.isfinite(d)
        return m

    # ---- dependency of pixels on the spline coefficients -> column groups
    def groups(vv):
        p = _unpack(vv, K, coat_on)
        r, z = model.curve(p["c"])
        z = np.maximum.accumulate(z)
        m = 4 * p["sigma"] + p["coat"] + 2.0
        s_lo = np.interp(pz_use - m, z, model.s, left=0.0)
        s_hi = np.interp(pz_use + m, z, model.s)
        kc = np.arange(K) * knot
        D = (s_lo[:, None] <= kc[None, :] + 2 * knot) & (s_hi[:, None] >= kc[None, :] - 2 * knot)
        D[:, 1] |= (s_lo <= 1 * knot)  # mirrored part of phi_1 near the apex
        cols = []
        for k in range(K):
            for g in cols:
                if not (D[:, g].any(axis=1) & D[:, k]).any():
                    g.append(k)
                    break
            else:
                cols.append([k])
        return D, cols

    # weights (Poisson): sigma_i = noise_rel * a * sqrt(M_i / a)
    if noise is None or not noise > 0:
        noise = 0.01
    L2 = np.diff(np.eye(K), 2, axis=0) if K > 2 else np.zeros((0, K))

    def solve_lin(B, w):
        lin, *_ = np.linalg.lstsq(B * w[:, None], I * w, rcond=None)
        return lin

    # monotone height along the meridian: z(s) is linear in c, hinge penalty on decreases
    # (a fold below the apex would be invisible to the body model, i.e. unconstrained)
    ms = np.arange(0, s.size - 1, max(1, int(round(knot / 4 / (s[1] - s[0])))))
    Az = (model.basis[ms[1:]] * nz[ms[1:], None] - model.basis[ms[:-1]] * nz[ms[:-1], None])
    bz = z0[ms[1:]] - z0[ms[:-1]]
    mu = 100.0

    def penalty(vv):
        """Penalty residuals and their Jacobian w.r.t. c (smoothness, monotone z)."""
        c = vv[:K]
        dz = Az @ c + bz
        neg = dz < 0
        r_ = np.concatenate([np.sqrt(smooth_weight) * (L2 @ c), mu * np.where(neg, dz, 0.0)])
        J_ = np.vstack([np.sqrt(smooth_weight) * L2, mu * Az * neg[:, None]])
        return r_, J_

    def cost_of(vv, w, ssm):
        B = render(vv, ssm)
        lin = solve_lin(B, w)
        res = (I - B @ lin) * w
        pen = penalty(vv)[0]
        return float(res @ res + pen @ pen), B, lin, res

    ssm = ss_band(v)
    B = render(v, ssm)
    lin = solve_lin(B, np.ones(I.size))
    bg = float(lin[0]) if lin[0] > 0 else float(np.median(I))
    w = 1.0 / (noise * bg * np.sqrt(np.clip(B @ lin, 0.05 * bg, None) / bg))
    cost, B, lin, res = cost_of(v, w, ssm)
    lam = 1e-2
    n_par = v.size
    lb = np.full(n_par, -np.inf)
    ub = np.full(n_par, np.inf)
    lb[:K], ub[:K] = -4.0, 4.0
    # globals stay near the per-normal estimates (blur, edge offset and coating are
    # partly degenerate: a wide blur with an edge moved inwards is a local minimum)
    lb[K + 2], ub[K + 2] = v[K + 2] + np.log(0.6), v[K + 2] + np.log(1.6)
    lb[K + 3], ub[K + 3] = v[K + 3] + np.log(0.1), v[K + 3] + np.log(10.0)
    if coat_on:
        lb[K + 4], ub[K + 4] = v[K + 4] + np.log(0.1), v[K + 4] + np.log(10.0)
        lb[K + 5], ub[K + 5] = v[K + 5] + np.log(0.5), v[K + 5] + np.log(2.0)
    max_step = np.array([0.5] * K + [0.5, 0.01, 0.1, 0.2] + ([0.2, 0.15] if coat_on else []))

    def lm(v, cost, B, lin, res, ssm, active, iters, lam=1e-2):
        """Levenberg-Marquardt over the ``active`` nonlinear parameters (+ the linear ones)."""
        act = np.nonzero(active)[0]
        JTJ, it = None, 0
        for it in range(1, iters + 1):
            J = np.zeros((I.size, n_par))
            if active[:K].any():
                D, cols = groups(v)
                for g in cols:
                    vv = v.copy()
                    vv[g] += steps[g]
                    dB = (render(vv, ssm) - B) @ lin
                    owner = np.full(I.size, -1)
                    for k in g:
                        owner[D[:, k]] = k
                    ok = owner >= 0
                    J[ok, owner[ok]] = -dB[ok] * w[ok] / steps[owner[ok]]
            for k in act[act >= K]:
                vv = v.copy()
                vv[k] += steps[k]
                J[:, k] = -((render(vv, ssm) - B) @ lin) * w / steps[k]
            cols_ = np.concatenate([act, n_par + np.arange(3)])
            Jf = np.hstack([J, -B * w[:, None]])[:, cols_]
            pr, pj = penalty(v)
            Lp = np.hstack([pj, np.zeros((pj.shape[0], n_par - K + 3))])[:, cols_]
            JTJ = Jf.T @ Jf + Lp.T @ Lp
            g_ = Jf.T @ res + Lp.T @ pr
            improved, dc, st = False, 0.0, np.zeros(n_par)
            for _ in range(6):
                A = JTJ + lam * np.diag(np.diag(JTJ) + 1e-12)
                try:
                    step = -np.linalg.solve(A, g_)
                except np.linalg.LinAlgError:
                    lam *= 10
                    continue
                st = np.zeros(n_par)
                st[act] = step[:act.size]
                st = st * min(1.0, float(np.min(max_step / (np.abs(st) + 1e-300))))  # trust region
                vn = np.clip(v + st, lb, ub)
                cn_, Bn, linn, resn = cost_of(vn, w, ssm)
                if cn_ < cost:
                    dc = cost - cn_
                    v, cost, B, lin, res = vn, cn_, Bn, linn, resn
                    lam = max(lam / 5, 1e-6)
                    improved = True
                    break
                lam *= 8
            if not improved or (dc < 1e-5 * cost and np.max(np.abs(st[:K + 2])) < 5e-3):
                break
            moved = np.max(np.abs(model.basis @ (v[:K] - band_v[0][:K]))) + abs(v[K] - band_v[0][K]) * 2
            if moved > 0.4:
                ssm = ss_band(v)
                band_v[0] = v.copy()
                cost, B, lin, res = cost_of(v, w, ssm)
        return v, cost, B, lin, res, ssm, JTJ, it, act

    band_v = [v.copy()]
    glob = np.zeros(n_par, bool)
    glob[K:] = True
    v, cost, B, lin, res, ssm, JTJ, it0, act = lm(v, cost, B, lin, res, ssm, glob, 8)
    w = 1.0 / (noise * bg * np.sqrt(np.clip(B @ lin, 0.05 * bg, None) / bg))  # re-weight
    cost, B, lin, res = cost_of(v, w, ssm)
    v, cost, B, lin, res, ssm, JTJ, it, act = lm(v, cost, B, lin, res, ssm, np.ones(n_par, bool), max_iter)
    it += it0

    p = _unpack(v, K, coat_on)
    dof = max(1, I.size - n_par - 3)
    chi2 = float(res @ res) / dof
    stderr = {}
    flags = []
    try:
        cov = np.linalg.inv(JTJ) * chi2 if JTJ is not None else None
    except np.linalg.LinAlgError:
        cov = None
    if cov is not None:
        sd_ = np.sqrt(np.clip(np.diag(cov)[:act.size], 0, None))
        stderr = {nm: float(x) for nm, x in zip(names, sd_) if not nm.startswith("c")}
        stderr["delta_max"] = float(np.max(sd_[:K]))
        if coat_on:
            rel_c, rel_k = sd_[K + 5], sd_[K + 4]
            at_bound = np.any(v[K + 2:] >= ub[K + 2:] - 1e-6) or np.any(v[K + 2:] <= lb[K + 2:] + 1e-6)
            if rel_c > 0.3 or rel_k > 0.3 or at_bound:
                flags.append(f"coating not identifiable (rel. s.e. thickness {rel_c:.2f}, core k {rel_k:.2f})")
    hit = np.nonzero(np.abs(v[:K]) >= 3.99)[0]
    if hit.size:
        flags.append(f"edge offset hit its bound (+-4 px) at knots {hit.tolist()} of {K}")

    # ---- output: outer silhouette, both flanks, 1 px apart, left -> apex -> right
    r, z = model.curve(p["c"])
    fr = model.frame(p)
    z = np.maximum.accumulate(z)  # as in the body model
    sel = z <= 1.3 * hpx
    r, z = r[sel], z[sel]
    sa = np.concatenate([[0.0], np.cumsum(np.hypot(np.diff(r), np.diff(z)))])
    so = np.arange(0.0, sa[-1], 1.0)
    ro, zo = np.interp(so, sa, r), np.interp(so, sa, z)
    xo = np.concatenate([-ro[:0:-1], ro])
    zo = np.concatenate([zo[:0:-1], zo])
    pts_out = fr.to_image(xo, zo)
    nrm = np.column_stack([np.gradient(pts_out[:, 1]), -np.gradient(pts_out[:, 0])])
    nrm /= np.hypot(*nrm.T)[:, None] + 1e-12
    edge = EdgeFit(pts_out, nrm, np.ones(len(pts_out), bool), float(p["k_o"]), float(p["k_c"]),
                   float(p["coat"]), float(p["sigma"]), float(np.sqrt(np.mean((res / w) ** 2))),
                   np.full(len(pts_out), float(lin[0])))
    params = dict(sigma_px=float(p["sigma"]), k_outer=float(p["k_o"]), k_core=float(p["k_c"]),
                  coat_px=float(p["coat"]), axis_shift_px=float(p["x0"]), axis_rot_rad=float(p["dth"]),
                  apex_shift_px=float(-(model.basis[0] @ p["c"])), knot_px=knot, n_knots=K,
                  background=bg, gradient=lin[1:].tolist())
    return GlobalFit(edge, fr, params, stderr, flags, int(I.size), it, chi2)
