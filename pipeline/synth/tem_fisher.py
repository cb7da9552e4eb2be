"""Cramér-Rao lower bound (CRB) for the power index n of a tip in a synthetic side-view TEM image.

Model.  The image of ``pipeline.synth.tem_image.render_tem_image`` has Poisson
counts with expectation lambda_p(theta) = N_bg * I_p(theta), where I is the
noise-free ``expected_tem_image`` (relative to the background) and
N_bg = (edge_snr / contrast)^2 the background dose of the renderer (fixed: it is
the electron dose, not a parameter).  The Fisher information is

    F_ij = sum_p (d lambda_p / d theta_i)(d lambda_p / d theta_j) / lambda_p
         = N_bg * sum_p (dI_p/dtheta_i)(dI_p/dtheta_j) / I_p,

so F scales with N_bg (SNR^2) and the bounds with 1/SNR.  Parameters theta:

* n and log r_ref of the power law r(z) = r_ref (z / z_ref)^(1/n) inside the fit
  window 0 <= z <= z_w (z_ref = z_w / 2; r_ref = (n Q z_ref)^(1/n), so this is
  paper Eq. 1 with log Q = n log r_ref - log n - log z_ref).  The map
  (n, log r_ref) -> (n, log Q) leaves n unchanged, so (F^-1)_nn is the same in both
  parameterisations; the covariance is reported in (n, log Q) via its Jacobian.
  The internal choice only conditions the finite differences (at fixed SI Q a
  step in n rescales the whole radius by Q's units);
* the outer profile ABOVE the window, r(z) = r_true(z) + sum_k c_k B_k(z) for
  z > z_w: clamped cubic B-splines with breakpoints every ``fine_spacing`` for
  ``fine_extent`` above z_w, then every ``coarse_spacing`` up to the top of the
  image.  The clamped knot at z_w leaves r free to jump there: the window's power
  law does not constrain the shank;
* nuisances: apex row and column (px), rotation (deg), blur sigma (px), the
  background level b (I is proportional to b), the two illumination-gradient
  amplitudes, log lambda_core, and with a coating its thickness (m) and
  log lambda_coat.

Why this is a valid lower bound.  For any UNBIASED estimator of n (jointly with
the other parameters), var(n_hat) >= (F^-1)_nn (Cramér-Rao).  Every parameter
the true data-generating process has but the model holds fixed is information
given for free: removing parameters (taking a sub-block of F before inverting)
can only DECREASE (F^-1)_nn.  A real tip's shank has far more freedom than our
finite spline basis (and real images have more nuisances than listed), so a
coarser knot spacing above the window makes the bound looser (smaller) but
still a valid lower bound for the harder real problem; the "optimistic" bound
(only n, log Q, apex row/col and rotation free: shank and all illumination /
material / blur parameters known exactly) is smaller still.  A biased estimator
(e.g. one pulled towards a prior) can have a smaller variance or mean squared
error at some true values, paid for by bias elsewhere; the bound is local (at
the true theta) and a lower bound on the error of any unbiased fit.

Numerics.  Derivatives are central finite differences of the full expected
image with a FIXED supersampling band (the pixels within 3 + ``band_margin`` px
of a silhouette at the true parameters), so a step never switches pixels
between centre sampling and supersampling.  Geometric steps (window law along
the surface normal, shank coefficients, apex, coating thickness) move the
silhouette by ``step_px`` pixels at most: large compared with the sub-sample
spacing (1/supersample px) so the square-root edge does not make the quotient
spiky, small compared with the edge width for the truncation error, and a
multiple of half that spacing, so that a central difference moving an edge
parallel to the pixel grid (the flat face of a blunt apex) crosses the same
number of sub-sample rows at any sub-pixel position (otherwise the apex-row
information of n = 6 tips scatters by +-20 %).  Rotation moves a point at
distance L from the apex by L dtheta: each pixel takes the quotient of the step
that moves its own distance by ~``step_px`` (one step per octave of L).  Renders
that only change the radius table redo the coating erosion locally.  The Fisher
sum is restricted to the bounding box of each derivative's non-zero pixels
(exactly zero outside: the renders are identical there), which loses nothing.
"""

from __future__ import annotations

import math
import time
from dataclasses import dataclass, field

import numpy as np
from scipy.interpolate import BSpline

from pipeline.synth.tem_image import axis_contrast, background_dose, expected_tem_image, radius_tables
from pipeline.tem.projection import eroded_radius

__all__ = ["FisherResult", "fisher_information", "crb_summary", "window_knots", "default_apex"]

