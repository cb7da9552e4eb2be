"""Forward model of the silhouette fit (``pipeline.tem.silhouette_fit``, its doc): the meridian's
B-spline offsets, the body's cross-section tables, the Beer-Lambert image of the body with pixel
integration and blur, and the binning of the image."""

from __future__ import annotations

import numpy as np
from scipy import ndimage, sparse
from scipy.spatial import cKDTree

from pipeline.tem.offset_loops import trimmed_loops
from pipeline.tem.projection import chord, core_radius_sq_table

# pixel integration: the projected thickness has a square-root kink at a silhouette, which
# the midpoint rule samples poorly; pixels whose centre lies within _FINE_PX of a silhouette
# (the kink is inside them) are averaged over 8 x 8 sub-samples, those up to _BAND_PX over
# 4 x 4 (smooth there), the rest at the centre.  4 x 4 everywhere left a model error on a
# flat face along a pixel row that a thin phantom layer absorbed (noise-free n 6 at 0.5 nm px:
# chi^2 -592 with the layer; the edge 0.48 nm out) and biased n there by +0.08.
_SS_FINE, _SS = 8, 4
_FINE_PX, _BAND_PX = 1.0, 2.0
# The pixel map is refreshed once the curve (or the layer thickness) moved more than this
# (px).  It must not equal the LM's step limit on the offsets (0.6 px, ``silhouette_fit._bounds``):
# a step at the limit moves the curve by exactly that, up to rounding, and with the two equal
# the last bit decided whether the map was refreshed, and the fit's path followed.  Below the
# limit a full step always refreshes the map.  benchmarks/bench_tem_path_dependence.py (120
# images; n moved by > 1e-6 / > 0.1): fitted window x (1 + 1e-12) 81 / 31 with the threshold
# at 0.6, 12 / 2 at 0.5; core table x (1 + 1e-13) 13 / 5, then 1 (by 6e-5) / 0.
MAP_REFRESH_PX = 0.5
LINEAR_ACTIVE_SET_ITERS = 5  # solves of the illumination with censored pixels (``_Problem.linear``)


def _sub_offsets(m):
    """(drow, dcol) of m x m sub-samples of a pixel (centre at 0)."""
    sub = (np.arange(m) + 0.5) / m - 0.5
    return np.column_stack([np.repeat(sub, m), np.tile(sub, m)])


KNOT_NM = 1.2  # knot spacing of the edge-offset spline (nm)


def _bspline(u):
    """Cardinal cubic B-spline (support |u| < 2)."""
    a = np.abs(u)
    out = np.where(a < 1, 2 / 3 - a**2 + 0.5 * a**3, 0.0)
    return np.where((a >= 1) & (a < 2), (2 - a) ** 3 / 6, out)


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


