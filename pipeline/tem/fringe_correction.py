"""Defocus-fringe correction of the silhouette fit's edge: one uniform normal offset of the
fitted curve, from a coherent (Fresnel) rendering of the fitted body.

Why.  The Beer-Lambert model (``silhouette_model``) has no phase.  In a defocused bright-field
image the exit wave psi = exp(-(k/2) t + i eta t) (t the projected thickness, px; k the fitted
attenuation, 1/px; eta the phase per length sigma_e V0, rad/px) is propagated by the defocus df,
and the image of the tip carries Fresnel fringes ~ sqrt(lambda |df|) wide: on the wave-optical
simulator (``pipeline.synth.tem_wave``, df = +-1.5 um, 0.27 nm px) the intensity at the true
edge is 0.51 or 0.87 instead of 0.90, with a fringe of 1.49 2 nm outside.  The transmission fit
takes part of it for the body: its edge lies 0.3-1.8 nm outside (bench_tem_independent).
A first-order (transport-of-intensity) term cannot describe this: for one material
T grad(phi) = -(eta / k) grad(T), so the TIE term -(lambda df / 2 pi) div(T grad phi) is
(lambda df eta / 2 pi k) laplacian(T), the derivative of the Gaussian blur with respect to
sigma^2 / 2, i.e. a change of the blur width that the fit already has; and the fringes are far
from first order (a 50 % change of the intensity).  Measured on 12 uncoated wave images at
df = -1.5 / +1.5 um (median |edge bias|, nm): Beer-Lambert 1.24 / 0.63; with a linear term
gamma laplacian(G_sigma * (-ln T)) 1.12 / 0.95; gamma laplacian(G_sigma * T) 1.90 / 0.88; with
Laplacians or differences of Gaussians 0.5-4 nm wide (several linear terms) 1.2-2.2 / 0.6-0.9;
this correction 0.28 / 0.32.

What.  After the fit (shape c, blur sigma, attenuations, layer), the edge is moved by a uniform
offset delta (px, outward +) fitted together with the defocus, the phase, the blur and one common
scale g of the attenuations to the same pixels and weights:

    image = (a0 + a_r row + a_c col) x G_s * [T_g(c + delta) + dI_g(c + delta)],
    dI = |F^-1[F[psi] P]|^2 - |psi|^2,   P(f) = exp(i pi A f^2),

T_g the model's sub-sampled Beer-Lambert transmission with the attenuations g k_o, g k_c, psi on
the pixels of the fit's rectangle (continued at its borders into a padded FFT grid): its complex mean
over the transmission's sub-samples at the pixels near the edge, its value at the centre elsewhere
(sampled at the centre alone, a blunt face crossing a row of centres made the rendering jump by up to
0.87 for a move of 0.008 px, and the fits stopped at such jumps; averaged, the jump is 0.22), f in
cycles/px, A = lambda df / px^2
(px^2; Kirkland's sign: df > 0 underfocus).  A = 0 gives dI = 0, the Beer-Lambert model.  On the
simulator's own exit wave, pixel-averaged, this dI reproduces its intensity to 0.01-0.04
(0.27 nm px, df +-1.5 um).  The fit: Levenberg-Marquardt over (delta, A, ln eta, ln s, ln g) with
finite differences.  Why g: the fit's attenuations were fitted with its own edge, so every chord
inside moves with the offset; with them held, moving the edge onto the true silhouette darkened
or brightened the whole body and the linear illumination took the difference (held-out image 27,
1.3 um overfocus: the edge 0.29 nm inside; with g 0.07 nm).  The fringe pattern is periodic-like in
A, so one start finds the wrong basin: A = 0 and ten defoci from 2 % to 60 % of the largest
(``START_FRACTIONS``, either sign, spaced about geometrically) are each taken to the optimum of
a 1-D model of the arc-averaged edge profile; those optima and the Beer-Lambert state are ranked by
their 2-D chi^2, the best two (and the best of each sign of A where those two have none of it:
``_with_each_sign``) get three LM steps, and the best of them is continued (``_screened_starts``).
Starts at no less than 8 % of the largest missed a slight defocus at fine pixels (held-out image
51: 87 nm overfocus at 0.12 nm px, A = -18 px^2 against a smallest start of 34 px^2; its edge
stayed 0.32 nm outside, now 0.01 nm); starts down to 0.5 % changed no edge by more than 0.05 nm
on the 260 images of ``bench_tem_independent``'s three sets and cost 8-13 % more.  Ranking the 1-D
optima by their own chi^2 to save 2-D evaluations put 6 of those edges 0.6-2.2 nm outward, into a
wrong basin: not done.

The offset is applied only if chi^2 falls by more than ``MIN_DCHI2`` AND |delta| is within what a
fringe can shift, ``MAX_SHIFT_PER_FRINGE`` x sqrt(|A|) + ``SHIFT_SLACK_PX`` (a large offset
at A ~ 0 is not a fringe: it is a model error elsewhere, e.g. an unfitted layer).  Only fits
whose reduced chi^2 exceeds ``MIN_CHI2_RED`` are tried (a fringe the size of the noise does not
bias the edge beyond its error; the Beer-Lambert images of the project's tests never reach it).

Its uncertainty.  The offset's standard error from J^T J is the noise's alone (0.00-0.02 nm); the
rendering's model error is not in it, and the largest part of that is the sign of the defocus, which
chi^2 does not identify: where a light layer was not fitted (a coated tip read as one material), the
wrong sign explains the layer as a fringe and beats the right one by 2e4-1e5 in chi^2.  Of the 153
images of ``bench_tem_independent``'s three sets where the correction was applied, 32 took the wrong
sign; on 6 of them it moved an edge that lay within 0.26 nm of the true silhouette 0.4-1.7 nm inwards,
outside the edge SD it reported (grid 1, 94, 100, 119; held-out 29, 37), and so did one of the right
sign (DLC set 76).  So the applied edge carries a second common offset of ``MOVE_SD_SHARE`` x |offset|
(2 SD reach back to the uncorrected edge).  Measured on the three sets (grid / DLC set / held-out):
edge-offset coverage 88.0 / 91.5 / 89.3 % -> 92.3 / 91.5 / 91.1 % (the DLC set's case is lost
anyway), median edge SD 0.33 / 0.31 / 0.27 -> 0.51 / 0.49 / 0.33 nm; sigma_n, the coverage of n and
of the pull-off unchanged (stage 2's apex and Q take up a common offset).  Over the 153 (grades of
the same runs, recomputed), a share of 0.3 / 0.4 / 0.5 covered 3 / 5 / 7 more edges than none.

Why chi^2 cannot tell the sign, and the sign given.  A real exit wave (a body that only absorbs)
propagated by +df and -df gives complex-conjugate waves (the kernel is even in f; spherical
aberration, which does not change sign, breaks this only slightly), so the same intensity: the image's
dependence on the sign of the defocus comes from the phase eta t alone, i.e. from where the body is
thin enough to pass electrons, the edge's outermost nanometres, which is where a light layer lies.
The vacuum's fringes further out carry no sign.  So the sign is what the microscope's operator knows
and the image may not show: ``sign`` +1 (underfocus, A >= 0) or -1 (overfocus, A <= 0) keeps the
fit to that sign (its starts, its 1-D screen and its LM steps, every distinct candidate of the screen
going on: ``SCREEN_KEEP_SIGNED``); 0 (the default) fits both.

A light layer that is the dark fringe, with an overfocus given.  In a slight overfocus the dark fringe
just outside an uncoated edge is read by the silhouette fit as a light layer 0.65-2.2 nm thick, and
the edge reported is its outer surface, 0.3-0.8 nm out, often under ``MIN_CHI2_RED`` (README, issue
16, "a slight overfocus pushes the edge out").  Rendering the fitted outer curve as one body of the
core's material (``one_material``) takes the layer back where that fits better; without the sign
it took real oxides' layers off at the wrong sign, and cost 1.4-2.6x on every thin oxide (tried and
not kept).  With an overfocus given, both bodies are rendered at that sign only (``silhouette_fit``,
``LAYER_AS_FRINGE_MAX``).

The core's own phase.  In a coated body the core (Si, mean inner potential 12.1-12.6 V) shifts the
phase more per length than a native oxide (10.1-10.7 V) or a carbon layer (8-10 V) around it, by
``CORE_PHASE_RATIO``: phi = eta t_outer + (eta_c - eta) t_core.  With one phase for the whole body the
phase step at a flat face's core, 1-2 nm above the oxide's bottom and seen through a long chord,
makes a fringe the model can only place by moving the face: on the wave-optical simulator (held-out
image 31 of ``bench_tem_independent``: n 4.77, 1.22 nm oxide, 0.48 um underfocus) the oxide's
potential raised to the core's takes the face's +0.23 nm away, and the coated body with its layer
held at the true thickness fits with chi^2 2.3e4 at the ratio 1.2 against 5.0e4 at 1 (its edge within
0.02 nm, dn -0.03 against -0.13).  One material renders as before (eta_c = eta).
"""