OPTIMISTIC = ("n", "log_r_ref", "apex_row", "apex_col", "rotation")


def default_apex(shape, orientation="down", seed=0, apex_frac=(0.68, 0.5)):
    """Apex (row, col) drawn exactly as ``render_tem_image`` draws it for ``seed``."""
    rng = np.random.default_rng(seed)
    H, W = shape
    r_a = apex_frac[0] * H + rng.uniform(-0.5, 0.5)
    c_a = apex_frac[1] * W + rng.uniform(-0.5, 0.5)
    return (H - 1 - r_a if orientation == "up" else r_a), c_a


def window_knots(z_w, z_top, fine_spacing=1e-9, fine_extent=10e-9, coarse_spacing=5e-9):
    """Breakpoints (m) of the shank spline: fine_spacing up to z_w + fine_extent, then coarse, up to >= z_top.

    z_top: highest visible z (m).  The last interval is merged into the one below when less
    than half of it is visible (its end basis function would be barely constrained).
    """
    nf = int(round(fine_extent / fine_spacing))
    bp = list(z_w + fine_spacing * np.arange(nf + 1))
    while bp[-1] < z_top:
        bp.append(bp[-1] + coarse_spacing)
    while len(bp) > 2 and z_top - bp[-2] < 0.5 * (bp[-1] - bp[-2]):
        del bp[-2]
    return np.asarray(bp)


def _tip_frame_z(rows, cols, apex, px, rotation_deg, orientation):
    th = math.radians(rotation_deg)
    sgn = 1.0 if orientation == "down" else -1.0
    dx = (cols - apex[1]) * px
    dy = sgn * (apex[0] - rows) * px
    return -dx * math.sin(th) + dy * math.cos(th)


class _Profile:
    """Radius tables (zt, r_outer, r_core) of the perturbed profile, erosion updated locally."""

    def __init__(self, n, Q, px, shape, coating, z_w, breakpoints, cone_above):
        self.n, self.coating, self.z_w = float(n), float(coating), float(z_w)
        self.zt, self.ro, self.rc = radius_tables(n, Q, px, shape, coating, cone_above=cone_above)
        self.z_ref = z_w / 2.0
        self.r_ref = float((n * Q * self.z_ref) ** (1.0 / n))
        zt = self.zt
        self.iw = np.nonzero((zt >= 0) & (zt <= z_w))[0]  # window indices
        t = np.concatenate([[breakpoints[0]] * 3, breakpoints, [breakpoints[-1]] * 3])
        self.is_ = np.nonzero((zt > z_w) & (zt <= breakpoints[-1]))[0]  # spline indices
        self.B = BSpline.design_matrix(zt[self.is_], t, 3).tocsc()
        self.n_spline = self.B.shape[1]
        dz = zt[1] - zt[0]
        self.k = int(np.ceil(coating / dz)) if coating > 0 else 0

    def window_radius(self, n, log_r_ref):
        z = self.zt[self.iw]
        return np.exp(log_r_ref) * np.power(z / self.z_ref, 1.0 / n)

    def tables(self, n=None, dlog_r=0.0, spline=None, dc=0.0):
        """Tables with the window law (n, log r_ref + dlog_r) or spline ``spline`` shifted by dc (m)."""
        ro = self.ro.copy()
        if spline is None:
            idx = self.iw
            ro[idx] = self.window_radius(self.n if n is None else n, math.log(self.r_ref) + dlog_r)
        else:
            col = self.B[:, [spline]].tocoo()
            idx = self.is_[col.row]
            ro[idx] += dc * col.data
        return self.zt, ro, self._core(ro, idx.min(), idx.max())

    def _core(self, ro, i0, i1):
        """Core radius table: the base one with the erosion redone on the indices affected by [i0, i1]."""
        if self.coating <= 0:
            return ro
        k, m = self.k, ro.size
        a, b = max(0, i0 - 2 * k), min(m, i1 + 2 * k + 1)
        # eroded_radius reads only the grid step from z: pass the table's own first
        # entries so the stencil (k, caps) is bit-identical to the full erosion
        loc = eroded_radius(self.zt[: b - a], ro[a:b], self.coating)
        lo, hi = max(a, i0 - k), min(b, i1 + k + 1)  # outputs whose disk stays inside [a, b)
        lo_i = lo if a == 0 else max(lo, a + k)
        hi_i = hi if b == m else min(hi, b - k)
        rc = self.rc.copy()
        rc[lo_i:hi_i] = loc[lo_i - a : hi_i - a]
        return rc