def _extreme_cover(lo, hi, seg, n_levels, fill, reduce):
    """Per level index in [0, n_levels): ``reduce`` (np.minimum / np.maximum) of the ``seg``
    whose range [lo, hi) holds it, ``fill`` where none does."""
    cnt = np.maximum(hi - lo, 0)
    out = np.full(n_levels, fill)
    total = int(cnt.sum())
    if total:
        start = np.repeat(lo - (np.cumsum(cnt) - cnt), cnt)
        reduce.at(out, start + np.arange(total), np.repeat(seg, cnt))
    return out


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
        each level along one half (apex -> outwards), with the rows whose interpolation can
        see it (``chords``), or None if the half is monotone."""
        rm = np.maximum.accumulate(zh)
        dip = np.nonzero(zh < rm)[0]
        if dip.size == 0:
            return None
        # only the levels spanned by the dips, only the points up to the last dip
        lv = (self.zg >= zh[dip].min() - self.dz) & (self.zg <= rm[dip].max() + self.dz)
        zg = self.zg[lv]
        xh, zh = xh[: dip[-1] + 2], zh[: dip[-1] + 2]
        # segment i leaves the sublevel set {z <= level} (up) for the levels in
        # [z_i, z_i+1), re-enters it (down) for those in [z_i+1, z_i): per level the first
        # up and the last down segment (level index ranges by bisection, no levels x points table)
        q = np.searchsorted(zg, zh, side="left")
        nseg = zh.size - 1
        seg = np.arange(nseg)
        first_up = _extreme_cover(q[:-1], q[1:], seg, zg.size, nseg, np.minimum)
        last_dn = _extreme_cover(q[1:], q[:-1], seg, zg.size, -1, np.maximum)
        has = (first_up < nseg) & (last_dn >= 0)
        if not has.any():
            return None
        i_up = np.where(first_up < nseg, first_up, 0)
        i_dn = np.where(last_dn >= 0, last_dn, nseg - 1)
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
        # the rows whose interpolation can see the hole (a radius > 0 at row i or i + 1): elsewhere the
        # interpolated radius is <= 0 and its chord 0
        return rad, cen, (rad[:-1] > 0) | (rad[1:] > 0)

    def set_coat(self, coat):
        self.coat = float(coat)
        # squared radii for the interpolation (no material: 0); the core on its own grid, which
        # starts at its apex, coat above the outer one (continuous in coat and in the shape)
        self.rho2 = np.square(np.maximum(self.rho, 0.0))
        self.zc0 = self.zg[0] + self.coat
        self.rho_c2 = core_radius_sq_table(self.rho2, self.dz, self.coat) if self.coat > 0 else self.rho2

    def chords(self, x, z, core=True):
        """(t_outer, t_core) at tip-frame points (px); t_core only if ``core``."""
        core = core and self.coat > 0
        below, i, w, w1 = _rows(z, self.zg[0], self.dz, self.zg.size)
        xx = x - _lerp(self.cen, i, w, w1)
        # rho^2 is interpolated between the table rows, not rho: it is linear in z at a
        # paraboloidal apex and far less curved than rho(z) ~ z^(1/n) on a flatter one, whose
        # radius jumps from 0 to the face within a fraction of a row (rho interpolated
        # linearly put a noise-free coated n 4 apex 0.045 nm off, rho^2 0.01 nm)
        t_o = _chord_in_place(_lerp(self.rho2, i, w, w1), xx, below)
        for rad, hc, rows in self.holes:
            # only points with material (where t_o = 0 the hole leaves it 0) on the rows that see the hole
            j = np.nonzero((t_o > 0) & rows[i])[0]
            ij, wj, wj1 = i[j], w[j], w1[j]
            t_o[j] = np.maximum(t_o[j] - chord(_lerp(rad, ij, wj, wj1), x[j] - _lerp(hc, ij, wj, wj1)), 0.0)
        if not core:
            return t_o, t_o
        return t_o, self._core(z, xx)

    def core_chords(self, x, z):
        """t_core alone at tip-frame points (px) (the outer body's centre line is needed)."""
        below, i, w, w1 = _rows(z, self.zg[0], self.dz, self.zg.size)
        return self._core(z, x - _lerp(self.cen, i, w, w1))

    def _core(self, z, xx):
        below, i, w, w1 = _rows(z, self.zc0, self.dz, self.rho_c2.size)
        return _chord_in_place(_lerp(self.rho_c2, i, w, w1), xx, below)


def _beer_lambert(t_o, t_c, k_o, k_c):
    """exp(-(k_o t_o + (k_c - k_o) t_c)); the second term (+0) skipped for one layer (k_c = k_o)."""
    a = k_o * t_o
    if k_c != k_o:
        a += (k_c - k_o) * t_c
    np.negative(a, out=a)
    return np.exp(a, out=a)


def _square_of_difference(a, b):
    """(a - b)^2, in ``a``'s buffer."""
    a -= b
    return np.square(a, out=a)


def _rows(z, z0, dz, n):
    """(below the table, row i, weight w of row i + 1, 1 - w) of linear interpolation at
    heights ``z`` in a table of ``n`` rows z0 + j dz (clipped to its ends)."""
    f = z - z0
    f /= dz
    below = f < 0
    np.clip(f, 0.0, n - 1.000001, out=f)
    i = f.astype(np.intp)
    f -= i
    return below, i, f, 1 - f


def _lerp(table, i, w, w1):
    """table[i] (1 - w) + table[i + 1] w (``_rows``), in one buffer (row i + 1 read as row i of
    the table's view from its second row: no index array i + 1)."""
    out = np.take(table, i)
    out *= w1
    b = np.take(table[1:], i)
    b *= w
    out += b
    return out


def _chord_in_place(r2, xx, below):
    """``projection.chord_sq(r2, xx)`` (0 where ``below``), computed in ``r2``'s buffer."""
    r2 -= np.square(xx)
    np.maximum(r2, 0.0, out=r2)
    np.sqrt(r2, out=r2)
    r2 *= 2.0
    r2[below] = 0.0
    return r2


# the residual pixels' band (px) outside and inside the starting contour (``_Problem``): 3 x 1.5 px for the
# contour's own distance from the edge, plus 4 px of vacuum or 14 px of body
BAND_OUTSIDE_PX, BAND_INSIDE_PX = 3.0 * 1.5 + 4.0, 3.0 * 1.5 + 14.0

# what ``_Problem.update_pixel_map`` and ``offset_map`` set: the pixel map
_MAP_ATTRS = ("_j_res", "_j_ref", "dist_need", "u_res", "Phi", "map_c", "map_coat")


class _Problem:
    """Fixed pixel geometry, data and the forward model of one silhouette fit."""

    def __init__(self, img, frame, curve, hpx, noise, knot, sigma_max=4.0, censored=None):
        self.img, self.frame = img, frame
        self.knot = knot
        self.set_reference(curve)
        S, x0, z0, nx, nz = curve
        self.ztop = 1.02 * hpx
        H, W = img.shape
        # residual pixels: band around the initial curve, z <= ztop
        out_m, in_m = BAND_OUTSIDE_PX, BAND_INSIDE_PX
        sel = z0 <= self.ztop + out_m + 2
        ci = frame.to_image(x0[sel], z0[sel])
        mrg = int(np.ceil(out_m + in_m + 4 * sigma_max + 4))
        r_lo = int(max(0, np.floor(ci[:, 0].min()) - mrg))
        r_hi = int(min(H, np.ceil(ci[:, 0].max()) + mrg + 1))
        c_lo = int(max(0, np.floor(ci[:, 1].min()) - mrg))
        c_hi = int(min(W, np.ceil(ci[:, 1].max()) + mrg + 1))
        self.shape, self.origin = (r_hi - r_lo, c_hi - c_lo), (r_lo, c_lo)  # origin: its first pixel (row, col)
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
        self.cens = _censored_at(censored, (slice(r_lo, r_hi), slice(c_lo, c_hi)), self.idx)
        self.rn = (RR.ravel()[self.idx] - 0.5 * (r_lo + r_hi)) / max(H, 1)
        self.cn = (CC.ravel()[self.idx] - 0.5 * (c_lo + c_hi)) / max(W, 1)
        self.rows, self.cols = RR.ravel()[self.idx], CC.ravel()[self.idx]
        self.pz_res = pz[self.idx]
        self.px_res = px[self.idx]
        # sub-pixel offsets in the tip frame (rotation only)
        self.sub = [(off @ frame.v, off @ frame.u) for off in (_sub_offsets(_SS_FINE), _sub_offsets(_SS))]
        self.noise = noise
        self.w = np.ones(self.idx.size)
        self.map_c = None
        self.tiles, self._canvas = _blur_tiles(self.idx, self.shape), np.ones(self.shape)  # ``blurred``'s

    def set_reference(self, curve):
        """Reference meridian (S, x, z, nx, nz) and its B-spline basis (knots every D)."""
        S, x0, z0, nx, nz = curve
        self.S, self.x0, self.z0, self.nx, self.nz = S, x0, z0, nx, nz
        k_lo = int(np.floor(S[0] / self.knot)) - 1
        k_hi = int(np.ceil(S[-1] / self.knot)) + 1
        self.kc = np.arange(k_lo, k_hi + 1)
        self.K = self.kc.size
        idx, val = self.spline_rows(S)
        self.Bc = sparse.csr_matrix(
            (val.ravel(), (np.repeat(np.arange(S.size), 4), idx.ravel())), shape=(S.size, self.K)
        ).toarray()
        self.map_c = None
        self.version = getattr(self, "version", 0) + 1  # (map, weights, reference) changed

    def rebase(self, c):
        """Make the curve of offsets ``c`` the new reference (offsets then start at 0): the
        smoothness penalty then acts relative to the fitted shape, not the contour's."""
        x, z = self.curve(c)
        self.set_reference(reference_curve((x, z), step=float(self.S[1] - self.S[0]), smooth_px=0.0))

    # ------------------------------------------------------------------ geometry
    def curve(self, c):
        """(x, z) of the meridian with offsets ``c`` along the reference normals, any loop of the
        moved curve cut off (``offset_loops``)."""
        d = self.Bc @ c
        return trimmed_loops(self.x0 + d * self.nx, self.z0 + d * self.nz, self.nx, self.nz)

    def spline_rows(self, S):
        """Sparse B-spline rows at arc positions S: (index (N, 4) into c, value (N, 4))."""
        u = S / self.knot
        j0 = np.floor(u).astype(int) - 1
        j = j0[:, None] + np.arange(4)[None, :]
        val = _bspline(u[:, None] - j)
        return np.clip(j - self.kc[0], 0, self.K - 1), val

    def update_pixel_map(self, c, coat, cold=False):
        """Nearest curve point of every needed pixel: B-spline rows of the residual pixels
        (local-translation Jacobian) and the distance map that selects the pixels to
        supersample.  The search starts from the last map's nearest points (a local search:
        its result can depend on the earlier maps); ``cold``: a k-d tree over the whole
        curve, so that the map is a function of (c, coat) alone."""
        x, z = self.curve(c)
        # only residual pixels can be near a silhouette (outer edge: inside the band by
        # construction; core: coat <= 12 px fitted, 14 px held (``held_layer.HELD_MAX_PX``) < inner band width)
        # the curve is sampled every 0.25 px; every 2nd point is close enough (distance error
        # <= 0.13 px, arc position <= 0.25 px)
        dec = 2
        xs, zs = x[::dec], z[::dec]
        j_old = self._j_res if not cold and getattr(self, "_j_ref", None) is self.S else None
        if j_old is None:
            d, j = cKDTree(np.column_stack([xs, zs])).query(np.column_stack([self.px_res, self.pz_res]))
        else:
            # the curve moved < 1 px since the last map: search +-4 px of arc around the
            # old nearest point; pixels whose nearest point lies on the window edge are
            # looked up in a k-d tree
            w = 8
            cand = j_old[:, None] + np.arange(-w, w + 1)[None, :]
            np.clip(cand, 0, xs.size - 1, out=cand)
            d2 = _square_of_difference(np.take(xs, cand), self.px_res[:, None])
            d2 += _square_of_difference(np.take(zs, cand), self.pz_res[:, None])
            k = np.argmin(d2, axis=1)
            rows = np.arange(k.size)
            j, d = cand[rows, k], np.sqrt(d2[rows, k])
            redo = np.nonzero(((k == 0) & (j > 0)) | ((k == 2 * w) & (j < xs.size - 1)))[0]
            if redo.size:
                d[redo], j[redo] = cKDTree(np.column_stack([xs, zs])).query(
                    np.column_stack([self.px_res[redo], self.pz_res[redo]])
                )
        self._j_res, self._j_ref = j, self.S
        self.dist_need = np.full(self.need.size, np.inf)
        self.dist_need[self.res_in_need] = d
        idx, val = self.spline_rows(self.S[::dec][j])
        self.u_res = self.S[::dec][j] / self.knot - self.kc[0]  # knot coordinate of each pixel
        n = idx.shape[0]
        self.Phi = sparse.csr_matrix((val.ravel(), (np.repeat(np.arange(n), 4), idx.ravel())), shape=(n, self.K))
        self.map_c, self.map_coat = c.copy(), float(coat)
        self.version = getattr(self, "version", 0) + 1

    def map_kept(self):
        """The pixel map as it is (``update_pixel_map``'s attributes), for ``restore_map``."""
        return {k: getattr(self, k, None) for k in _MAP_ATTRS}

    def restore_map(self, kept):
        """Put back the pixel map ``kept`` (``map_kept``) after a trial of other bodies, under a new version
        (the states evaluated meanwhile are not reused): the fit goes on as if they had not been tried."""
        for k, v in kept.items():
            setattr(self, k, v)
        self.version = getattr(self, "version", 0) + 1

    def offset_map(self, c, coat, delta, sd0):
        """Make the pixel map that of the curve ``c`` moved by a uniform ``delta`` (px, outward +;
        the curve of c + delta), derived from ``sd0``, the needed pixels' signed distances (px,
        inside -) in the map of ``c`` itself: each pixel keeps its nearest point, its distance
        becomes |sd0 - delta_q|, delta_q = delta rounded to MAP_REFRESH_PX, so the supersampled
        bands stay fixed within each such step as between the fit's own refreshes.  A function of
        (c, coat, delta) alone; a refresh of the map along an optimiser's path would make the model
        depend on the path (the defocus-fringe correction moves the edge by up to 10 px).  The
        offset moves the curve along the reference normals, which differ from the fitted curve's
        by up to ~25 deg, so the distances are approximate: against a map made afresh for the moved
        curve, within 0.15 px at |delta| = 1 px and 0.3-1.3 px at 4-10 px near the curve (it only
        chooses which pixels are sub-sampled; the chords are exact; measured on two test tips, the
        fitted offset moved by <= 0.013 px, 0.3 of its standard error)."""
        dq = MAP_REFRESH_PX * np.round(delta / MAP_REFRESH_PX)
        self.dist_need = np.abs(sd0 - dq)
        self.map_c, self.map_coat = c + delta, float(coat)
        self.version = getattr(self, "version", 0) + 1

    def map_stale(self, c, coat):
        # B-splines are >= 0 and sum to 1: no curve point moved more than max |dc|
        return (
            self.map_c is None
            or np.max(np.abs(c - self.map_c)) > MAP_REFRESH_PX
            or abs(coat - self.map_coat) > MAP_REFRESH_PX
        )

    # ------------------------------------------------------------------ forward model
    def chords(self, c, coat, sub=None, outer=None, body=None, centres=None):
        """Chords (t_o, t_c) at the needed pixel centres, and at sub-samples of the pixels near
        the outer or core silhouette (T is averaged there, where it has the square-root kink):
        8 x 8 within _FINE_PX, 4 x 4 up to _BAND_PX.  Returns (t_o, t_c, bands), bands a list
        of (pixel indices, sub-sample t_o, sub-sample t_c, sub-samples per pixel).  ``sub``
        (indices into the needed pixels): only those, with band indices local to ``sub``.
        ``outer``: (chords of this ``c`` for another layer thickness, the ``version`` they were
        made on): their outer chords are taken as they are if the pixel map is still that one.
        ``body`` (the ``_Body`` of this ``c`` and ``coat``) and ``centres`` ((t_o, t_c) at the
        needed pixel centres, from that body): a caller that has them already (the fringe
        correction) passes them in; the numbers are the same."""
        if self.map_stale(c, coat):
            self.update_pixel_map(c, coat)
        if outer is not None:
            outer = outer[0] if outer[1] == self.version else None
        if body is None:
            body = _Body(*self.curve(c), coat)
        xc, zc, dist = self.nx_, self.nz_, self.dist_need
        if sub is not None:
            xc, zc, dist = xc[sub], zc[sub], dist[sub]
        if centres is not None and sub is None and outer is None:
            t_o, t_c = centres
        elif outer is None:
            t_o, t_c = body.chords(xc, zc)
        else:
            t_o = outer[0]
            t_c = body.core_chords(xc, zc) if body.coat > 0 else t_o
        # the bands are fixed between updates of the distance map (the model must be smooth
        # in the parameters for the finite differences)
        sd = np.where(t_o > 0, -dist, dist)
        near = np.abs(sd)
        if self.map_coat > 0:
            near = np.minimum(near, np.abs(sd + self.map_coat))
        bands = []
        for k, ((sx, sz), sel) in enumerate(zip(self.sub, (near < _FINE_PX, (near >= _FINE_PX) & (near < _BAND_PX)))):
            bi = np.nonzero(sel)[0]
            xs = (xc[bi, None] + sx[None, :]).ravel()
            zs = (zc[bi, None] + sz[None, :]).ravel()
            if outer is None:
                s_o, s_c = body.chords(xs, zs)
            else:
                s_o = outer[2][k][1]
                s_c = body.core_chords(xs, zs) if body.coat > 0 else s_o
            bands.append((bi, s_o, s_c, sx.size))
        return (t_o, t_c, bands)

    @staticmethod
    def transmission(ch, k_o, k_c):
        t_o, t_c, bands = ch
        T = _beer_lambert(t_o, t_c, k_o, k_c)
        for bi, s_o, s_c, m in bands:
            if bi.size:
                T[bi] = _beer_lambert(s_o, s_c, k_o, k_c).reshape(-1, m).mean(1)
        return T

    def blurred(self, T, sigma):
        """Columns (Npix, 3): blur(T), blur(T) x row, blur(T) x col at the residual pixels.

        The blur of the rectangle is computed only on the tiles that hold residual pixels, each
        widened by the kernel radius (cut at the rectangle's sides, where the "nearest"
        extension is the rectangle's own): the same numbers at those pixels as one blur of
        the whole rectangle (the separable passes read nothing outside the widened tile)."""
        img = self._canvas
        img.ravel()[self.need] = T  # every needed pixel is written: the same image as a fresh one
        if sigma > 0.05:
            rad, k = _gauss_kernel(sigma)
            H, W = self.shape
            bt = np.empty(self.idx.size)
            for sel, rr, cc, (r0, r1, c0, c1) in self.tiles:
                a0, b0 = max(0, r0 - rad), max(0, c0 - rad)
                blk = ndimage.correlate1d(img[a0 : min(H, r1 + rad), b0 : min(W, c1 + rad)], k, 0, mode="nearest")
                blk = ndimage.correlate1d(blk[r0 - a0 : r1 - a0], k, 1, mode="nearest")  # the tile's rows only
                bt[sel] = blk[rr - r0, cc - b0]
        else:
            bt = img.ravel()[self.idx]
        B = np.empty((bt.size, 3))
        B[:, 0] = bt
        np.multiply(bt, self.rn, out=B[:, 1])
        np.multiply(bt, self.cn, out=B[:, 2])
        return B

    def linear(self, B):
        """Illumination (a, b_row, b_col) by weighted linear least squares (3 x 3 normal equations).
        With censored pixels, the minimum of the censored residual (``model``): first without them,
        then with those the model leaves below their value, as data at that value, until that set
        stops changing (at most ``LINEAR_ACTIVE_SET_ITERS`` solves)."""
        if self.cens is None:
            A = B * self.w[:, None]
            return np.linalg.solve(A.T @ A, A.T @ (self.I * self.w))
        use = ~self.cens
        for _ in range(LINEAR_ACTIVE_SET_ITERS):
            w = self.w * use
            A = B * w[:, None]
            lin = np.linalg.solve(A.T @ A, A.T @ (self.I * w))
            now = ~self.cens | (B @ lin < self.I)
            if np.array_equal(now, use):
                break
            use = now
        return lin

    def n_data(self, B, lin):
        """Residual pixels that count at (B, lin): all but the censored ones whose model is above
        their value (those say nothing more and have residual 0: not degrees of freedom)."""
        if self.cens is None:
            return int(self.idx.size)
        return int(np.count_nonzero(~self.cens | (B @ lin < self.I)))

    def model(self, B, lin):
        """Image model at the residual pixels, B @ lin; at a censored pixel it is held at the value
        read wherever it is above it (the residual is then 0: the image is at least that)."""
        M = B @ lin
        return M if self.cens is None else np.where(self.cens, np.minimum(M, self.I), M)

    def active(self, M):
        """Weights of the linear parameters' Jacobian columns at the model ``M`` (``model``): 0 at
        the censored pixels whose model is above their value, else 1 (None: all 1)."""
        return None if self.cens is None else (~self.cens | (M < self.I)).astype(float)

    def set_weights(self, model):
        """Poisson weights 1/sd with sd = noise x sqrt(model / background) (flattened image)."""
        m = np.clip(model, 0.05, None)
        self.w = 1.0 / (self.noise * np.sqrt(m))
        self.version = getattr(self, "version", 0) + 1


def _censored_at(censored, rect, idx):
    """The censored residual pixels (a saturated detector: the image is at least the value read
    there; bool at the flat indices ``idx`` of the rectangle ``rect`` of ``censored``), or None if
    none of them is."""
    if censored is None:
        return None
    cens = np.asarray(censored, bool)[rect].ravel()[idx]
    return cens if cens.any() else None


def _gauss_kernel(sigma, truncate=4.0):
    """(radius, weights) of ``ndimage.gaussian_filter``'s 1-D kernel (same numbers)."""
    rad = int(truncate * float(sigma) + 0.5)
    x = np.arange(-rad, rad + 1)
    phi = np.exp(-0.5 / (sigma * sigma) * x**2)
    return rad, (phi / phi.sum())[::-1]


def _blur_tiles(idx, shape, rows=64, gap=48):
    """Tiles of the residual pixels ``idx`` (flat indices into ``shape``) for ``_Problem.blurred``:
    strips of ``rows`` rows, split where a strip's pixels leave more than ``gap`` columns free
    (the two flanks); each (positions in ``idx``, their rows, their columns, (row0, row1, col0,
    col1) of the tile, ends exclusive)."""
    rr, cc = np.divmod(idx, shape[1])
    tiles = []
    for s in np.unique(rr // rows):
        sel = np.nonzero(rr // rows == s)[0]
        sel = sel[np.argsort(cc[sel], kind="stable")]
        cut = np.nonzero(np.diff(cc[sel]) > gap)[0] + 1
        for part in np.split(sel, cut):
            r, c = rr[part], cc[part]
            tiles.append((part, r, c, (int(r.min()), int(r.max()) + 1, int(c.min()), int(c.max()) + 1)))
    return tiles


def _axis_attenuation(img, frame, curve, background=1.0):
    """k (1/px) from the transmission on the axis 6-30 px above the apex (blur-free zone).  The rows
    are chosen by index (6 and 30 px lie on the table's grid: compared as heights, the row at 6 px
    read 6.0 or 6.000000000000002 by the rounding of the axis angle, was in or out of the median,
    and the fit started from another k on each arithmetic path)."""
    S, x, z, _, _ = curve
    body = _Body(x, z, 0.0)
    zg = body.zg
    rows = np.arange(zg.size)
    ok = (body.rho > 5) & (rows > np.floor(6.0 / body.dz + 0.5)) & (rows < np.floor(30.0 / body.dz + 0.5))
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