from __future__ import annotations

import numpy as np
from scipy import fft as sfft
from scipy import ndimage
from scipy.optimize import least_squares

from pipeline.tem.silhouette_model import _Body

MIN_CHI2_RED = 5.0  # the correction is tried only above this reduced chi^2 of the fit ...
LAYER_AS_FRINGE_MAX = 2.5e-9  # ... or, with an overfocus given, where the fit's light layer is thinner (m)
MIN_DCHI2 = 25.0  # chi^2 decrease needed to apply it (4 extra parameters besides the offset)
MAX_SHIFT_PER_FRINGE = 1.5  # largest accepted |offset| per fringe width sqrt(|A|) (px / px) ...
SHIFT_SLACK_PX = 0.25  # ... plus this (px)
PHASE_PER_M = 0.085e9  # start of eta (rad/m): sigma_e V0, 0.05-0.12 rad/nm for V0 8-12 V, 100-300 kV
PHASE_RANGE = (0.4, 1.9)  # eta within this factor range of the start
# the core's phase per length over the outer layer's, in a coated body: the ratio of their mean inner
# potentials, Si 12.1-12.6 V over SiO2 10.1-10.7 V or amorphous carbon 8-10 V (module doc, "The core's
# own phase")
CORE_PHASE_RATIO = 1.2
LAMBDA_DF_MAX = 3.0e-12 * 2.0e-6  # m^2: lambda (2.0 pm at 300 kV .. 3.7 pm at 100 kV) x |df| <= 2 um
_START_SIZES = (0.02, 0.04, 0.08, 0.25, 0.6)
START_FRACTIONS = tuple(-f for f in reversed(_START_SIZES)) + _START_SIZES  # starts of A, fractions of the largest
# the correction's own model error, as a share of its move: a common-offset SD of the applied edge
# (module doc, "Its uncertainty")
MOVE_SD_SHARE = 0.5
PAD_MIN_PX, PAD_MAX_PX = 16, 64  # FFT padding around the rectangle (px): the kernel's reach, within these
START_STEPS = 3  # LM steps from every screened start; the best is continued
SCREEN_KEEP = 2  # starts taken into the 2-D fit after the 1-D screen, with the best of each sign (``_with_each_sign``)
# ... with the sign given: half the starts, and a 1-D optimum in the right basin can rank low in 2-D
# before the 2-D fit has moved its blur and attenuation scale (held-out 33 of ``bench_tem_independent``:
# 1.6 um overfocus at 0.12 nm px, the 1-D optimum at A = -287 px^2 ranked below A = -2 px^2), so every
# distinct candidate goes on
SCREEN_KEEP_SIGNED = 6
SCREEN_NFEV = 40  # model evaluations of each start's 1-D fit
SCREEN_MIN_BINS = 8  # bins of the edge profile with data needed for the 1-D screen
RESIDUALS_KEPT = 16  # residual vectors kept by ``_Coherent.residual``
_FD = np.array([0.05, 0.5, 0.05, 0.03, 0.02])  # finite-difference steps of (delta, A, ln eta, ln s, ln g)
_NQ = _FD.size