@dataclass
class FisherResult:
    """Fisher information of one synthetic image (per unit background dose) and its context."""

    names: list
    fisher_unit: np.ndarray  # F / N_bg (dimensionless counts per count)
    n_bg: float  # background dose of the case (counts/pixel)
    edge_snr: float  # the edge SNR that n_bg corresponds to
    n: float
    Q: float
    r_ref: float
    z_ref: float
    elapsed: float  # s
    renders: int
    info: dict = field(default_factory=dict)

    @property
    def fisher(self):
        return self.fisher_unit * self.n_bg

    def covariance(self, names=None, n_bg=None):
        """Inverse of the Fisher sub-block of ``names`` (all by default) at dose ``n_bg``."""
        idx = [self.names.index(s) for s in (names or self.names)]
        F = self.fisher_unit[np.ix_(idx, idx)] * (self.n_bg if n_bg is None else n_bg)
        d = np.sqrt(np.diag(F))
        if np.any(d <= 0):
            bad = [self.names[i] for i, v in zip(idx, d) if v <= 0]
            raise np.linalg.LinAlgError(f"no information on {bad}")
        Fs = F / np.outer(d, d)  # scaled: unit diagonal
        C = np.linalg.inv(Fs) / np.outer(d, d)
        return C, [self.names[i] for i in idx], float(np.linalg.cond(Fs))


def _bbox_sparse(d, tol=0.0):
    """(r0, r1, c0, c1, block) of the non-zero part of derivative image d."""
    nz = np.abs(d) > tol
    rows, cols = np.nonzero(nz.any(axis=1))[0], np.nonzero(nz.any(axis=0))[0]
    if rows.size == 0:
        return 0, 0, 0, 0, d[:0, :0]
    r0, r1, c0, c1 = rows[0], rows[-1] + 1, cols[0], cols[-1] + 1
    return r0, r1, c0, c1, d[r0:r1, c0:c1]


def _central(fn, h):
    """Central difference of fn at 0 with step h."""
    return (fn(h) - fn(-h)) / (2.0 * h)


def _shape_derivatives(prof, render, s):
    """Image derivatives with respect to n, log r_ref and each shank spline coefficient, and the
    steps of the first two.  The window power law's steps move the surface by at most ``s`` (m)
    along its normal (a radial change dr moves it by dr / sqrt(1 + (dr/dz)^2): little on the flat
    face of a blunt apex)."""
    derivs = {}
    zw = prof.zt[prof.iw]
    rw = prof.window_radius(prof.n, math.log(prof.r_ref))
    to_normal = 1.0 / np.sqrt(1.0 + np.gradient(rw, zw) ** 2)
    dr_dn = rw * np.log(np.maximum(zw, 1e-300) / prof.z_ref) / prof.n**2  # |dr/dn| (m), 0 at the apex
    dn = s / np.max(np.abs(dr_dn) * to_normal)
    derivs["n"] = _central(lambda h: render(tables=prof.tables(n=prof.n + h)), dn)
    dl = s / np.max(rw * to_normal)
    derivs["log_r_ref"] = _central(lambda h: render(tables=prof.tables(dlog_r=h)), dl)
    for k in range(prof.n_spline):
        derivs[f"c{k}"] = _central(lambda h, k=k: render(tables=prof.tables(spline=k, dc=h)), s)
    return derivs, dn, dl


def _fisher_matrix(derivatives, expected):
    """F_ij = sum over pixels of d_i d_j / I (Poisson), each derivative image cut to its bounding
    box and only overlapping boxes summed."""
    w = 1.0 / expected
    blocks = [_bbox_sparse(d) for d in derivatives]
    P = len(blocks)
    F = np.zeros((P, P))
    for i in range(P):
        ri0, ri1, ci0, ci1, bi = blocks[i]
        for j in range(i, P):
            rj0, rj1, cj0, cj1, bj = blocks[j]
            r0, r1, c0, c1 = max(ri0, rj0), min(ri1, rj1), max(ci0, cj0), min(ci1, cj1)
            if r1 <= r0 or c1 <= c0:
                continue
            F[i, j] = F[j, i] = np.einsum(
                "ij,ij,ij->",
                bi[r0 - ri0 : r1 - ri0, c0 - ci0 : c1 - ci0],
                bj[r0 - rj0 : r1 - rj0, c0 - cj0 : c1 - cj0],
                w[r0:r1, c0:c1],
            )
    return F


