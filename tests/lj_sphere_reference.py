"""Independent reference for the elastic solver: L-J 3-9 adhesion of a paraboloid (n = 2).

A second implementation that shares no discretisation with pipeline.mechanics.elastic_contact,
in the spirit of Greenwood (1997, Proc. R. Soc. A 453:1277) and Feng (2000): uniform nodes,
pressure piecewise LINEAR (hat functions) with nodal values tau(gap_j) (nodal collocation, no
cell means), ring kernel (4/pi) s K(m)/(x+s), m = 4xs/(x+s)^2, integrated by Gauss-Legendre
with the log singularity of K at s = x subtracted and integrated analytically, and the path
followed by pseudo-arc-length continuation in (gap, D) on that fixed grid instead of the
solver's pinned zone radius on rebuilt grids.  (Feng's central-gap control fails for L-J on the
JKR side: once in contact the central gap stays at about -0.02 h over the whole contact branch.)  Units as in the
solver: x in c_h = (2 R h)^(1/2), gaps in h, stress in sigma_0; kappa = sigma_0 c_h/(E* h).
"""

from __future__ import annotations

import numpy as np
from scipy import integrate
from scipy import special as sp

ZETA = 1.0 / 0.974
_GX, _GW = np.polynomial.legendre.leggauss(16)
_GX, _GW = 0.5 * (_GX + 1.0), 0.5 * _GW


def lj(s):
    r = ZETA / (ZETA + s)
    return 8.0 / (3.0 * ZETA) * (r**3 - r**9)


def lj_slope(s):
    r = ZETA / (ZETA + s)
    return 8.0 / (3.0 * ZETA**2) * (9.0 * r**10 - 3.0 * r**4)


def hat_influence(x):
    """K[i, j] = (4/pi) int phi_j(s) s K(m(x_i, s)) / (x_i + s) ds on uniform nodes x."""
    N = x.size
    dx = x[1] - x[0]
    K = np.zeros((N, N))
    for e in range(N - 1):  # element [x_e, x_e+1]
        s = x[e] + dx * _GX  # (16,)
        xi = x[:, None]
        tot = xi + s[None, :]
        p = ((xi - s[None, :]) / tot) ** 2  # 1 - m
        with np.errstate(divide="ignore", invalid="ignore"):
            ratio = np.where(tot > 0, s[None, :] / tot, 1.0)
        reg = sp.ellipkm1(p) - np.log(4.0) + 0.5 * np.log(p)  # K - ln(4/k'), smooth
        for j, phi in ((e, (x[e + 1] - s) / dx), (e + 1, (s - x[e]) / dx)):
            g = 4.0 / np.pi * phi[None, :] * ratio  # (N, 16)
            smooth = g * (np.log(4.0 * tot) + reg)
            K[:, j] += dx * (smooth @ _GW)
            # -ln|x - s|: plain Gauss away from the element, subtraction next to it
            near = (x >= x[e] - 1e-12) & (x <= x[e + 1] + 1e-12)
            far = ~near
            K[far, j] += dx * ((g[far] * -np.log(np.abs(xi[far] - s[None, :]))) @ _GW)
            for i in np.nonzero(near)[0]:
                gx = (
                    4.0
                    / np.pi
                    * (np.interp(x[i], [x[e], x[e + 1]], [1.0, 0.0] if j == e else [0.0, 1.0]))
                    * (x[i] / (2.0 * x[i]) if x[i] > 0 else 1.0)
                )
                u = s - x[i]
                with np.errstate(divide="ignore"):
                    sub = (g[i] - gx) * -np.log(np.abs(u))
                sub[~np.isfinite(sub)] = 0.0
                a, b = x[e] - x[i], x[e + 1] - x[i]

                def F(v):
                    return 0.0 if v == 0 else -(v * np.log(abs(v)) - v)

                K[i, j] += dx * (sub @ _GW) + gx * (F(b) - F(a))
    # x = 0: K(m = 0) = pi/2 exactly (no singularity; the split above would cancel two logs)
    K[0] = 2.0 * dx
    K[0, 0] = K[0, -1] = dx
    return K


