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
extra parameters) with physical values (0.1 < k_o/k_c < 0.8, thickness >= MIN_COAT_PX).
A layered fit within +-``COAT_DCHI2`` of the single layer is neither found nor
excluded (thin light oxide at coarse pixels, heavy blur or low SNR: the image cannot
say whether it is there): the single-layer edge is kept, flagged "coating
ambiguous", and its covariance widened by a common offset of half the largest outward
shift among such layered fits (the SD of a 50/50 mixture of the two edges).  A coated fit whose
thickness has a relative standard error > 30 % is flagged "coating not
identifiable".  A given thickness (``coat_hint``) starts the coated fit there and
keeps it.

The result carries, for every output edge point, its B-spline row and the
covariance of the c_k (marginal over all other parameters, px^2; from finite-
difference spline columns at the solution, ``_Fitter.polish``): the fit stage
propagates it into the covariance of (n, Q) (neighbouring edge points are strongly
correlated, so a point-wise residual scatter would understate it).
"""
from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
from scipy import ndimage, sparse
from scipy.spatial import cKDTree

from pipeline.tem.edges import TipFrame
from pipeline.tem.projection import chord, chord_sq, core_radius_sq_table

__all__ = ["GlobalFit", "fit_silhouette", "reference_curve", "COAT_DCHI2"]

# pixel integration: the projected thickness has a square-root kink at a silhouette, which
# the midpoint rule samples poorly; pixels whose centre lies within _FINE_PX of a silhouette
# (the kink is inside them) are averaged over 8 x 8 sub-samples, those up to _BAND_PX over
# 4 x 4 (smooth there), the rest at the centre.  4 x 4 everywhere left a model error on a
# flat face along a pixel row that a thin phantom layer absorbed (noise-free n 6 at 0.5 nm px:
# chi^2 -592 with the layer; the edge 0.48 nm out) and biased n there by +0.08.
_SS_FINE, _SS = 8, 4
_FINE_PX, _BAND_PX = 1.0, 2.0


def _sub_offsets(m):
    """(drow, dcol) of m x m sub-samples of a pixel (centre at 0)."""
    sub = (np.arange(m) + 0.5) / m - 0.5
    return np.column_stack([np.repeat(sub, m), np.tile(sub, m)])
KNOT_NM = 1.2  # knot spacing of the edge-offset spline (nm)
COAT_DCHI2 = 10.0  # chi^2 decrease needed to accept a coating layer (2 extra parameters, p ~ 0.5 %)
# layer thicknesses (px) tried as starts of the coated fit; a start converges to the layer
# only within ~30 % of its thickness (measured on 96 synthetic cases, oxide 1-2.5 nm)
COAT_GRID_PX = (1.5, 2.0, 2.5, 3.0, 4.0, 5.0, 6.0, 7.5, 9.0, 11.0)
# a hidden light layer (contrast ratio 1/3) widens the single-layer blur: sigma_single^2 ~
# sigma^2 + BLUR_PER_COAT t^2 (px; 0.25-0.31 measured for t = 2-6 px, blur 0.5 and 2 px)
BLUR_PER_COAT = 0.28
# thicker layers than COAT_PER_BLUR x sigma_single are not tried: the relation allows
# t <= 1.9 sigma_single with no blur at all; layers of weaker contrast widen the blur less
# (ratio 0.5: t/sigma_single <= 1.7, ratio 0.7: <= 2.4 measured), 0.8 is not accepted anyway
COAT_PER_BLUR = 2.6
# thinnest layer that counts as one (px, the smallest start of the search): with the coated model
# continuous in the thickness, a 1.1 px layer of contrast 0.45 under a 1 px blur absorbed the
# single-layer model's own error on a noise-free uncoated flat face (chi^2 -19, edge 0.1 nm out)
MIN_COAT_PX = 1.5
COAT_START_ITERS = 3  # full LM iterations from each of the two best starts
COAT_EXTRA_STARTS = 3  # further starts tried when the decision is borderline
POLISH_MIN_DCHI2 = 1.0  # an exact Gauss-Newton step is taken if chi^2 falls by more than this x K
GLOBAL_EPS = 4e-3  # central-difference step of the global columns of the exact Jacobian (log units)
# weight of the soft monotone-flank penalty (1/px).  Flat faces: a bump is seen through
# the vacuum, a dimple (a hole in the section) only through the dark body, so a hard
# constraint (100) pushes a noisy face outwards and none (0) lets it sink inwards; 20
# leaves the least bias in n over blunt tips at SNR 10-15 (n 4.6-6: mean |dn| 0.03 -> 0.01)
MONOTONE_WEIGHT = 20.0


def _bspline(u):
    """Cardinal cubic B-spline (support |u| < 2)."""
    a = np.abs(u)
    out = np.where(a < 1, 2 / 3 - a**2 + 0.5 * a**3, 0.0)
    return np.where((a >= 1) & (a < 2), (2 - a) ** 3 / 6, out)


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


def reference_curve(pts_tip, step=0.25, smooth_px=2.0):
    """Smoothed polyline (x, z) (tip frame, px) -> S (signed arc length, apex 0), x, z, nx, nz."""
    x, z = pts_tip
    if x[0] > x[-1]:
        x, z = x[::-1], z[::-1]
    seg = np.hypot(np.diff(x), np.diff(z))
    keep = np.concatenate([[True], seg > 1e-9])
    x, z = x[keep], z[keep]
    s = np.concatenate([[0.0], np.cumsum(np.hypot(np.diff(x), np.diff(z)))])
    si = np.arange(0.0, s[-1], step)
    x, z = np.interp(si, s, x), np.interp(si, s, z)
    if smooth_px > 0:
        x = ndimage.gaussian_filter1d(x, smooth_px / step, mode="nearest")
        z = ndimage.gaussian_filter1d(z, smooth_px / step, mode="nearest")
    s = np.concatenate([[0.0], np.cumsum(np.hypot(np.diff(x), np.diff(z)))])
    S = s - s[int(np.argmin(z))]
    tx, tz = np.gradient(x, s), np.gradient(z, s)
    nn = np.hypot(tx, tz) + 1e-12
    return S, x, z, tz / nn, -tx / nn


class _Body:
    """Cross-section tables of the body bounded by a (left -> right) meridian polyline.

    At height z the section is the disc spanning the outermost points of the curve at or
    below z (cen +- rho), minus a hole on each side of the lowest point where the curve
    rises above z in between (a dimple or a valley beyond a ridge, as a disc of its own).
    The holes make inward and outward wiggles of a flat face equally visible: with the
    filled envelope alone, a dimple is invisible while a bump is not, and noise then
    pushes the fitted apex outwards (n biased low on blunt tips)."""

    dz = 0.1

    def __init__(self, x, z, coat):
        i0 = int(np.argmin(z))
        halves = [(x[: i0 + 1][::-1], z[: i0 + 1][::-1]), (x[i0:], z[i0:])]  # apex -> outwards
        z0 = z[i0]
        z_out = [np.minimum.accumulate(zh[::-1])[::-1] for _, zh in halves]  # outermost crossing
        top = max(min(z_out[0][-1], z_out[1][-1]), z0 + 2 * self.dz)
        self.zg = np.arange(z0, top + 1e-9, self.dz)
        xo = [np.interp(self.zg, zo + 1e-9 * np.arange(zo.size), xh) for zo, (xh, _) in zip(z_out, halves)]
        self.rho = np.maximum(0.5 * (xo[1] - xo[0]), 0.0)
        self.cen = 0.5 * (xo[1] + xo[0])
        self.holes = [h for h in (self._hole(xh, zh) for xh, zh in halves) if h is not None]
        self.set_coat(coat)

    def _hole(self, xh, zh):
        """(radius, centre) tables of the gap between the first and the last crossing of
        each level along one half (apex -> outwards), or None if the half is monotone."""
        rm = np.maximum.accumulate(zh)
        dip = np.nonzero(zh < rm)[0]
        if dip.size == 0:
            return None
        # only the levels spanned by the dips, only the points up to the last dip
        lv = (self.zg >= zh[dip].min() - self.dz) & (self.zg <= rm[dip].max() + self.dz)
        zg = self.zg[lv]
        xh, zh = xh[: dip[-1] + 2], zh[: dip[-1] + 2]
        below = zh[None, :] <= zg[:, None]  # (levels, points)
        up = below[:, :-1] & ~below[:, 1:]  # leaves the sublevel set between i and i+1
        down = ~below[:, :-1] & below[:, 1:]  # re-enters it
        has = down.any(1) & up.any(1)
        if not has.any():
            return None
        i_up = np.argmax(up, 1)
        i_dn = down.shape[1] - 1 - np.argmax(down[:, ::-1], 1)
        has &= i_dn > i_up

        def cross(i):
            za, zb = zh[i], zh[i + 1]
            t = np.clip((zg - za) / np.where(zb != za, zb - za, 1.0), 0.0, 1.0)
            return xh[i] + t * (xh[i + 1] - xh[i])

        xa, xb = cross(i_up), cross(i_dn)
        has_lv = np.nonzero(lv)[0][has]
        if has_lv.size == 0:
            return None
        rad = np.full(self.zg.size, -1.0)
        cen = np.zeros(self.zg.size)
        rad[lv] = np.where(has, 0.5 * np.abs(xb - xa), -1.0)
        cen[lv] = np.where(has, 0.5 * (xa + xb), xa)
        # levels whose interpolation can see the hole
        lo, hi = max(0, has_lv[0] - 1), min(self.zg.size - 1, has_lv[-1] + 1)
        return rad, cen, lo, hi

    def set_coat(self, coat):
        self.coat = float(coat)
        # squared radii for the interpolation (no material: 0); the core on its own grid, which
        # starts at its apex, coat above the outer one (continuous in coat and in the shape)
        self.rho2 = np.square(np.maximum(self.rho, 0.0))
        self.zc0 = self.zg[0] + self.coat
        self.rho_c2 = core_radius_sq_table(self.rho2, self.dz, self.coat) if self.coat > 0 else self.rho2

    def chords(self, x, z, core=True):
        """(t_outer, t_core) at tip-frame points (px); t_core only if ``core``."""
        f = (z - self.zg[0]) / self.dz
        below = f < 0
        f = np.clip(f, 0.0, self.zg.size - 1.000001)
        i = f.astype(np.intp)
        w = f - i
        cen = self.cen[i] * (1 - w) + self.cen[i + 1] * w
        xx = x - cen
        # rho^2 is interpolated between the table rows, not rho: it is linear in z at a
        # paraboloidal apex and far less curved than rho(z) ~ z^(1/n) on a flatter one, whose
        # radius jumps from 0 to the face within a fraction of a row (rho interpolated
        # linearly put a noise-free coated n 4 apex 0.045 nm off, rho^2 0.01 nm)
        rho2 = self.rho2[i] * (1 - w) + self.rho2[i + 1] * w
        t_o = np.where(below, 0.0, chord_sq(rho2, xx))
        for rad, hc, lo, hi in self.holes:
            j = np.nonzero((i >= lo) & (i < hi) & ~below)[0]
            ij, wj = i[j], w[j]
            r_h = rad[ij] * (1 - wj) + rad[ij + 1] * wj
            c_h = hc[ij] * (1 - wj) + hc[ij + 1] * wj
            t_o[j] = np.maximum(t_o[j] - chord(r_h, x[j] - c_h), 0.0)
        if not core or self.coat <= 0:
            return t_o, t_o
        fc = (z - self.zc0) / self.dz
        below_c = fc < 0
        fc = np.clip(fc, 0.0, self.rho_c2.size - 1.000001)
        ic = fc.astype(np.intp)
        wc = fc - ic
        rc2 = self.rho_c2[ic] * (1 - wc) + self.rho_c2[ic + 1] * wc
        return t_o, np.where(below_c, 0.0, chord_sq(rc2, xx))


class _Problem:
    """Fixed pixel geometry, data and the forward model of one silhouette fit."""

    def __init__(self, img, frame, curve, hpx, noise, knot, sigma_max=4.0):
        self.img, self.frame = img, frame
        self.knot = knot
        self.set_reference(curve)
        S, x0, z0, nx, nz = curve
        self.ztop = 1.02 * hpx
        H, W = img.shape
        # residual pixels: band around the initial curve, z <= ztop
        out_m, in_m = 3.0 * 1.5 + 4.0, 3.0 * 1.5 + 14.0
        sel = z0 <= self.ztop + out_m + 2
        ci = frame.to_image(x0[sel], z0[sel])
        mrg = int(np.ceil(out_m + in_m + 4 * sigma_max + 4))
        r_lo = int(max(0, np.floor(ci[:, 0].min()) - mrg))
        r_hi = int(min(H, np.ceil(ci[:, 0].max()) + mrg + 1))
        c_lo = int(max(0, np.floor(ci[:, 1].min()) - mrg))
        c_hi = int(min(W, np.ceil(ci[:, 1].max()) + mrg + 1))
        self.shape = (r_hi - r_lo, c_hi - c_lo)
        RR, CC = np.mgrid[r_lo:r_hi, c_lo:c_hi].astype(float)
        P = np.column_stack([RR.ravel(), CC.ravel()])
        px, pz = frame.to_tip(P)
        # distance to the curve's vertices 1 px apart (it is sampled every 0.25 px): at the
        # band limits (>= 8 px away) the excess over the true distance is < 0.02 px
        dec = max(1, int(round(1.0 / max(S[1] - S[0], 1e-9))))
        tree = cKDTree(np.column_stack([x0[::dec], z0[::dec]]))
        dist, _ = tree.query(np.column_stack([px, pz]), distance_upper_bound=in_m + 1)
        body0 = _Body(x0, z0, 0.0)
        t0, _ = body0.chords(px, pz, core=False)
        inside = t0 > 0
        sd = np.where(inside, -dist, dist)
        use = (sd <= out_m) & (sd >= -in_m) & (pz <= self.ztop)
        # blur support must stay inside the rectangle (unless it is the image border)
        bm = int(np.ceil(4 * sigma_max + 1))
        rl, cl = RR.ravel() - r_lo, CC.ravel() - c_lo
        use &= ((rl >= bm) | (r_lo == 0)) & ((rl < self.shape[0] - bm) | (r_hi == H))
        use &= ((cl >= bm) | (c_lo == 0)) & ((cl < self.shape[1] - bm) | (c_hi == W))
        self.idx = np.nonzero(use)[0]
        if self.idx.size < 50:
            raise ValueError("too few pixels near the edge for the silhouette fit")
        need = np.zeros(self.shape, bool)
        need.ravel()[self.idx] = True
        need = ndimage.binary_dilation(need, np.ones((3, 3), bool), int(np.ceil(4 * sigma_max)) + 2)
        self.need = np.nonzero(need.ravel())[0]
        self.nx_, self.nz_ = px[self.need], pz[self.need]
        # position of each residual pixel within the need list
        pos = np.full(P.shape[0], -1)
        pos[self.need] = np.arange(self.need.size)
        self.res_in_need = pos[self.idx]
        self.I = img[r_lo:r_hi, c_lo:c_hi].ravel()[self.idx]
        rn = (RR.ravel()[self.idx] - 0.5 * (r_lo + r_hi)) / max(H, 1)
        cn = (CC.ravel()[self.idx] - 0.5 * (c_lo + c_hi)) / max(W, 1)
        self.rn, self.cn = rn, cn
        self.rows, self.cols = RR.ravel()[self.idx], CC.ravel()[self.idx]
        self.pz_res = pz[self.idx]
        self.px_res = px[self.idx]
        # sub-pixel offsets in the tip frame (rotation only)
        self.sub = [(off @ frame.v, off @ frame.u) for off in (_sub_offsets(_SS_FINE), _sub_offsets(_SS))]
        self.noise = noise
        self.w = np.ones(self.idx.size)
        self.map_c = None

    def set_reference(self, curve):
        """Reference meridian (S, x, z, nx, nz) and its B-spline basis (knots every D)."""
        S, x0, z0, nx, nz = curve
        self.S, self.x0, self.z0, self.nx, self.nz = S, x0, z0, nx, nz
        k_lo = int(np.floor(S[0] / self.knot)) - 1
        k_hi = int(np.ceil(S[-1] / self.knot)) + 1
        self.kc = np.arange(k_lo, k_hi + 1)
        self.K = self.kc.size
        idx, val = self.spline_rows(S)
        self.Bc = sparse.csr_matrix((val.ravel(), (np.repeat(np.arange(S.size), 4), idx.ravel())),
                                    shape=(S.size, self.K)).toarray()
        self.map_c = None

    def rebase(self, c):
        """Make the curve of offsets ``c`` the new reference (offsets then start at 0): the
        smoothness penalty then acts relative to the fitted shape, not the contour's."""
        x, z = self.curve(c)
        self.set_reference(reference_curve((x, z), step=float(self.S[1] - self.S[0]), smooth_px=0.0))

    # ------------------------------------------------------------------ geometry
    def curve(self, c):
        d = self.Bc @ c
        return self.x0 + d * self.nx, self.z0 + d * self.nz

    def spline_rows(self, S):
        """Sparse B-spline rows at arc positions S: (index (N, 4) into c, value (N, 4))."""
        u = S / self.knot
        j0 = np.floor(u).astype(int) - 1
        j = j0[:, None] + np.arange(4)[None, :]
        val = _bspline(u[:, None] - j)
        return np.clip(j - self.kc[0], 0, self.K - 1), val

    def update_pixel_map(self, c, coat):
        """Nearest curve point of every needed pixel: B-spline rows of the residual pixels
        (local-translation Jacobian) and the distance map that selects the pixels to
        supersample."""
        x, z = self.curve(c)
        # only residual pixels can be near a silhouette (outer edge: inside the band by
        # construction; core: coat <= 12 px < inner band width)
        # the curve is sampled every 0.25 px; every 2nd point is close enough (distance error
        # <= 0.13 px, arc position <= 0.25 px)
        dec = 2
        xs, zs = x[::dec], z[::dec]
        j_old = self._j_res if getattr(self, "_j_ref", None) is self.S else None
        if j_old is None:
            d, j = cKDTree(np.column_stack([xs, zs])).query(np.column_stack([self.px_res, self.pz_res]))
        else:
            # the curve moved < 1 px since the last map: search +-4 px of arc around the
            # old nearest point; pixels whose nearest point lies on the window edge are
            # looked up in a k-d tree
            w = 8
            cand = np.clip(j_old[:, None] + np.arange(-w, w + 1)[None, :], 0, xs.size - 1)
            d2 = (xs[cand] - self.px_res[:, None]) ** 2 + (zs[cand] - self.pz_res[:, None]) ** 2
            k = np.argmin(d2, axis=1)
            rows = np.arange(k.size)
            j, d = cand[rows, k], np.sqrt(d2[rows, k])
            redo = np.nonzero(((k == 0) & (j > 0)) | ((k == 2 * w) & (j < xs.size - 1)))[0]
            if redo.size:
                d[redo], j[redo] = cKDTree(np.column_stack([xs, zs])).query(
                    np.column_stack([self.px_res[redo], self.pz_res[redo]]))
        self._j_res, self._j_ref = j, self.S
        self.dist_need = np.full(self.need.size, np.inf)
        self.dist_need[self.res_in_need] = d
        idx, val = self.spline_rows(self.S[::dec][j])
        self.u_res = self.S[::dec][j] / self.knot - self.kc[0]  # knot coordinate of each pixel
        n = idx.shape[0]
        self.Phi = sparse.csr_matrix((val.ravel(), (np.repeat(np.arange(n), 4), idx.ravel())), shape=(n, self.K))
        self.map_c, self.map_coat = c.copy(), float(coat)

    def map_stale(self, c, coat):
        # B-splines are >= 0 and sum to 1: no curve point moved more than max |dc|
        return (self.map_c is None or np.max(np.abs(c - self.map_c)) > 0.6
                or abs(coat - self.map_coat) > 0.6)

    # ------------------------------------------------------------------ forward model
    def chords(self, c, coat, sub=None):
        """Chords (t_o, t_c) at the needed pixel centres, and at sub-samples of the pixels near
        the outer or core silhouette (T is averaged there, where it has the square-root kink):
        8 x 8 within _FINE_PX, 4 x 4 up to _BAND_PX.  Returns (t_o, t_c, bands), bands a list
        of (pixel indices, sub-sample t_o, sub-sample t_c, sub-samples per pixel).  ``sub``
        (indices into the needed pixels): only those, with band indices local to ``sub``."""
        if self.map_stale(c, coat):
            self.update_pixel_map(c, coat)
        x, z = self.curve(c)
        body = _Body(x, z, coat)
        xc, zc, dist = self.nx_, self.nz_, self.dist_need
        if sub is not None:
            xc, zc, dist = xc[sub], zc[sub], dist[sub]
        t_o, t_c = body.chords(xc, zc)
        # the bands are fixed between updates of the distance map (the model must be smooth
        # in the parameters for the finite differences)
        sd = np.where(t_o > 0, -dist, dist)
        near = np.abs(sd)
        if self.map_coat > 0:
            near = np.minimum(near, np.abs(sd + self.map_coat))
        bands = []
        for (sx, sz), sel in zip(self.sub, (near < _FINE_PX, (near >= _FINE_PX) & (near < _BAND_PX))):
            bi = np.nonzero(sel)[0]
            xs = (xc[bi, None] + sx[None, :]).ravel()
            zs = (zc[bi, None] + sz[None, :]).ravel()
            s_o, s_c = body.chords(xs, zs)
            bands.append((bi, s_o, s_c, sx.size))
        return (t_o, t_c, bands)

    @staticmethod
    def transmission(ch, k_o, k_c):
        t_o, t_c, bands = ch
        T = np.exp(-(k_o * t_o + (k_c - k_o) * t_c))
        for bi, s_o, s_c, m in bands:
            if bi.size:
                T[bi] = np.exp(-(k_o * s_o + (k_c - k_o) * s_c)).reshape(-1, m).mean(1)
        return T

    def blurred(self, T, sigma):
        """Columns (Npix, 3): blur(T), blur(T) x row, blur(T) x col at the residual pixels."""
        img = np.ones(self.shape[0] * self.shape[1])
        img[self.need] = T
        img = img.reshape(self.shape)
        if sigma > 0.05:
            img = ndimage.gaussian_filter(img, sigma, mode="nearest", truncate=4.0)
        bt = img.ravel()[self.idx]
        return np.column_stack([bt, bt * self.rn, bt * self.cn])

    def linear(self, B):
        A = B * self.w[:, None]
        return np.linalg.solve(A.T @ A, A.T @ (self.I * self.w))  # 3 x 3 normal equations

    def set_weights(self, model):
        """Poisson weights 1/sd with sd = noise x sqrt(model / background) (flattened image)."""
        m = np.clip(model, 0.05, None)
        self.w = 1.0 / (self.noise * np.sqrt(m))