def step_limits(q):
    """Largest change of each of q = (delta px, A px^2, ln eta, ln s, ln g) in one Levenberg-Marquardt step."""
    return np.array([1.5, 0.25 * abs(q[1]) + 5.0, 0.5, 0.3, 0.2])


def _exit_wave(t_o, t_c, k_o, k_c, eta, eta_c):
    """psi = exp(-(k/2) t + i phi) of chords t_o (outer body) and t_c (core) in px, with the outer
    material's and the core's attenuations k_o, k_c (1/px) and phases per length eta, eta_c (rad/px):
    phi = eta t_o + (eta_c - eta) t_c (module doc; one material: eta_c = eta, t_c = t_o)."""
    return np.exp(-0.5 * (k_o * t_o + (k_c - k_o) * t_c) + 1j * (eta * t_o + (eta_c - eta) * t_c))


class _Coherent:
    """The coherent rendering of one fitted silhouette (module doc) on its problem's pixels."""

    def __init__(self, prob, fitter, st, pixel_size, sign=0, one_material=False):
        self.p = prob
        self.sign = int(np.sign(sign))  # the defocus's sign given: A kept >= 0 (+1) or <= 0 (-1); 0 both
        self.c, self.sigma, self.k_o, self.k_c, self.coat = fitter.unpack(st.v)
        if one_material:  # the fitted outer curve as one body of the core's material (module doc)
            self.coat, self.k_o = 0.0, self.k_c
        self.core_phase = CORE_PHASE_RATIO if self.coat > 0 else 1.0  # the core's phase per length / the layer's
        H, W = prob.shape
        r0, c0 = prob.origin
        RR, CC = np.mgrid[r0 : r0 + H, c0 : c0 + W].astype(float)
        self.px, self.pz = prob.frame.to_tip(np.column_stack([RR.ravel(), CC.ravel()]))
        self._grids = {}
        self.eta0 = PHASE_PER_M * float(pixel_size or 0.25e-9)
        self._fields = {}
        self._T = {}  # (delta, g) -> sub-sampled Beer-Lambert transmission at the needed pixels
        self._waves = {}  # (delta, eta, g) -> exit wave (complex64) and |psi|^2 at the needed pixels
        self._spectra = {}  # (delta, eta, g, padding) -> FFT of the padded exit wave (A's column reuses it)
        self._fringes = {}  # (delta, A, eta, g) -> dI at the needed pixels (the blur's column reuses it)
        self._residuals = {}  # bytes of q -> residuals (the screen's candidates are the LM's starts)
        # the pixel map of the fitted curve, made from it alone, and its signed distances: every
        # offset's map is derived from them (``_Problem.offset_map``), whatever was evaluated before
        prob.update_pixel_map(self.c, self.coat, cold=True)
        self.chords0 = _Body(*prob.curve(self.c), self.coat).chords(prob.nx_, prob.nz_)  # at the needed pixels
        self.sd0 = np.where(self.chords0[0] > 0, -prob.dist_need, prob.dist_need)

    def fields(self, delta):
        """(t_outer, t_core at every rectangle pixel centre, the needed pixels' chords with their
        sub-samples (``_Problem.chords``), indices of the rectangle pixels with material) of the curve
        moved by ``delta`` (the last three kept).  One body serves both, and the needed pixels' centre
        chords are the rectangle's (the same numbers as the silhouette model's own)."""
        key = float(delta)
        if key not in self._fields:
            c = self.c + delta
            self.p.offset_map(self.c, self.coat, delta, self.sd0)
            body = _Body(*self.p.curve(c), self.coat)
            t_o, t_c = body.chords(self.px, self.pz)
            need = self.p.need
            ch = self.p.chords(c, self.coat, body=body, centres=(t_o[need], t_c[need]))
            _keep(self._fields, key, (t_o, t_c, ch, np.nonzero((t_o > 0) | (t_c > 0))[0]))
        return self._fields[key]

    def transmission(self, delta, g):
        """Sub-sampled Beer-Lambert T at the needed pixels of the curve moved by ``delta``, with the
        attenuations scaled by ``g`` (the last three kept)."""
        key = (float(delta), float(g))
        if key not in self._T:
            _keep(self._T, key, self.p.transmission(self.fields(delta)[2], g * self.k_o, g * self.k_c))
        return self._T[key]

    def grid(self, A):
        """(padding, padded shape, f_y^2, f_x^2) of the FFT grid for the kernel of ``A``: the padding
        covers the kernel's reach |A| f_max (f_max = 0.5 cycles/px) plus 8 px, rounded up to 16 px."""
        pad = int(np.clip(16 * np.ceil((0.5 * abs(A) + 8.0) / 16), PAD_MIN_PX, PAD_MAX_PX))
        if pad not in self._grids:
            H, W = self.p.shape
            full = (sfft.next_fast_len(H + 2 * pad), sfft.next_fast_len(W + 2 * pad))
            self._grids[pad] = (pad, full, sfft.fftfreq(full[0]) ** 2, sfft.fftfreq(full[1]) ** 2)
        return self._grids[pad]

    def wave(self, delta, eta, g):
        """(exit wave psi on the rectangle, complex64: averaged over the sub-samples near the edge, module
        doc; |psi|^2 at the needed pixels) of the curve moved by ``delta`` with phase per length ``eta``
        and the attenuations scaled by ``g`` (the last three kept)."""
        key = (float(delta), float(eta), float(g))
        if key not in self._waves:
            t_o, t_c, (_, _, bands), m = self.fields(delta)
            k_o, k_c = g * self.k_o, g * self.k_c
            psi = np.ones(t_o.size, complex)  # vacuum: exp(0) = 1
            eta_c = self.core_phase * eta
            psi[m] = _exit_wave(t_o[m], t_c[m], k_o, k_c, eta, eta_c)
            for bi, s_o, s_c, n_sub in bands:  # the pixels near an edge: the wave averaged over the pixel
                if bi.size:
                    psi[self.p.need[bi]] = _exit_wave(s_o, s_c, k_o, k_c, eta, eta_c).reshape(-1, n_sub).mean(1)
            _keep(self._waves, key, (psi.astype(np.complex64).reshape(self.p.shape), np.abs(psi[self.p.need]) ** 2))
        return self._waves[key]

    def fringe(self, delta, A, eta, g):
        """dI (module doc) at the needed pixels (the last five kept: a Jacobian needs four)."""
        key = (float(delta), float(A), float(eta), float(g))
        if key not in self._fringes:
            psi, psi2 = self.wave(delta, eta, g)
            H, W = self.p.shape
            pad, full, fy2, fx2 = self.grid(A)
            skey = (float(delta), float(eta), float(g), pad)
            if skey not in self._spectra:
                widths = ((pad, full[0] - H - pad), (pad, full[1] - W - pad))
                spectrum = sfft.fft2(np.pad(psi, widths, mode="edge"), workers=1, overwrite_x=True)
                _keep(self._spectra, skey, spectrum, size=2)
            spec = self._spectra[skey] * np.exp(1j * np.pi * A * fy2).astype(np.complex64)[:, None]
            spec *= np.exp(1j * np.pi * A * fx2).astype(np.complex64)[None, :]
            out = sfft.ifft2(spec, workers=1, overwrite_x=True)[pad : pad + H, pad : pad + W].ravel()[self.p.need]
            _keep(self._fringes, key, out.real.astype(float) ** 2 + out.imag.astype(float) ** 2 - psi2, size=5)
        return self._fringes[key]

    def residual(self, q):
        """Weighted residuals at q = (delta px, A px^2, ln(eta / eta0), ln(s / sigma), ln g) (the
        last ``RESIDUALS_KEPT`` kept: the starts' and the best run's are asked for again)."""
        key = np.asarray(q, float).tobytes()
        if key not in self._residuals:
            delta, A, leta, lsig, lg = q
            g = float(np.exp(lg))
            T = self.transmission(delta, g)
            M = T + self.fringe(delta, A, self.eta0 * np.exp(leta), g) if A != 0 else T
            B = self.p.blurred(M, self.sigma * np.exp(lsig))
            _keep(self._residuals, key, (self.p.I - self.p.model(B, self.p.linear(B))) * self.p.w, RESIDUALS_KEPT)
        return self._residuals[key]

    def lm(self, q, iters):
        """Levenberg-Marquardt from q: (q, chi^2, J^T J)."""
        r = self.residual(q)
        cost, JTJ, lam = float(r @ r), None, 1e-2
        lim = step_limits(q)
        for _ in range(iters):
            J = self.jacobian(q, r)
            JTJ, g = J.T @ J, J.T @ r
            for _ in range(5):
                dq = np.clip(-np.linalg.solve(JTJ + lam * np.diag(np.diag(JTJ) + 1e-12), g), -lim, lim)
                qn = q + dq
                qn[2] = np.clip(qn[2], *np.log(PHASE_RANGE))
                if self.sign:
                    qn[1] = self.sign * max(self.sign * qn[1], 0.0)
                rn = self.residual(qn)
                if float(rn @ rn) < cost:
                    gain = cost - float(rn @ rn)
                    q, r, cost = qn, rn, float(rn @ rn)
                    lam = max(lam / 5, 1e-6)
                    break
                lam *= 8
            else:
                break
            if gain < 1e-4 * cost:
                break
        return q, cost, JTJ

    def jacobian(self, q, r=None, cols=range(_NQ)):
        """Forward-difference Jacobian of ``residual`` at q (steps ``_FD``; the step in A towards the
        sign given, so that it stays on that side of 0); ``cols``: those columns only."""
        r = self.residual(q) if r is None else r
        fd = _FD if self.sign >= 0 else _FD * np.array([1.0, -1.0, 1.0, 1.0, 1.0])
        return np.column_stack([(self.residual(q + np.eye(_NQ)[i] * fd[i]) - r) / fd[i] for i in cols])


