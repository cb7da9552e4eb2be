"""The edge's shape refitted with the coherent rendering of the defocus-fringe correction.

Why.  The correction (``fringe_correction``) moves the Beer-Lambert fit's edge by one uniform
offset.  But that fit took the fringes for the body differently along the edge: at the apex,
where the body is thin over a wide stretch of the edge (a blunt face) or curved in two directions,
the fringe pulls the edge otherwise than on the flanks.  After the uniform offset the flanks lie on
the silhouette and the apex does not: on the wave-optical grid (``bench_tem_independent``) the
mean signed edge error 0-1 nm above the apex was -0.1 to -0.3 nm in overfocus beside +0.4 nm at 1-2
nm, and n was off by 0.3-0.9 where the Cramér-Rao bound of the image allows 0.02-0.05
(``bench_tem_bound``; grid 30, 48, 112).

What.  With the defocus, the phase, the blur and the attenuation scale of the correction as the
start, the edge offsets c_k (``silhouette_model``'s knots) are fitted again together with those four,
Levenberg-Marquardt on the coherent model's residuals and the silhouette fit's own penalty
(smoothness, monotone flanks).  The shape columns are local translations, as in the Beer-Lambert
fit (``silhouette_solver``): phi_k(S_i) G_i, G the change of the coherent rendering per uniform
outward offset (its column in the correction's Jacobian), phi_k the knot's B-spline at the pixel's
nearest point of the curve.  A fringe is set by the edge beside it, so this is the same
approximation there; it only steers the steps (each step is judged on the exact rendering), and at
the true body the coherent residuals are noise whatever the Jacobian, so it does not bias where the
fit stops.

Its uncertainty.  The move from the Beer-Lambert edge is the rendering's correction, and its model
error is taken as half of it, as for the uniform offset (``fringe_correction.MOVE_SD_SHARE``): the
edge covariance gets (MOVE_SD_SHARE x move)(MOVE_SD_SHARE x move)^T, a mode along the move's own
shape (for a uniform move, exactly the common term it replaces), so 2 SD reach back to the Beer-Lambert
edge in n as in the offset.
"""

from __future__ import annotations

import types

import numpy as np

from pipeline.tem.fringe_correction import PHASE_PER_M, PHASE_RANGE, _Coherent, step_limits
from pipeline.tem.silhouette_model import _bspline

SHAPE_ITERS = 40  # Levenberg-Marquardt steps at most
SHAPE_TRIES = 3  # damped steps tried from one point (the current lam, then 10 x max(lam, 0.01) twice) before it stops
SHAPE_STEP_PX = 0.5  # largest change of one knot's offset per step (px)
SHAPE_TOL_PX = 0.005  # converged when no knot moved more than this (px) in an accepted step ...
SHAPE_TOL_COST = 1e-5  # ... or chi^2 fell by less than this share
SHAPE_KNOT_FACTOR = 3  # the move's knots every this many of the edge's (1.2 nm: every 3.6 nm)
SHAPE_GLOBALS = (1, 2, 3, 4)  # the correction's parameters refitted with the shape: A, ln eta, ln s, ln g
SHAPE_MIN_WEIGHT = 0.05  # a coefficient of the move whose data weight is below this share of the median is held
SHAPE_HEIGHT = 1.4  # the move is fitted up to this many profile heights above the apex (the edge's points: 1.3)


def _coarse_basis(prob, factor, c, z_max):
    """(K, M): the edge's knots' moves from the M coefficients of the move, cubic B-splines with knots
    every ``factor`` knots of the edge's (the move is smooth on that scale), zero at the knots above
    ``z_max`` (px; the curve of offsets ``c``; there the fit's rectangle ends, its rendering is
    continued at the border, and the profile does not reach)."""
    S = prob.kc * prob.knot
    z = np.interp(S, prob.S, prob.curve(c)[1])
    u = np.arange(prob.K) / factor
    j = np.arange(int(np.ceil(u[-1])) + 3) - 1
    D = _bspline(u[:, None] - j[None, :])
    D[z > z_max] = 0.0
    return D[:, np.any(D != 0.0, axis=0)]