@dataclass
class _State:
    v: np.ndarray
    cost: float
    ch: tuple
    T: np.ndarray
    B: np.ndarray
    lin: np.ndarray
    res: np.ndarray


class _Fitter:
    """Levenberg-Marquardt over (c, log sigma, log k_o[, log k_c, log coat]) (+ linear)."""

    def __init__(self, prob: _Problem, coated, smooth_weight=2.0, mu=MONOTONE_WEIGHT):
        self.p = prob
        self.coated = coated
        K = prob.K
        self.K = K
        self.L2 = np.sqrt(smooth_weight) * np.diff(np.eye(K), 2, axis=0)
        # monotone z along each flank: sample the curve every ~D/4 from the apex outwards
        S = prob.S
        i0 = int(np.argmin(np.abs(S)))
        stp = max(1, int(round(prob.knot / 4 / max(S[1] - S[0], 1e-9))))
        right = np.arange(i0, S.size, stp)
        left = np.arange(i0, -1, -stp)
        rows_a, rows_b = [], []
        for br in (right, left):
            rows_a.append(br[1:])
            rows_b.append(br[:-1])
        a, b = np.concatenate(rows_a), np.concatenate(rows_b)
        self.Az = prob.Bc[a] * prob.nz[a, None] - prob.Bc[b] * prob.nz[b, None]
        self.bz = prob.z0[a] - prob.z0[b]
        self.mu = mu

    def unpack(self, v):
        K = self.K
        sigma, k_o = np.exp(v[K]), np.exp(v[K + 1])
        if self.coated:
            return v[:K], sigma, k_o, np.exp(v[K + 2]), np.exp(v[K + 3])
        return v[:K], sigma, k_o, k_o, 0.0

    def penalty(self, c):
        # second differences of the offsets, and a soft monotone z along each flank
        dz = self.Az @ c + self.bz
        neg = dz < 0
        r = np.concatenate([self.L2 @ c, self.mu * np.where(neg, dz, 0.0)])
        J = np.vstack([self.L2, self.mu * self.Az * neg[:, None]])
        return r, J

    def evaluate(self, v, ch=None):
        c, sigma, k_o, k_c, coat = self.unpack(v)
        if ch is None:
            ch = self.p.chords(c, coat)
        T = self.p.transmission(ch, k_o, k_c)
        B = self.p.blurred(T, sigma)
        lin = self.p.linear(B)
        res = (self.p.I - B @ lin) * self.p.w
        pr, _ = self.penalty(c)
        return _State(v, float(res @ res + pr @ pr), ch, T, B, lin, res)

    def jacobian(self, st: _State, with_shape=True, central=False):
        """Weighted Jacobian of the residuals: G (Npix,), the column of a uniform outward
        offset of the whole curve (shape columns are phi_k(S_i) G_i, local translation), and
        the dense columns of the globals and the linear parameters, with their names.

        The global columns are forward differences of 0.02 in log (the LM steps), or with
        ``central`` central differences of GLOBAL_EPS (the exact Jacobian: near the optimum the
        gradient J^T r is what decides where the fit stops, and a forward step of 2 % in the
        layer thickness, 0.15 px, misstates it by ~50 on a coated flat face)."""
        p = self.p
        c, sigma, k_o, k_c, coat = self.unpack(st.v)
        M0 = st.B @ st.lin

        def col(B):
            return -(B @ st.lin - M0) * p.w

        G = None
        if with_shape:
            eps = 0.05
            ch = p.chords(c + eps, coat)  # partition of unity: all c + eps = uniform offset
            G = col(p.blurred(p.transmission(ch, k_o, k_c), sigma)) / eps
        models = [lambda e: p.blurred(st.T, sigma * np.exp(e))]
        names = ["log_sigma"]
        if self.coated:
            models += [lambda e: p.blurred(p.transmission(st.ch, k_o * np.exp(e), k_c), sigma),
                       lambda e: p.blurred(p.transmission(st.ch, k_o, k_c * np.exp(e)), sigma),
                       lambda e: p.blurred(p.transmission(p.chords(c, coat * np.exp(e)), k_o, k_c), sigma)]
            names += ["log_k_o", "log_k_c", "log_coat"]
        else:
            models.append(lambda e: p.blurred(p.transmission(st.ch, k_o * np.exp(e), k_o * np.exp(e)), sigma))
            names.append("log_k_o")
        if central:
            e = GLOBAL_EPS
            cols = [(col(m(e)) - col(m(-e))) / (2 * e) for m in models]
        else:
            cols = [col(m(0.02)) / 0.02 for m in models]
        Jo = np.column_stack(cols + [-st.B * p.w[:, None]])
        return G, Jo, names + ["lin_a", "lin_row", "lin_col"]

    def height_bands(self, c, coat):
        """Range of tip-frame heights (px) of the curve points under each knot's support,
        widened by the layer thickness (the core points that depend on them).

        A meridian point is a ring of the body of revolution: moving it changes the projected
        thickness along the whole horizontal line of pixels at its height inside the ring
        (both sides of the axis), not only near the point; the core (erosion by ``coat``)
        moves with it within +-coat of its height (taking only the core point along the
        normal missed part of that on a flat coated face: gradient errors of 4-8 at the
        apex knots).  Pixel sub-samples reach 1.5 px further, the blur 4 sigma."""
        p = self.p
        x, z = p.curve(c)
        lo, hi = np.full(self.K, np.inf), np.full(self.K, -np.inf)
        u = p.S / p.knot - p.kc[0]  # knot coordinate of every curve point
        for k in range(self.K):
            m = np.abs(u - k) < 2.0
            if m.any():
                # the core is the erosion by a disk of radius coat: a core point at height z
                # depends on the outer curve anywhere within z +- coat
                lo[k] = float(z[m].min()) - coat
                hi[k] = float(z[m].max()) + coat
        return lo, hi

    def exact_jacobian(self, st, eps=0.05):
        """Weighted Jacobian at ``st`` with finite-difference shape columns: (state on a fixed
        pixel map, Jc (Npix, K), Jo (Npix, globals + linear), names).

        The local-translation columns used for the LM steps credit a pixel to the nearest
        point of the curve; the projection of a body of revolution does not work that way
        (``height_bands``): near the apex and on a flat face they are wrong by 50-240 %, and a
        fixed point of those steps is not the least-squares optimum.  Here knots whose height
        bands do not overlap are perturbed in one rendering (greedy colouring of the interval
        graph, optimal), and each pixel's change goes to the knot whose band holds its height."""
        p, K = self.p, self.K
        c, sigma, k_o, k_c, coat = self.unpack(st.v)
        p.update_pixel_map(c, coat)  # one fixed pixel map for the base and the perturbations
        st = self.evaluate(st.v)
        _, Jo, names = self.jacobian(st, with_shape=False, central=True)
        M0 = st.B @ st.lin
        lo0, hi0 = self.height_bands(c, coat)
        pad = 3.0 * sigma + 1.5  # sub-samples and blur (its tail beyond 3 sigma: ~1 %)
        lo, hi = lo0 - pad, hi0 + pad
        groups, ends = [], []
        for k in np.argsort(lo):
            if not np.isfinite(lo[k]):
                continue
            for g, e in enumerate(ends):
                if e < lo[k]:
                    groups[g].append(k)
                    ends[g] = hi[k]
                    break
            else:
                groups.append([k])
                ends.append(hi[k])
        zr, zn = p.pz_res, p.nz_
        Jc = np.zeros((zr.size, K))
        for ks in groups:
            ks = np.asarray(ks)
            v = st.v.copy()
            v[ks] += eps
            # only the pixels whose chords can change are re-rendered
            sub = np.zeros(zn.size, bool)
            for k in ks:
                sub |= (zn >= lo0[k] - 1.5) & (zn <= hi0[k] + 1.5)
            sub = np.nonzero(sub)[0]
            T = st.T.copy()
            T[sub] = p.transmission(p.chords(v[:K], coat, sub), k_o, k_c)
            B = p.blurred(T, sigma)
            d = -(B @ st.lin - M0) * p.w / eps
            # bands of one group are disjoint and sorted: the knot whose band holds each pixel
            j = np.searchsorted(lo[ks], zr, side="right") - 1
            ok = (j >= 0) & (zr <= hi[ks[np.clip(j, 0, None)]])
            Jc[ok, ks[j[ok]]] = d[ok]
        self.n_groups = len(groups)
        return st, Jc, Jo, [f"c{k}" for k in range(K)] + names

    def polish(self, st, lb, ub, max_step, steps=2):
        """J^T J (incl. the penalty) of ``exact_jacobian``, for the covariance, and up to
        ``steps`` Gauss-Newton steps with it where the LM solution is clearly short of the
        optimum.

        The LM steps use local-translation columns and stop where THOSE are stationary.  Where
        the signal dominates that is far from the least-squares optimum: a coated fit at 0.1 nm
        px, SNR 20 lies 520-1440 above it in chi^2, and these steps halve the scatter of n there
        (SD 0.015 -> 0.008, bound 0.005).  Where the noise dominates a step only refits noise
        (chi^2 falls by 2-12 with K = 43-89 shape parameters) and the LM solution, held back by
        its columns like a regularised fit, scatters less (n 2 at 0.5 nm px, SNR 10: SD 0.14
        against 0.18 stepped; bound 0.15).  So a step (each component within the LM step limits,
        or half of it) is taken only if it lowers chi^2 by more than K; a second one, with the same
        Jacobian, follows the first (a first step can overshoot where the model is far from linear).
        Returns (state, J^T J, names) with J^T J at the LM solution (the covariance)."""
        K = self.K
        st, Jc, Jo, names = self.exact_jacobian(st)
        J = np.hstack([Jc, Jo])
        JTJ = J.T @ J
        _, pj = self.penalty(st.v[:K])
        JTJ[:K, :K] += pj.T @ pj
        try:
            A = np.linalg.inv(JTJ + 1e-9 * np.diag(np.diag(JTJ) + 1e-12))
        except np.linalg.LinAlgError:
            return st, JTJ, names
        for _ in range(steps):  # the later steps reuse the Jacobian (it barely changes over a step)
            pr, _ = self.penalty(st.v[:K])
            g = J.T @ st.res
            g[:K] += pj.T @ pr
            # the step of (shape, globals); the linear illumination terms come along.  Each
            # component within the LM step limits: a weakly determined knot at the curve's end
            # must not run off, the well-determined rest of the step is kept
            step = np.clip(-(A @ g)[: st.v.size], -max_step, max_step)
            for frac in (1.0, 0.5):
                sn = self.evaluate(np.clip(st.v + frac * step, lb, ub))
                if st.cost - sn.cost > POLISH_MIN_DCHI2 * K:
                    break
            else:
                break
            st = sn
        return st, JTJ, names

    def normal_equations(self, st, shape_mode):
        """J^T J and J^T r over (shape..., globals, linear) incl. the penalty."""
        p, K = self.p, self.K
        G, Jo, names = self.jacobian(st, shape_mode != "none")
        pr, pj = self.penalty(st.v[:K])
        if shape_mode == "full":
            PG = p.Phi.multiply(G[:, None]).tocsr()
            Ass = (PG.T @ PG).toarray() + pj.T @ pj
            Aso = np.asarray(PG.T @ Jo)
            gs = np.asarray(PG.T @ st.res).ravel() + pj.T @ pr
            names = [f"c{k}" for k in range(K)] + names
        elif shape_mode == "uniform":
            ps = pj.sum(1)
            Ass = np.array([[G @ G + ps @ ps]])
            Aso = (G @ Jo)[None, :]
            gs = np.array([G @ st.res + ps @ pr])
            names = ["offset"] + names
        else:
            Ass, Aso, gs = np.zeros((0, 0)), np.zeros((0, Jo.shape[1])), np.zeros(0)
        JTJ = np.block([[Ass, Aso], [Aso.T, Jo.T @ Jo]])
        grad = np.concatenate([gs, Jo.T @ st.res])
        return JTJ, grad, names, Ass.shape[0], Jo.shape[1] - 3

    def run(self, v, shape_mode, iters, lb, ub, max_step, lam=1e-2, tol=1e-5):
        """LM iterations; shape_mode "full" (all c_k), "uniform" (one common offset: all c_k
        equal) or "none"."""
        K = self.K
        st = self.evaluate(v)
        JTJ, it, names = None, 0, []
        for it in range(1, iters + 1):
            if shape_mode == "full" and self.p.map_stale(st.v[:K], self.unpack(st.v)[4]):
                self.p.update_pixel_map(st.v[:K], self.unpack(st.v)[4])
                # the supersampled band moved: the state must be re-evaluated on the new map,
                # or the finite-difference columns against it pick up the band change
                st = self.evaluate(st.v)
            JTJ, grad, names, nsh, ng = self.normal_equations(st, shape_mode)
            improved, dc, dv = False, 0.0, np.zeros_like(v)
            # parameters at a bound whose descent direction points outwards are held fixed
            pv = np.concatenate([st.v[:K] if shape_mode == "full" else st.v[:1] if nsh else [], st.v[K:K + ng]])
            plb = np.concatenate([lb[:nsh], lb[K:K + ng]])
            pub = np.concatenate([ub[:nsh], ub[K:K + ng]])
            held = np.zeros(grad.size, bool)
            held[: nsh + ng] = ((pv <= plb + 1e-9) & (grad[: nsh + ng] > 0)) | ((pv >= pub - 1e-9) & (grad[: nsh + ng] < 0))
            for _ in range(6):
                A = JTJ + lam * np.diag(np.diag(JTJ) + 1e-12)
                A[held, :] = 0.0
                A[:, held] = 0.0
                A[held, held] = 1.0
                try:
                    step = -np.linalg.solve(A, np.where(held, 0.0, grad))[: nsh + ng]
                except np.linalg.LinAlgError:
                    lam *= 10
                    continue
                dv = np.zeros_like(st.v)
                dv[:K] = step[:K] if shape_mode == "full" else (step[0] if nsh else 0.0)
                dv[K:K + ng] = step[nsh:]
                dv *= min(1.0, float(np.min(max_step / (np.abs(dv) + 1e-300))))
                vn = np.clip(st.v + dv, lb, ub)
                sn = self.evaluate(vn)
                if sn.cost < st.cost:
                    dc = st.cost - sn.cost
                    st = sn
                    lam = max(lam / 5, 1e-7)
                    improved = True
                    break
                lam *= 8
            if not improved or (dc < tol * st.cost and np.max(np.abs(dv[:K])) < 5e-3):
                break
        return st, JTJ, names, it


