"""Solver of the silhouette fit: Levenberg-Marquardt over the forward model's parameters with the
soft monotone-flank penalty, its Jacobians (local translation, exact) and the exact Gauss-Newton polish."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from pipeline.tem.silhouette_model import _Problem

POLISH_MIN_DCHI2 = 1.0  # an exact Gauss-Newton step is taken if chi^2 falls by more than this x K
GLOBAL_EPS = 4e-3  # central-difference step of the global columns of the exact Jacobian (log units)
# weight of the soft monotone-flank penalty (1/px).  Flat faces: a bump is seen through
# the vacuum, a dimple (a hole in the section) only through the dark body, so a hard
# constraint (100) pushes a noisy face outwards and none (0) lets it sink inwards; 20
# leaves the least bias in n over blunt tips at SNR 10-15 (n 4.6-6: mean |dn| 0.03 -> 0.01)
MONOTONE_WEIGHT = 20.0
STATE_CACHE = 12  # evaluated states kept per fitter (the coating search ranks up to 10 starts)


@dataclass
class _State:
    v: np.ndarray
    cost: float
    ch: tuple
    T: np.ndarray
    B: np.ndarray
    lin: np.ndarray
    res: np.ndarray
    version: int = 0  # the problem's version (pixel map, weights, reference) it was made on


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
        self._cache, self._cache_version = {}, None  # evaluated states (``evaluate``)

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

    def evaluate(self, v):
        """The state at parameters ``v``.  The last few are kept while the problem's pixel map,
        weights and reference stay the same (``_Problem.version``) and the map is not stale at
        ``v``: a run that starts where another stopped, or from a start already ranked, gets the
        same state without rendering it again."""
        c, sigma, k_o, k_c, coat = self.unpack(v)
        key = v.tobytes()
        if self._cache_version != self.p.version:
            self._cache, self._cache_version = {}, self.p.version
        if key in self._cache and not self.p.map_stale(c, coat):
            return self._cache[key]
        ch = self.p.chords(c, coat)
        T = self.p.transmission(ch, k_o, k_c)
        B = self.p.blurred(T, sigma)
        lin = self.p.linear(B)
        res = (self.p.I - self.p.model(B, lin)) * self.p.w
        pr, _ = self.penalty(c)
        st = _State(v, float(res @ res + pr @ pr), ch, T, B, lin, res, self.p.version)
        if self._cache_version != self.p.version:  # the map was updated for v
            self._cache, self._cache_version = {}, self.p.version
        if len(self._cache) >= STATE_CACHE:
            self._cache.pop(next(iter(self._cache)))
        self._cache[key] = st
        return st

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
        M0 = p.model(st.B, st.lin)

        def col(B):
            return -(p.model(B, st.lin) - M0) * p.w

        G = None
        if with_shape:
            eps = 0.05
            ch = p.chords(c + eps, coat)  # partition of unity: c + eps = uniform offset
            G = col(p.blurred(p.transmission(ch, k_o, k_c), sigma)) / eps
        models = [lambda e: p.blurred(st.T, sigma * np.exp(e))]
        names = ["log_sigma"]
        if self.coated:
            models += [
                lambda e: p.blurred(p.transmission(st.ch, k_o * np.exp(e), k_c), sigma),
                lambda e: p.blurred(p.transmission(st.ch, k_o, k_c * np.exp(e)), sigma),
                lambda e: p.blurred(
                    p.transmission(p.chords(c, coat * np.exp(e), outer=(st.ch, st.version)), k_o, k_c),
                    sigma,
                ),
            ]
            names += ["log_k_o", "log_k_c", "log_coat"]
        else:
            models.append(lambda e: p.blurred(p.transmission(st.ch, k_o * np.exp(e), k_o * np.exp(e)), sigma))
            names.append("log_k_o")
        if central:
            e = GLOBAL_EPS
            cols = [(col(m(e)) - col(m(-e))) / (2 * e) for m in models]
        else:
            cols = [col(m(0.02)) / 0.02 for m in models]
        act = p.active(M0)
        Jo = np.column_stack(cols + [-st.B * (p.w if act is None else p.w * act)[:, None]])
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
        # one fixed pixel map for the base and the perturbations, built from (c, coat) alone: the
        # maps the LM and the coated trial fits left must not decide which pixels are supersampled
        p.update_pixel_map(c, coat, cold=True)
        st = self.evaluate(st.v)
        _, Jo, names = self.jacobian(st, with_shape=False, central=True)
        M0 = p.model(st.B, st.lin)
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
            d = -(p.model(B, st.lin) - M0) * p.w / eps
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
        for it in range(1, iters + 1):  # noqa: B007 - it, the iterations done, is returned
            if shape_mode == "full" and self.p.map_stale(st.v[:K], self.unpack(st.v)[4]):
                self.p.update_pixel_map(st.v[:K], self.unpack(st.v)[4])
                # the supersampled band moved: the state must be re-evaluated on the new map,
                # or the finite-difference columns against it pick up the band change
                st = self.evaluate(st.v)
            JTJ, grad, names, nsh, ng = self.normal_equations(st, shape_mode)
            improved, dc, dv = False, 0.0, np.zeros_like(v)
            # parameters at a bound whose descent direction points outwards are held fixed
            pv = np.concatenate([st.v[:K] if shape_mode == "full" else st.v[:1] if nsh else [], st.v[K : K + ng]])
            plb = np.concatenate([lb[:nsh], lb[K : K + ng]])
            pub = np.concatenate([ub[:nsh], ub[K : K + ng]])
            held = np.zeros(grad.size, bool)
            held[: nsh + ng] = ((pv <= plb + 1e-9) & (grad[: nsh + ng] > 0)) | (
                (pv >= pub - 1e-9) & (grad[: nsh + ng] < 0)
            )
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
                dv[K : K + ng] = step[nsh:]
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