def fisher_information(
    n,
    Q,
    pixel_size,
    shape,
    *,
    blur_sigma_px=1.0,
    edge_snr=5.0,
    coating_thickness=0.0,
    rotation_deg=0.0,
    orientation="down",
    apex_px=None,
    seed=0,
    z_window=6e-9,
    fine_spacing=1e-9,
    fine_extent=10e-9,
    coarse_spacing=5e-9,
    step_px=0.3,
    supersample=5,
    band_margin=2,
    lambda_core=40e-9,
    lambda_coat=120e-9,
    gradient=0.04,
    cone_above=25e-9,
    keep_images=False,
):
    """Fisher information of the Poisson image of ``render_tem_image`` (same arguments, SI) about
    (n, log r_ref, shank spline coefficients, nuisances); see the module doc.

    step_px: largest silhouette displacement (px) of a geometric finite-difference step
    (rounded up to a multiple of 1/(2 supersample));
    supersample: sub-samples per pixel side in the (fixed) silhouette band;
    keep_images: also return the expected image, the band and the derivative images in ``info``.
    """
    t0 = time.perf_counter()
    H, W = shape
    px = float(pixel_size)
    apex = default_apex(shape, orientation, seed) if apex_px is None else tuple(map(float, apex_px))
    corner_r, corner_c = np.array([0, 0, H - 1, H - 1]), np.array([0, W - 1, 0, W - 1])  # pixel centres
    z_top = float(_tip_frame_z(corner_r, corner_c, apex, px, rotation_deg, orientation).max())
    knots = window_knots(z_window, z_top, fine_spacing, fine_extent, coarse_spacing)
    prof = _Profile(n, Q, px, shape, coating_thickness, z_window, knots, cone_above)
    base = dict(
        n=n,
        Q=Q,
        pixel_size=px,
        shape=shape,
        apex_px=apex,
        rotation_deg=rotation_deg,
        blur_sigma_px=blur_sigma_px,
        coating_thickness=coating_thickness,
        orientation=orientation,
        lambda_core=lambda_core,
        lambda_coat=lambda_coat,
        background=1.0,
        gradient=gradient,
        gradient_perp=0.0,
        supersample=supersample,
        cone_above=cone_above,
    )
    tables0 = (prof.zt, prof.ro, prof.rc)
    I0, band = expected_tem_image(**base, tables=tables0, band_width=3 + band_margin, return_band=True)
    base.update(band=band)
    n_bg = background_dose(edge_snr, axis_contrast(tables0, lambda_core, lambda_coat))
    renders = [1]

    def render(**over):
        kw = dict(base, tables=tables0)
        kw.update(over)
        renders[0] += 1
        return expected_tem_image(**kw)

    derivs, dropped, steps = _all_derivatives(prof, render, base, apex, step_px, z_window)
    names = list(derivs)
    F = _fisher_matrix([derivs[k] for k in names], I0)
    info = dict(
        steps=steps, z_top=z_top, apex_px=apex, n_spline=prof.n_spline, band_pixels=int(band.sum()), dropped=dropped
    )
    if keep_images:
        info.update(expected=I0, band=band, derivatives=derivs)
    return FisherResult(
        names,
        F,
        n_bg,
        float(edge_snr),
        float(n),
        float(Q),
        prof.r_ref,
        prof.z_ref,
        time.perf_counter() - t0,
        renders[0],
        info,
    )