def _keep(cache, key, value, size=3):
    """Put ``value`` in the small FIFO ``cache`` (at most ``size`` entries)."""
    if len(cache) >= size:
        cache.pop(next(iter(cache)))
    cache[key] = value


def _offset_sd(JTJ, scale):
    """Standard error of the offset (px) from J^T J of (delta, A, ln eta, ln s, ln g), marginal over the
    parameters the image determines.  In focus (A ~ 0) the phase changes nothing, its column is zero
    and J^T J singular: such columns (diagonal below 1e-10 of the largest) are left out instead of
    making the offset's error NaN (10 of the 120 grid images).  NaN if the offset itself is not
    determined; the correction is then not applied."""
    d = np.diag(JTJ)
    keep = d > 1e-10 * max(float(d.max()), 1e-300)
    if not keep[0]:
        return float("nan")
    try:
        var = np.linalg.inv(JTJ[np.ix_(keep, keep)])[0, 0] * scale
    except np.linalg.LinAlgError:
        return float("nan")
    return float(np.sqrt(var)) if np.isfinite(var) and var >= 0 else float("nan")


def fringe_offset(prob, fitter, st, pixel_size, iters=10, sign=0, one_material=False, start=None):
    """Fit of the coherent rendering of the fitted silhouette ``st`` (module doc), at either sign of
    the defocus (``sign`` 0) or at the sign given (+1 underfocus, -1 overfocus); with ``one_material``
    the fitted outer curve is rendered as one body of the core's material ("A light layer that is the
    dark fringe"); with ``start`` (q, as ``_Coherent.residual``'s) the fit starts there alone, without
    the screen of starts (a body close to one already fitted: ``held_layer``).  Returns a dict:
    offset_px (uniform outward offset of the edge), offset_sd_px (its noise), model_sd_px (its model
    error, ``MOVE_SD_SHARE`` x |offset|), A_px2 (lambda df / px^2), eta
    (rad/px), sigma_px (blur), attenuation_scale (g), dchi2 (chi^2 decrease against the Beer-Lambert
    model), chi2 and chi2_beer_lambert (the two), sign (the sign given, 0 if none), applied,
    screen_chi2 and screen_chi2_overfocus (after the screen's ``START_STEPS``: the best start's chi^2 and
    the best of those in overfocus, inf if none; NaN and inf with ``start``)."""
    co = _Coherent(prob, fitter, st, pixel_size, sign, one_material)
    r0 = co.residual(np.zeros(_NQ))
    chi0 = float(r0 @ r0)
    a_max = LAMBDA_DF_MAX / float(pixel_size or 0.25e-9) ** 2
    ls0 = float(np.log(0.5 / co.sigma)) if co.sigma > 0.6 else 0.0  # the fit's blur took part of the fringe
    starts = [np.zeros(_NQ)]
    for fa in START_FRACTIONS:
        if fa * co.sign < 0:
            continue  # the other sign than the one given
        A = fa * a_max
        # the fringe shifts the transmission edge outwards by up to ~sqrt(|A|) (more in overfocus)
        starts.append(np.array([-(0.8 if A < 0 else 0.3) * np.sqrt(abs(A)), A, 0.0, ls0, 0.0]))
    over = np.inf  # the best chi^2 of an overfocus (A < 0) after the screen's steps
    if start is None:
        runs = [co.lm(q, START_STEPS) for q in _screened_starts(prob, st, co, starts, a_max)]
        best = min(runs, key=lambda t: t[1])
        over = min([c for qr, c, _ in runs if qr[1] < 0], default=np.inf)
        q, cost, _ = co.lm(best[0], iters)
        screen = best[1]
    else:
        q, cost, _ = co.lm(np.asarray(start, float), iters)
        screen = np.nan
    r = co.residual(q)
    J = co.jacobian(q, r)
    JTJ = J.T @ J  # at the solution
    # censored pixels whose model is above their value have residual exactly 0: not data
    n_data = prob.idx.size if prob.cens is None else int(np.count_nonzero(~prob.cens | (r != 0)))
    dof = max(1, n_data - 7)
    sd = _offset_sd(JTJ, max(cost / dof, 1.0))
    delta, A = float(q[0]), float(q[1])
    bound = MAX_SHIFT_PER_FRINGE * np.sqrt(abs(A)) + SHIFT_SLACK_PX
    return dict(
        offset_px=delta,
        offset_sd_px=sd,
        model_sd_px=MOVE_SD_SHARE * abs(delta),
        A_px2=A,
        eta=float(co.eta0 * np.exp(q[2])),
        sigma_px=float(co.sigma * np.exp(q[3])),
        attenuation_scale=float(np.exp(q[4])),
        dchi2=chi0 - cost,
        chi2=cost,
        chi2_beer_lambert=chi0,
        sign=co.sign,
        applied=bool(chi0 - cost > MIN_DCHI2 and abs(delta) <= bound and np.isfinite(sd)),
        screen_chi2=float(screen),
        screen_chi2_overfocus=float(over),
    )