def _tail(D, x_end):
    """Rigid estimate of 2 int_{x_end}^inf tau(D + x^2) x dx (the far tail of the force)."""
    return integrate.quad(lambda t: lj(D + t), x_end**2, np.inf, limit=200)[0]


def pulloff_ratio(kappa, **kw):
    """See :func:`_pulloff_ratio` (single-threaded BLAS: small systems, shared machines)."""
    from threadpoolctl import threadpool_limits

    with threadpool_limits(limits=1, user_api="blas"):
        return _pulloff_ratio(kappa, **kw)


def _pulloff_ratio(kappa, x_end=6.0, nodes=241, d_start=3.0, ds0=0.05):
    """Max tension f = F/F_rigid,Dugdale along the equilibrium path (n = 2).

    Pseudo-arc-length continuation in (g, D) with the norm ds^2 = mean(dg^2) + dD^2, from
    D = d_start (apart) inwards until the force is compressive; f at the maximum from a parabola
    through the three best path points in arc length.
    """
    x = np.linspace(0.0, x_end, nodes)
    K = hat_influence(x)
    dx = x[1] - x[0]
    w = x * dx  # int phi_j x dx (interior nodes)
    w[0] = dx * dx / 6.0
    w[-1] = (x[-1] / 2.0 - dx / 6.0) * dx
    N = x.size

    def residual(g, D):
        return g - D - x**2 + kappa * (K @ lj(g))

    def jac(g):
        J = kappa * K * lj_slope(g)[None, :]
        J[np.diag_indices_from(J)] += 1.0
        return np.column_stack([J, -np.ones(N)])  # unknowns (g, D)

    def force(g, D):
        return 2.0 * (w @ lj(g)) + _tail(D, x_end)

    # start: Newton at fixed D = d_start
    g, D = d_start + x**2, d_start
    for _ in range(60):
        R = residual(g, D)
        if np.max(np.abs(R)) < 1e-12:
            break
        g = g - np.linalg.solve(jac(g)[:, :-1], R)
    scale = np.concatenate([np.full(N, 1.0 / N), [1.0]])
    t = np.zeros(N + 1)
    t[-1] = -1.0

    def tangent(g, t_prev):
        M = np.vstack([jac(g), scale * t_prev])
        z = np.linalg.solve(M, np.concatenate([np.zeros(N), [1.0]]))
        return z / np.sqrt(np.sum(scale * z * z))

    t = tangent(g, t)
    path_s, path_f = [0.0], [force(g, D)]
    s_now, ds = 0.0, ds0
    u = np.concatenate([g, [D]])
    for _ in range(4000):
        up = u + ds * t
        v = up.copy()
        ok = False
        for _ in range(30):
            R = np.concatenate([residual(v[:-1], v[-1]), [np.sum(scale * t * (v - up))]])
            if np.max(np.abs(R)) < 1e-11 * (1 + abs(v[-1])):
                ok = True
                break
            M = np.vstack([jac(v[:-1]), scale * t])
            v = v - np.linalg.solve(M, R)
            v[:-1] = np.maximum(v[:-1], -0.7 * ZETA)
        f = force(v[:-1], v[-1]) if ok else np.nan
        if not ok or abs(f - path_f[-1]) > 0.02:
            ds *= 0.5
            if ds < 1e-8:
                raise RuntimeError("reference continuation stalled")
            continue
        u = v
        t = tangent(u[:-1], t)
        s_now += ds
        path_s.append(s_now)
        path_f.append(f)
        if f < 0 and max(path_f) > 0:
            break
        ds = min(ds * 1.3, 0.2)
    fs, ss = np.array(path_f), np.array(path_s)
    i = int(np.argmax(fs))
    c = np.polyfit(ss[i - 1 : i + 2], fs[i - 1 : i + 2], 2)
    return float(c[2] - c[1] ** 2 / (4.0 * c[0])) if c[0] < 0 else float(fs[i])