def _all_derivatives(prof, render, base, apex, step_px, z_window):
    """The derivative images of ``fisher_information`` (``render(**over)``: the expected image
    with ``base``'s arguments changed by ``over``), those the image does not see dropped:
    (derivatives by name, the names dropped, the steps)."""
    px, supersample, blur_sigma_px = base["pixel_size"], base["supersample"], base["blur_sigma_px"]
    gradient, lambda_core, lambda_coat = base["gradient"], base["lambda_core"], base["lambda_coat"]
    coating_thickness = base["coating_thickness"]
    coated = coating_thickness > 0
    # geometric step, rounded up to a multiple of 1/(2 ss) px: a central difference that moves
    # an edge aligned with the pixel grid (the flat face of a blunt apex, a shank edge) then
    # spans a whole number of sub-sample rows at any sub-pixel position
    step_px = math.ceil(step_px * 2 * supersample - 1e-9) / (2.0 * supersample)
    s = step_px * px  # (m)
    derivs, dn, dl = _shape_derivatives(prof, render, s)
    derivs["apex_row"] = _central(lambda h: render(apex_px=(apex[0] + h, apex[1])), step_px)
    derivs["apex_col"] = _central(lambda h: render(apex_px=(apex[0], apex[1] + h)), step_px)
    derivs["rotation"] = _rotation_derivative(render, base, apex, px, step_px, z_window)
    ds = 0.05 * blur_sigma_px
    derivs["blur"] = _central(lambda h: render(blur_sigma_px=blur_sigma_px + h), ds) if blur_sigma_px > 0 else None
    derivs["background"] = _central(lambda h: render(background=1.0 + h), 1e-3)
    derivs["gradient"] = _central(lambda h: render(gradient=gradient + h), 1e-3)
    derivs["gradient_perp"] = _central(lambda h: render(gradient_perp=h), 1e-3)
    derivs["log_lambda_core"] = _central(lambda h: render(lambda_core=lambda_core * math.exp(h)), 1e-2)
    if coated:

        def coat(h):  # same grid and outer table, core eroded by the perturbed thickness
            t = coating_thickness + h
            return render(coating_thickness=t, tables=(prof.zt, prof.ro, eroded_radius(prof.zt, prof.ro, t)))

        derivs["coating"] = _central(coat, s)
        derivs["log_lambda_coat"] = _central(lambda h: render(lambda_coat=lambda_coat * math.exp(h)), 1e-2)
    # no blur -> no blur parameter; a shank coefficient the image does not see is dropped
    dropped = [k for k, v in derivs.items() if v is None or not np.any(v)]
    derivs = {k: v for k, v in derivs.items() if k not in dropped}
    return derivs, dropped, dict(n=dn, log_r_ref=dl, spline=s, apex_px=step_px, blur=ds)


def _rotation_derivative(render, base, apex, px, step_px, L0):
    """dI/d(rotation deg): per pixel the central quotient of the step moving its own distance
    from the apex by ~step_px px (steps for distances L0 * 2^j, one per octave)."""
    H, W = base["shape"]
    rows, cols = np.mgrid[0:H, 0:W]
    L = np.hypot(rows - apex[0], cols - apex[1]) * px
    Lmax = max(float(L.max()), L0)
    J = int(np.ceil(np.log2(Lmax / L0))) + 1
    j_of = np.clip(np.floor(np.log2(np.maximum(L, 1e-30) / L0)).astype(int), 0, J - 1)
    rot0 = base["rotation_deg"]
    out = np.zeros((H, W))
    for j in range(J):
        sel = j_of == j
        if not sel.any():
            continue
        h = math.degrees(step_px * px / (L0 * 2.0**j * 1.5))  # mid-octave distance moves step_px
        q = (render(rotation_deg=rot0 + h) - render(rotation_deg=rot0 - h)) / (2.0 * h)
        out[sel] = q[sel]
    return out


CRB_HEIGHTS = np.arange(1, 7) * 1e-9  # m, crb_summary's default heights above the apex


def crb_summary(res: FisherResult, heights=CRB_HEIGHTS, edge_snr=None):
    """Bounds from a FisherResult: CRB of n (full nuisances, optimistic) and of the relative rigid
    Dugdale pull-off area error (Eq. 12, ``pipeline.fits.power_law.rigid_dugdale_area``) at ``heights`` (m).

    edge_snr: evaluate at this edge SNR instead of the one of ``res`` (F scales with SNR^2).
    Returns dict: crb_n, crb_n_opt, crb_logQ, crb_dugdale (per h, relative), crb_dugdale_opt,
    cond (condition number of the scaled Fisher matrix), cov_nlogQ (2 x 2, full).
    """
    from pipeline.fits.power_law import rigid_dugdale_log_gradient

    n_bg = res.n_bg * (1.0 if edge_snr is None else (edge_snr / res.edge_snr) ** 2)
    n, Q = res.n, res.Q
    # (n, log r_ref) -> (n, log Q): log Q = n log r_ref - log n - log z_ref
    Jac = np.array([[1.0, 0.0], [math.log(res.r_ref) - 1.0 / n, n]])
    g = rigid_dugdale_log_gradient(n, Q, heights)  # d log A(h) / d(n, log Q), Eq. 12
    out = {}
    for tag, names in (("", None), ("_opt", list(OPTIMISTIC))):
        C, nm, cond = res.covariance(names, n_bg)
        i = [nm.index("n"), nm.index("log_r_ref")]
        Cq = Jac @ C[np.ix_(i, i)] @ Jac.T
        out["crb_n" + tag] = math.sqrt(Cq[0, 0])
        out["crb_logQ" + tag] = math.sqrt(Cq[1, 1])
        out["crb_dugdale" + tag] = np.sqrt(np.einsum("hi,ij,hj->h", g, Cq, g))
        out["cond" + tag] = cond
        out["cov_nlogQ" + tag] = Cq
    return out