def _screened_starts(prob, st, co, starts, a_max):
    """The starts of the 2-D fit (``_with_each_sign``; ``SCREEN_KEEP_SIGNED`` with the sign of the defocus
    given), from the Beer-Lambert state (``starts[0]``, A = 0)
    and the optimum of every start in a fit of the arc-averaged edge profile (``_edge_profile``,
    ``_profile_model``: a 1-D FFT, cheap), ranked by their chi^2 in 2-D (one ``residual`` each).
    The 1-D fit finds the basin of the fringe pattern; its own chi^2 is not trusted to rank the
    basins (the arc average mixes the edge's directions and curvatures).  Candidates that the 1-D
    fit took to one optimum count once (``_distinct``).  Where fewer than ``SCREEN_MIN_BINS`` bins of
    the profile hold data (a saturated detector clips nearly all of it), the starts themselves are
    ranked.  Measured on the 65 grid images where the correction runs (``bench_tem_independent``),
    against three LM steps from every start: the final chi^2 lower by > 1 % on 19, higher by > 1 %
    on 10."""
    prof = _edge_profile(prob, co, st)
    if prof is None:
        candidates = list(starts)
    else:
        dg, kt, t_o, dd, y, se = prof
        lo = np.array([-40.0, -2.0 * a_max - 5.0, np.log(PHASE_RANGE[0]), -3.0])
        hi = np.array([40.0, 2.0 * a_max + 5.0, np.log(PHASE_RANGE[1]), 3.0])
        if co.sign > 0:
            lo[1] = 0.0
        elif co.sign < 0:
            hi[1] = 0.0

        cache = {}  # ``_profile_model``'s grids, spectra and images of this profile

        def res(q):
            return (_profile_model(q, dg, kt, t_o, co.eta0, co.sigma, at=dd, cache=cache) - y) / se

        fits = [
            least_squares(res, np.clip(q[:4], lo + 1e-9, hi - 1e-9), bounds=(lo, hi), max_nfev=SCREEN_NFEV)
            for q in starts
        ]
        candidates = [starts[0]] + [np.r_[f.x, 0.0] for f in fits]  # g = 1: the 1-D model has no g
    chi2 = [float(r @ r) for r in map(co.residual, candidates)]
    kept = []
    for j in np.argsort(chi2, kind="stable"):
        if all(_distinct(candidates[j], q) for q in kept):
            kept.append(candidates[j])
    if co.sign:
        return kept[:SCREEN_KEEP_SIGNED]
    return _with_each_sign(kept)