def _axis_attenuation(img, frame, curve, background=1.0):
    """k (1/px) from the transmission on the axis 6-30 px above the apex (blur-free zone)."""
    S, x, z, _, _ = curve
    body = _Body(x, z, 0.0)
    zg = body.zg
    ok = (body.rho > 5) & (zg - zg[0] > 6) & (zg - zg[0] < 30)
    if ok.sum() < 5:
        return float("nan")
    pts = frame.to_image(body.cen[ok], zg[ok])
    I = ndimage.map_coordinates(img, pts.T, order=1, mode="nearest")
    T = np.clip(I / background, 1e-3, 0.999)
    return float(np.median(-np.log(T) / (2 * body.rho[ok])))


def _bin(img, b):
    """b x b block average (trailing rows/cols dropped); binned pixel i = fine b i + (b - 1)/2."""
    if b <= 1:
        return img
    h, w = (img.shape[0] // b) * b, (img.shape[1] // b) * b
    return img[:h, :w].reshape(h // b, b, w // b, b).mean(axis=(1, 3))


def bin_factor(pixel_size, min_px=0.2e-9):
    """Block size for the fit: pixels finer than ``min_px`` are averaged in b x b blocks
    (the edge is then still sampled at <= 2 x min_px; precision is set by the noise and
    the number of pixels along the edge, not by their size)."""
    if not pixel_size:
        return 1
    return int(max(1, np.floor(min_px / pixel_size + 1e-6)))


def _coated_start(f1, st1, lim2, thickness):
    """Coated-model parameters for a layer of ``thickness`` px under the single-layer fit ``st1``.

    The single-layer edge of a hidden light layer lies inside the outer surface by about half
    the layer (outer = single + t/2), and the fit widened its blur to absorb the layer:
    sigma_single^2 ~ sigma^2 + BLUR_PER_COAT t^2, so the layer's own blur is what is left."""
    c1, sg1, ko1, _, _ = f1.unpack(st1.v)
    sg = np.sqrt(max(sg1**2 - BLUR_PER_COAT * thickness**2, 0.3**2))
    v = np.concatenate([c1 + 0.5 * thickness, [np.log(sg), np.log(ko1 * 0.3), np.log(ko1 * 1.2), np.log(thickness)]])
    return np.clip(v, lim2[0] + 1e-6, lim2[1] - 1e-6)


def _converge(f2, st, cost1, lim2, max_iter, chunk=3):
    """LM on a coated fit to convergence, in chunks; stopped early once it is clearly worse
    than the single layer (chi^2 above it by > 3 COAT_DCHI2) and a chunk recovers less than a
    quarter of that deficit.  A start far below may still be on its way (noise-free images
    have one at -2e6 reach +1.4e5), one creeping at -40 is not.  Returns (state, iterations)."""
    n_it = 0
    while n_it < max_iter:
        before = st.cost
        st, _, _, it = f2.run(st.v, "full", min(chunk, max_iter - n_it), *lim2)
        n_it += it
        deficit = st.cost - cost1
        if it < chunk or (deficit > 3 * COAT_DCHI2 and before - st.cost < 0.25 * deficit):
            break
    return st, n_it


def _coating_search(f1, st1, f2, lim2, coat_hint, max_coat, max_iter):
    """Best physical coated fit and the coating decision (module doc, "Coating").

    The coated chi^2 surface has a basin per layer thickness: LM finds the layer only from
    a start within ~30 % of its thickness (and with the shape free: a uniform shift of the
    single-layer edge does not reach it on a blunt tip, whose flat face sees the layer through
    a longer chord than the flanks).  So: every thickness of ``COAT_GRID_PX`` that the
    single-layer blur leaves room for (t <= COAT_PER_BLUR sigma_single) is evaluated once
    from ``_coated_start``, the two best get ``COAT_START_ITERS`` full LM iterations and the
    better one is converged.  Only PHYSICAL fits (0.1 < k_o/k_c < 0.8, thickness >= MIN_COAT_PX)
    count: a coated fit with no contrast between the layers is the single layer fitting
    noise.  When the decision is borderline, ``COAT_EXTRA_STARTS`` more starts are tried.
    The decision compares LM solutions (``_Fitter.polish`` notes that LM stops short of the
    optimum, a layered fit further than a single one: the test errs towards no layer).
    Returns (state or None, iterations, coating-test dict)."""
    K = f1.K
    cost1 = st1.cost
    c1, sg1, _, _, _ = f1.unpack(st1.v)
    if coat_hint:
        cands = [float(np.clip(coat_hint, 0.6, max_coat * 0.95))]
    else:
        cands = [t for t in COAT_GRID_PX if t <= min(max_coat * 0.95, COAT_PER_BLUR * sg1)]
    test = {"model": "single", "threshold": COAT_DCHI2, "candidates_px": list(cands)}
    if not cands:
        test["skipped"] = "no room for a layer >= 1.5 px in the single-layer blur"
        return None, 0, test

    def physical(st):
        _, _, ko, kc, coat = f2.unpack(st.v)
        return bool(0.1 * kc < ko < 0.8 * kc and coat >= MIN_COAT_PX)

    starts = [_coated_start(f1, st1, lim2, t) for t in cands]
    order = np.argsort([f2.evaluate(v).cost for v in starts])
    n_it = 0
    runs = []
    for j in order[:2]:
        st, _, _, it = f2.run(starts[j], "full", COAT_START_ITERS, *lim2)
        n_it += it
        runs.append(st)
        if cost1 - st.cost > 3 * COAT_DCHI2 and physical(st):
            break  # a clear layer from the best-ranked start: the second is not needed
    st, it = _converge(f2, min(runs, key=lambda r: r.cost), cost1, lim2, max_iter)
    n_it += it
    runs.append(st)

    def best_physical():
        ph = [r for r in runs if physical(r)]
        return min(ph, key=lambda r: r.cost) if ph else None

    bp = best_physical()
    gain = cost1 - bp.cost if bp is not None else -np.inf
    if not coat_hint and (bp is None or -3 * COAT_DCHI2 < gain <= COAT_DCHI2):
        # borderline: a layer neither found nor clearly excluded (or none physical yet); a
        # physical layer found worse than the single layer may be a local minimum (the thin
        # oxides missed at coarse pixels and low SNR ended at -13 to -26)
        for j in order[2:2 + COAT_EXTRA_STARTS]:
            st, _, _, it = f2.run(starts[j], "full", COAT_START_ITERS, *lim2)
            n_it += it
            runs.append(st)
        nb = best_physical()
        if nb is not None and (bp is None or nb.cost < bp.cost):
            st, it = _converge(f2, nb, cost1, lim2, max_iter)
            n_it += it
            runs.append(st)
        bp = best_physical()
    if coat_hint:
        bp = min(runs, key=lambda r: r.cost)
    if bp is None:
        test["physical"] = False
        return None, n_it, test
    # a start that won after its first iterations: converged like the single-layer fit
    bp, it = _converge(f2, bp, cost1, lim2, max_iter)
    n_it += it
    _, _, ko2, kc2, coat2 = f2.unpack(bp.v)
    gain = float(st1.cost - bp.cost)
    # outward shift of the coated model's outer edge relative to the single layer's
    shift = float(np.mean(bp.v[:K] - c1))
    test.update(dchi2=gain, physical=physical(bp), thickness_px=float(coat2), contrast_ratio=float(ko2 / kc2),
                outer_shift_px=shift)
    if coat_hint or (gain > COAT_DCHI2 and physical(bp)):
        test["model"] = "coated"
    else:
        # light layers that fit about as well as none are neither found nor excluded: the
        # edge may lie as far out as the largest of them puts it
        def shift_of(r):
            return float(np.mean(r.v[:K] - c1))

        alike = [r for r in runs if physical(r) and cost1 - r.cost > -COAT_DCHI2 and shift_of(r) > 0.25]
        if physical(bp) and gain > -COAT_DCHI2 and shift_of(bp) > 0.25:
            alike.append(bp)
        if alike:
            # thicker layers stopped after their start iterations just outside the threshold
            # may reach it when converged: the largest shift needs them
            reach = max(shift_of(r) for r in alike)
            near = [r for r in runs if physical(r) and -3 * COAT_DCHI2 < cost1 - r.cost <= -COAT_DCHI2
                    and shift_of(r) > reach]
            for r in sorted(near, key=shift_of, reverse=True)[:2]:
                st, it = _converge(f2, r, cost1, lim2, max_iter)
                n_it += it
                if physical(st) and cost1 - st.cost > -COAT_DCHI2 and shift_of(st) > 0.25:
                    alike.append(st)
            far = max(alike, key=shift_of)
            _, _, ko_f, kc_f, coat_f = f2.unpack(far.v)
            test.update(ambiguous=True, ambiguous_shift_px=shift_of(far), ambiguous_thickness_px=float(coat_f),
                        ambiguous_dchi2=float(cost1 - far.cost))
    return bp, n_it, test


def fit_silhouette(flat, contour, frame: TipFrame, hpx, noise, pixel_size=None, coat_hint=None,
                   knot_nm=None, max_iter=25, binning=None) -> GlobalFit:
    """Fit the silhouette model (module doc) to ``flat`` (window with the background
    flattened to 1, tip pointing down), starting from ``contour`` (iso-line outside the
    surface, window px) in ``frame``; ``hpx`` profile height (px), ``noise`` background
    noise (relative); ``coat_hint`` None (auto), 0 (none) or a thickness (px).
    ``binning``: block size (default ``bin_factor(pixel_size)``); results are in the
    pixels of ``flat``."""
    b = int(binning or bin_factor(pixel_size))
    if b > 1:
        off = 0.5 * (b - 1)
        gf = fit_silhouette(_bin(np.asarray(flat, float), b), (np.asarray(contour) - off) / b,
                            TipFrame((frame.apex - off) / b, frame.angle), hpx / b, noise / b,
                            pixel_size * b, None if coat_hint is None else coat_hint / b, knot_nm, max_iter,
                            binning=1)
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
        if "candidates_px" in ct:
            ct["candidates_px"] = [t * b for t in ct["candidates_px"]]
        return gf
    flat = np.asarray(flat, float)
    knot_nm = knot_nm if knot_nm is not None else KNOT_NM
    knot = float(np.clip(knot_nm * 1e-9 / pixel_size if pixel_size else 6.0, 4.0, 16.0))
    # the reference must be smooth on the knot scale: its finer wiggles (contour noise)
    # would pass straight into the result, the spline offsets correct the large scales
    curve = reference_curve(frame.to_tip(contour), smooth_px=1.5 * knot)
    # noise floor 0.2 % of the background: model error of the forward model (noise-free images)
    prob = _Problem(flat, frame, curve, hpx, max(float(noise or 0.0), 2e-3), knot)
    K = prob.K
    k_ax = _axis_attenuation(flat, frame, curve)
    k0 = k_ax if np.isfinite(k_ax) and k_ax > 0 else 0.02
    max_coat = 12.0

    def bounds(coated):
        lb = [-6.0] * K + [np.log(0.25), np.log(k0 * 0.05)]
        ub = [6.0] * K + [np.log(4.0), np.log(k0 * 20)]
        ms = [0.6] * K + [0.25, 0.3]
        if coated:
            lb += [np.log(k0 * 0.05), np.log(0.5)]
            ub += [np.log(k0 * 20), np.log(max_coat)]
            ms += [0.3, 0.25]
        return np.array(lb), np.array(ub), np.array(ms)

    n_it = 0
    # 1) single layer, uniform offset from the contour + globals, two blur starts
    f1 = _Fitter(prob, coated=False)
    lim1 = bounds(False)
    best = None
    for sg in (0.8, 2.0):  # two blur starts, 2 iterations each; the better one goes on
        v = np.concatenate([np.full(K, -1.0), [np.log(sg), np.log(k0)]])
        st, _, _, it = f1.run(v, "uniform", 2, *lim1, tol=1e-4)
        n_it += it
        if best is None or st.cost < best.cost:
            best = st
    best, _, _, it = f1.run(best.v, "uniform", 6, *lim1, tol=1e-4)
    n_it += it
    prob.set_weights(best.B @ best.lin)
    # 2) single layer, full shape; then again relative to the fitted shape (the penalty
    #    on the offsets' curvature would otherwise keep the contour's rounded corners)
    st1, _, _, it = f1.run(best.v, "full", max_iter, *lim1)
    n_it += it
    prob.rebase(st1.v[:K])
    glob = st1.v[K:]
    K = prob.K
    f1 = _Fitter(prob, coated=False)
    lim1 = bounds(False)
    st1, _, _, it = f1.run(np.concatenate([np.zeros(K), glob]), "full", max_iter, *lim1)
    n_it += it
    fitter, st = f1, st1
    coat_test = {"model": "single"}
    if coat_hint and coat_hint > 0.95 * max_coat:
        # a given layer thicker than the fitted band: its core is outside the fitted pixels,
        # where the outer layer alone is seen (a thick DLC coating); a coated model would put
        # a core edge where the image has none
        coat_test["note"] = (f"the given layer ({coat_hint:.1f} px) is thicker than the fitted band "
                             f"({max_coat:.0f} px inside the edge): the outer layer is fitted alone")
        coat_hint = 0.0
    if coat_hint is None or coat_hint > 0:
        # 3) coated model: search over the layer thickness, then LM from the best start
        f2 = _Fitter(prob, coated=True)
        lim2 = bounds(True)
        st2, it, coat_test = _coating_search(f1, st1, f2, lim2, coat_hint, max_coat, max_iter)
        n_it += it
        if coat_test["model"] == "coated":
            fitter, st = f2, st2
    lim = bounds(fitter.coated)
    st, JTJ, names = fitter.polish(st, *lim)
    prob.map_c = None
    return _result(prob, fitter, st, JTJ, names, n_it, hpx, coat_test, pixel_size)


def _result(prob, fitter, st, JTJ, names, n_it, hpx, coat_test, pixel_size=None):
    c, sigma, k_o, k_c, coat = fitter.unpack(st.v)
    K = prob.K
    dof = max(1, prob.idx.size - len(names))
    chi2 = float(st.res @ st.res) / dof
    flags, stderr = [], {}
    try:
        cov = np.linalg.inv(JTJ) * max(chi2, 1.0)
    except np.linalg.LinAlgError:
        cov = np.full(JTJ.shape, np.nan)
        flags.append("singular silhouette covariance")
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
        flags.append(f"coating ambiguous: a light layer {coat_test['ambiguous_thickness_px'] * nm:.2f} nm thick changes "
                     f"chi^2 by {-coat_test['ambiguous_dchi2']:+.1f} (accepted below -{COAT_DCHI2:g}, excluded above "
                     f"+{COAT_DCHI2:g}); "
                     f"the edge may lie up to {shift * nm:.2f} nm further out; edge covariance widened "
                     f"(set tem.coating if the layer is known)")
    if fitter.coated:
        if stderr.get("log_coat", 0) > 0.3 or stderr.get("log_k_c", 0) > 0.3:
            flags.append(f"coating not identifiable (rel. s.e. thickness {stderr.get('log_coat', np.nan):.2f})")
    # output: outer silhouette at 1 px spacing in arc length, z <= 1.3 x profile height
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
    nrm = np.column_stack([nxo * prob.frame.v[0] + nzo * prob.frame.u[0], nxo * prob.frame.v[1] + nzo * prob.frame.u[1]])
    hit = np.nonzero(np.abs(c) >= 5.99)[0]
    if hit.size:
        flags.append(f"edge offset hit its bound (+-6 px) at {hit.size} of {K} knots")
    rms = float(np.sqrt(np.mean((st.res / prob.w) ** 2)))
    return GlobalFit(pts, nrm, basis, cov_c, prob.frame, float(sigma), float(k_o), float(k_c), float(coat), rms,
                     chi2, int(prob.idx.size), int(n_it), stderr, flags, coat_test)