class _ShapeFit:
    """The coherent model of ``fringe_correction._Coherent`` at any edge offsets c."""

    def __init__(self, prob, fitter, st, fringe, pixel_size, hpx):
        self.p, self.fitter, self.v0, self.px = prob, fitter, st.v, pixel_size
        self.K = prob.K
        self.D = _coarse_basis(prob, SHAPE_KNOT_FACTOR, fitter.unpack(st.v)[0], SHAPE_HEIGHT * hpx)
        self.active = None  # the move's coefficients fitted (``normal_equations``)
        self.sign = int(np.sign(fringe.get("sign") or fringe["A_px2"]))  # A stays on its side
        self.one_material = "layer_as_fringe_dchi2" in fringe
        sigma = fitter.unpack(st.v)[1]
        eta0 = PHASE_PER_M * float(pixel_size or 0.25e-9)
        self.q0 = np.array(
            [
                0.0,
                fringe["A_px2"],
                np.log(fringe["eta"] / eta0),
                np.log(fringe["sigma_px"] / sigma),
                np.log(fringe["attenuation_scale"]),
            ]
        )

    def at(self, c, q):
        """(coherent model, residuals, penalty residuals, penalty Jacobian, cost) at offsets c, q."""
        v = self.v0.copy()
        v[: self.K] = c
        co = _Coherent(self.p, self.fitter, types.SimpleNamespace(v=v), self.px, self.sign, self.one_material)
        co.Phi = self.p.Phi  # the pixel map of c itself (a later trial remakes the problem's)
        r = co.residual(q)
        pr, pj = self.fitter.penalty(c)
        return co, r, pr, pj, float(r @ r + pr @ pr)

    def normal_equations(self, co, q, r, pr, pj):
        """J^T J and J^T r over (c_1..c_K, A, ln eta, ln s, ln g) with the penalty (module doc)."""
        J = co.jacobian(q, r, (0,) + SHAPE_GLOBALS)
        PG = co.Phi.multiply(J[:, :1]).tocsr() @ self.D  # local translations of the uniform offset's column
        if self.active is None:
            # the move's coefficients the image hardly sees (the curve's ends, beyond the fit's pixels) are
            # held: nothing but the penalty would stop them (chosen once, at the start)
            d = np.einsum("ij,ij->j", PG, PG)
            self.active = d > SHAPE_MIN_WEIGHT * (np.median(d[d > 0]) if np.any(d > 0) else np.inf)
            self.D = self.D[:, self.active]
            PG = PG[:, self.active]
        Jq = J[:, 1:]
        pj = pj @ self.D
        Ass = PG.T @ PG + pj.T @ pj
        Asq = PG.T @ Jq
        JTJ = np.block([[Ass, Asq], [Asq.T, Jq.T @ Jq]])
        grad = np.concatenate([PG.T @ r + pj.T @ pr, Jq.T @ r])
        return JTJ, grad

    def step(self, c, q, JTJ, grad, lam):
        """A damped Gauss-Newton step, each knot's move kept within SHAPE_STEP_PX and each of the
        correction's parameters within its step limit (``fringe_correction.step_limits``: unbounded, a
        nearly unseen ln g once stepped to exp overflow)."""
        M = self.D.shape[1]
        dv = -np.linalg.solve(JTJ + lam * np.diag(np.diag(JTJ) + 1e-12), grad)
        dc = self.D @ dv[:M]
        scale = min(1.0, SHAPE_STEP_PX / (float(np.max(np.abs(dc))) + 1e-300))
        dc, dv = dc * scale, dv * scale
        qn = q.copy()
        lim = step_limits(q)[list(SHAPE_GLOBALS)]
        qn[list(SHAPE_GLOBALS)] += np.clip(dv[M:], -lim, lim)
        qn[2] = np.clip(qn[2], *np.log(PHASE_RANGE))
        if self.sign:
            qn[1] = self.sign * max(self.sign * qn[1], 0.0)
        return c + dc, qn


def fringe_shape(prob, fitter, st, fringe, pixel_size, hpx, iters=SHAPE_ITERS):
    """The edge offsets c (px, ``silhouette_model``'s knots) refitted with the coherent rendering of an
    applied fringe correction ``fringe`` (module doc), from the Beer-Lambert state ``st`` moved by its
    uniform offset.  Returns a dict: c, move_px (c against the Beer-Lambert fit's offsets, per knot),
    chi2 (of the coherent model with the penalty), chi2_uniform (at the uniform offset), A_px2, eta,
    sigma_px, attenuation_scale (refitted with the shape), iterations, converged."""
    fit = _ShapeFit(prob, fitter, st, fringe, pixel_size, hpx)
    c_bl = fitter.unpack(st.v)[0]
    c, q = c_bl + fringe["offset_px"], fit.q0
    co, r, pr, pj, cost = fit.at(c, q)
    cost0, lam, converged, it = cost, 1e-2, False, 0
    for it in range(1, iters + 1):  # noqa: B007 - it, the iterations done, is returned
        JTJ, grad = fit.normal_equations(co, q, r, pr, pj)
        for _ in range(SHAPE_TRIES):
            cn, qn = fit.step(c, q, JTJ, grad, lam)
            trial = fit.at(cn, qn)
            if trial[4] < cost:
                moved, gain = float(np.max(np.abs(cn - c))), cost - trial[4]
                c, q = cn, qn
                co, r, pr, pj, cost = trial
                lam = max(lam / 5, 1e-6)
                break
            lam = 10 * max(lam, 1e-2)  # Marquardt's scaling shortens the step only from lam ~ 1 on
        else:
            converged = True  # no step lowers chi^2: at the optimum (or stuck)
            break
        if moved < SHAPE_TOL_PX or gain < SHAPE_TOL_COST * cost:
            converged = True
            break
    prob.map_c = None  # the pixel map is the last trial's: the next user makes its own
    return dict(
        c=c,
        move_px=c - c_bl,
        chi2=cost,
        chi2_uniform=cost0,
        A_px2=float(q[1]),
        eta=float(co.eta0 * np.exp(q[2])),
        sigma_px=float(fitter.unpack(st.v)[1] * np.exp(q[3])),
        attenuation_scale=float(np.exp(q[4])),
        iterations=it,
        converged=converged,
    )