def _with_each_sign(ranked):
    """The ``SCREEN_KEEP`` best of the ``ranked`` starts, and the best of each sign of A among the rest
    where those have none of it: a basin's 1-D optimum can rank low in 2-D before the 2-D fit has moved
    its blur and attenuation scale (module doc, ``SCREEN_KEEP_SIGNED``), and the two best were often of one
    sign, so the fit of both signs ended at a higher chi^2 than the fit at the other sign alone (grid 57
    of ``bench_tem_independent``, uncoated in 154 nm overfocus: 45189 at lambda df +3.1 px^2 against 28507
    at -6.1, the edge 0.41 nm outside against 0.11 nm inside; README, issue 16)."""
    kept = list(ranked[:SCREEN_KEEP])
    for sign in (1.0, -1.0):
        if not any(q[1] * sign > 0 for q in kept):
            kept += [q for q in ranked[SCREEN_KEEP:] if q[1] * sign > 0][:1]
    return kept


def _distinct(q1, q2):
    """Whether two starts (delta, A, ln eta, ln s) lie apart: by more than 0.25 px in the offset or
    1 px^2 + 5 % in A (two starts that the 1-D fit took to one optimum are one start)."""
    return bool(abs(q1[0] - q2[0]) > 0.25 or abs(q1[1] - q2[1]) > 1.0 + 0.05 * max(abs(q1[1]), abs(q2[1])))


def _edge_profile(prob, co, st, step=0.25):
    """The fitted pixels averaged along the edge in bins of ``step`` px of signed distance to the
    fitted outer curve (px, outward +; ``co.sd0``): the body over every residual pixel (bin centres
    dg, mean attenuation x chord kt, mean outer chord t_o: the chords do not depend on the data, so
    a clipped vacuum does not cut the body short) and the data over the uncensored ones (bin centres
    dd of the bins with >= 5 of them, image / illumination y, standard error se of each bin's mean).
    None where fewer than ``SCREEN_MIN_BINS`` bins hold data."""
    k_o, k_c = co.k_o, co.k_c
    t_o, t_c = (t[prob.res_in_need] for t in co.chords0)
    sd = co.sd0[prob.res_in_need]
    illum = st.lin[0] + st.lin[1] * prob.rn + st.lin[2] * prob.cn
    geo = np.isfinite(sd) & (illum > 0)
    illum = np.where(geo, illum, 1.0)
    if np.count_nonzero(geo) < 5 * SCREEN_MIN_BINS:
        return None
    b = np.full(sd.size, -1, np.intp)
    b[geo] = np.floor((sd[geo] - sd[geo].min()) / step).astype(np.intp)
    centres = sd[geo].min() + step * (np.arange(b.max() + 1) + 0.5)

    def means(sel, values, min_count):
        n = np.bincount(b[sel], minlength=centres.size)
        ok = n >= min_count
        return ok, [np.bincount(b[sel], v[sel], centres.size)[ok] / n[ok] for v in values]

    ok_g, (kt, t_o) = means(geo, (k_o * t_o + (k_c - k_o) * t_c, t_o), 1)
    data = geo if prob.cens is None else geo & ~prob.cens
    ok_d, (y, var) = means(data, (prob.I / illum, 1.0 / (prob.w * illum) ** 2), 5)
    if np.count_nonzero(ok_d) < SCREEN_MIN_BINS:
        return None
    se = np.sqrt(var / np.bincount(b[data], minlength=centres.size)[ok_d])
    return centres[ok_g], kt, t_o, centres[ok_d], y, se


def _profile_model(q, d, kt, t_o, eta0, sigma, at=None, fine=4, cache=None):
    """The coherent image of the arc-averaged edge (``_edge_profile``) at q = (delta, A, ln(eta /
    eta0), ln(s / sigma)) (``_Coherent.residual``'s parameters): the mean chord profile (kt, t_o at
    the bins ``d``) moved out by delta, its exit wave propagated across the edge in 1-D on a grid of
    ``fine`` samples per px, blurred, at the points ``at`` (default ``d``).  The grid is padded by
    2 |A| + 16 px (at least 64): the kernel spreads the grid's top frequency, 2 cycles/px, over
    2 |A| px, and a shorter padding wraps it round onto the edge.  ``cache`` (a dict, for calls with
    the same profile and points): the grids, the last spectra of the exit wave and the last unblurred
    images are kept in it by their parameters' bytes (a finite-difference column in A reuses the
    spectrum, one in the blur the image; the same numbers)."""
    delta, A, leta, lsig = q
    at = d if at is None else at
    grids, spectra, images = ({} if cache is None else cache).setdefault("1-D", ({}, {}, {}))
    pad = max(64.0, 2.0 * abs(A) + 16.0)
    if pad not in grids:
        g = np.arange(min(d.min(), at.min()) - pad, max(d.max(), at.max()) + pad, 1.0 / fine)
        _keep(grids, pad, (g, np.fft.fftfreq(g.size, d=1.0 / fine) ** 2), size=4)
    g, f2 = grids[pad]
    ikey = np.array([pad, delta, A, leta]).tobytes()
    if ikey not in images:
        skey = np.array([pad, delta, leta]).tobytes()
        if skey not in spectra:
            psi = np.exp(
                -0.5 * np.interp(g - delta, d, kt, right=0.0)
                + 1j * eta0 * np.exp(leta) * np.interp(g - delta, d, t_o, right=0.0)
            )
            _keep(spectra, skey, np.fft.fft(psi), size=4)
        _keep(images, ikey, np.abs(np.fft.ifft(spectra[skey] * np.exp(1j * np.pi * A * f2))) ** 2, size=4)
    return np.interp(at, g, ndimage.gaussian_filter1d(images[ikey], sigma * np.exp(lsig) * fine))
