"""Traction-separation laws for the elastic solver, in the paper's units (ERRATA table).

Separation s (from the zero-stress gap) in units of h, attractive stress tau = sigma/sigma_0,
sigma_0 = W_A/h, so that every law has unit work of adhesion (int tau ds = 1 over the
attractive part):

    Dugdale   tau = 1 on 0 <= s <= 1, 0 beyond                       hard wall at s = 0
    Tri1      0 -> 2 at s = 1/2 -> 0 at s = 1 (linear)                hard wall at s = 0
    Tri2      0 -> 1 at s = 1   -> 0 at s = 2 (linear)                hard wall at s = 0
    L-J 3-9   tau = (8/(3 zeta)) [(zeta/(zeta+s))^3 - (zeta/(zeta+s))^9],  zeta = z0/h = 1/0.974
              (Eq. 14 with d = z0 + s; repulsive for s < 0, no wall)
    table     user points (s_i, tau_i), s_i >= 0, linear between them, 0 beyond the last,
              hard wall at s = 0; the attractive area must be 1 (h and sigma_0 are then the
              Dugdale-equivalent range and stress of the table).

Hard wall ("unified variable").  A law with a wall is written in one variable y per point:
the gap is max(y, 0) and the traction is T(y) = tau(y) for y >= 0 and tau(0+) + y/c for y < 0,
i.e. -y/c is the extra compressive contact pressure (units of sigma_0); the solver picks the
scale c (``contact_scale``) so that y has the size of the gaps near the contact edge.  Contact (gap = 0,
pressure free) and separation are then one piecewise-linear equation, solved by semi-smooth
Newton without an active set.

Cell tractions.  The solver carries y at nodes, linear between nodes, and needs the
area-weighted mean of T(y(r)) over each cell [b_j, b_j+1] (b = midpoints).  For the
piecewise-linear laws (Dugdale, Tri1, Tri2, tables) these means are integrated EXACTLY
(moments of a polynomial between the points where y crosses the law's break points; jumps
such as the Dugdale edge give the exact moving-boundary derivative), so the traction
discontinuity is not smeared over a cell.  L-J is smooth and is integrated by 6-point
Gauss-Legendre quadrature per half-cell.
"""

from __future__ import annotations

from dataclasses import dataclass, field, replace

import numpy as np

from .rigid import LJ_H_OVER_Z0

__all__ = ["TractionLaw", "get_law", "tabulated_law", "LAW_NAMES"]

LAW_NAMES = ("dugdale", "lj", "tri1", "tri2")
_GL_U, _GL_W = np.polynomial.legendre.leggauss(6)
_GL_U = 0.5 * (_GL_U + 1.0)
_GL_W = 0.5 * _GL_W
_LJ_ZETA = 1.0 / LJ_H_OVER_Z0
_LJ_PEAK = (3.0 ** (1.0 / 6.0) - 1.0) * _LJ_ZETA  # separation of the L-J peak stress (units of h)


@dataclass(frozen=True)
class TractionLaw:
    """A traction law in units of (h, sigma_0); see the module docstring.

    ``features``: separations (units of h) where the law has a kink or a jump (the mesh is
    refined where the gap crosses them); ``reach``: separation beyond which the traction is
    zero (or, for L-J, below 1e-9 of its peak); ``wall``: hard contact at s = 0.
    """

    name: str
    kind: str  # "piecewise" or "lj"
    wall: bool
    features: tuple
    reach: float
    points: tuple = field(default=(), repr=False)  # (s, tau) break points of a piecewise law
    pin: float = 0.0  # separation whose radius marks the contact zone (solver control, see elastic_contact)
    contact_scale: float = 1.0  # y = -contact_scale * (extra contact pressure / sigma_0) in contact
    attraction: float = 1.0  # homotopy factor on the attractive stress (1 = the law itself)

    # ------------------------------------------------------------------ pointwise law
    def traction(self, y):
        """T(y) (tension positive, units of sigma_0) in the unified variable y (L-J: Eq. 14)."""
        y = np.asarray(y, float)
        if self.kind == "lj":
            r = _LJ_ZETA / (_LJ_ZETA + y)
            return 8.0 / (3.0 * _LJ_ZETA) * (self.attraction * r**3 - r**9)
        e_lo, e_hi, a, b, _, _ = self._pieces
        k = np.clip(np.searchsorted(e_hi, y, side="left"), 0, a.size - 1)
        return a[k] + b[k] * y

    def gap(self, y):
        """Gap (units of h) from y: max(y, 0) with a wall, y without."""
        y = np.asarray(y, float)
        return np.maximum(y, 0.0) if self.wall else y

    def gap_slope(self, y):
        y = np.asarray(y, float)
        return (y > 0.0).astype(float) if self.wall else np.ones_like(y)

    @property
    def _pieces(self):
        return _piece_table(self.points, self.contact_scale, self.attraction)

    # ------------------------------------------------------------ integrals over segments
    def with_ramps(self, width):
        """The same law with every jump replaced by a linear ramp of ``width`` (units of h)
        centred on it: the work of adhesion and the peak stay exactly the same and the change
        of the pull-off is second order in ``width``; it keeps the discrete equations Lipschitz
        where the gap is flat (apex of a high-n tip), which the Newton path needs."""
        if self.kind != "piecewise" or width <= 0:
            return self
        e_lo, e_hi, alpha, beta, je, _ = _build_pieces(self.points, 1.0)
        if not je.size:
            return self
        half = 0.5 * width
        pts = [p for p in self.points if np.all(np.abs(p[0] - je) >= half)]
        for e in je:
            k = int(np.searchsorted(e_hi, e))  # piece ending at e; piece k+1 starts there
            lo, hi = max(e - half, 0.0), e + half
            pts += [(float(lo), float(alpha[k] + beta[k] * lo)), (float(hi), float(alpha[k + 1] + beta[k + 1] * hi))]
        pts.sort(key=lambda p: p[0])
        return replace(self, points=tuple(pts), reach=max(self.reach, float(je.max()) + half))

    def segment_moments(self, ra, length, ya, yb):
        """int_0^1 T(y(u)) (ra + L u) L du for y(u) = ya + (yb - ya) u, and its derivatives.

        Vectorised over segments; returns (I, dI/dya, dI/dyb).  Exact for piecewise-linear
        laws (including jumps), 6-point Gauss-Legendre for L-J.
        """
        if self.kind == "lj":
            return _lj_segments(ra, length, ya, yb, self.attraction)
        return _piecewise_segments(self._pieces, ra, length, ya, yb)


def _piece_table(points, scale, attraction=1.0):
    """(e_lo, e_hi, alpha, beta, jump_edges, jump_sizes) of the extended law T(y)."""
    key = (points, scale, attraction)
    if key not in _PIECE_CACHE:
        if len(_PIECE_CACHE) > 256:
            _PIECE_CACHE.clear()
        _PIECE_CACHE[key] = _build_pieces(points, scale, attraction)
    return _PIECE_CACHE[key]


_PIECE_CACHE: dict = {}


def _build_pieces(points, scale, attraction=1.0):
    s = np.array([p[0] for p in points], float)
    t = attraction * np.array([p[1] for p in points], float)
    e_lo, e_hi, a, b = [-np.inf], [0.0], [t[0]], [1.0 / scale]  # compression: tau(0+) + y/scale
    for i in range(s.size - 1):
        if s[i + 1] > s[i]:
            slope = (t[i + 1] - t[i]) / (s[i + 1] - s[i])
            e_lo.append(s[i])
            e_hi.append(s[i + 1])
            a.append(t[i] - slope * s[i])
            b.append(slope)
    e_lo.append(s[-1])
    e_hi.append(np.inf)
    a.append(0.0)
    b.append(0.0)
    e_lo, e_hi, a, b = (np.array(v, float) for v in (e_lo, e_hi, a, b))
    # jumps at interior edges: right limit minus left limit
    edges = e_hi[:-1]
    right = a[1:] + b[1:] * edges
    left = a[:-1] + b[:-1] * edges
    jump = right - left
    keep = np.abs(jump) > 1e-15
    return e_lo, e_hi, a, b, edges[keep], jump[keep]


def _piecewise_segments(pieces, ra, length, ya, yb):
    e_lo, e_hi, a, b, je, jj = pieces
    ra, length, ya, yb = (np.asarray(v, float)[:, None] for v in (ra, length, ya, yb))
    d = yb - ya
    w0, w1 = ra * length, length * length
    small = np.abs(d) <= 1e-13 * (1.0 + np.abs(ya))
    inv = 1.0 / np.where(small, 1.0, d)
    with np.errstate(invalid="ignore"):
        u1 = np.clip((e_lo - ya) * inv, 0.0, 1.0)
        u2 = np.clip((e_hi - ya) * inv, 0.0, 1.0)
    lo, hi = np.minimum(u1, u2), np.maximum(u1, u2)
    ym = 0.5 * (ya + yb)
    inside = (ym > e_lo) & (ym <= e_hi)  # a point on a break belongs to the piece below it (y = 0: contact)
    lo = np.where(small, 0.0, lo)
    hi = np.where(small, inside.astype(float), hi)
    m0 = hi - lo
    m1 = 0.5 * (hi * hi - lo * lo)
    m2 = (hi**3 - lo**3) / 3.0
    c0 = a + b * ya
    c1 = b * d
    integral = (c0 * w0 * m0 + (c0 * w1 + c1 * w0) * m1 + c1 * w1 * m2).sum(axis=1)
    d_a = (b * (w0 * m0 + (w1 - w0) * m1 - w1 * m2)).sum(axis=1)
    d_b = (b * (w0 * m1 + w1 * m2)).sum(axis=1)
    if je.size:
        with np.errstate(invalid="ignore", divide="ignore"):
            ue = (je - ya) * inv
        hit = (~small) & (ue > 0.0) & (ue < 1.0)
        wgt = np.where(hit, jj * (w0 + w1 * ue) / np.abs(np.where(small, 1.0, d)), 0.0)
        d_a = d_a + (wgt * (1.0 - ue)).sum(axis=1)
        d_b = d_b + (wgt * ue).sum(axis=1)
    return integral, d_a, d_b


def _lj_segments(ra, length, ya, yb, attraction=1.0):
    """Cell integrals of the L-J 3-9 traction (Eq. 14) and their derivatives in the end values
    (ya, yb), by 6-point Gauss-Legendre quadrature (module doc)."""
    ra, length, ya, yb = (np.asarray(v, float)[:, None] for v in (ra, length, ya, yb))
    y = ya + (yb - ya) * _GL_U
    r = _LJ_ZETA / (_LJ_ZETA + y)
    r3 = r**3
    tau = 8.0 / (3.0 * _LJ_ZETA) * (attraction * r3 - r3**3)
    dtau = 8.0 / (3.0 * _LJ_ZETA**2) * (-3.0 * attraction * r3 * r + 9.0 * r3**3 * r)
    w = (ra + length * _GL_U) * length * _GL_W
    integral = (tau * w).sum(axis=1)
    d_a = (dtau * (1.0 - _GL_U) * w).sum(axis=1)
    d_b = (dtau * _GL_U * w).sum(axis=1)
    return integral, d_a, d_b


def tabulated_law(s, tau, name="table"):
    """A user traction law from points (s_i, tau_i) in units of (h, sigma_0), s_i >= 0 increasing.

    Linear between the points and zero beyond the last one (a non-zero last value is a jump
    to zero, as for Dugdale); a repeated s gives a jump.  Hard wall at s = 0.  The area under
    the law must be 1 within 1e-6 (that is what makes h and sigma_0 = W_A/h the
    Dugdale-equivalent range and stress); rescale s or tau to make it so.
    """
    s = np.asarray(s, float).ravel()
    tau = np.asarray(tau, float).ravel()
    if s.size < 2 or s.size != tau.size:
        raise ValueError("tabulated_law: need at least 2 points and as many tau values as s values")
    if not (np.all(np.isfinite(s)) and np.all(np.isfinite(tau))):
        raise ValueError("tabulated_law: s and tau must be finite")
    if s[0] != 0.0 or np.any(np.diff(s) < 0):
        raise ValueError("tabulated_law: s must start at 0 and be non-decreasing (units of h)")
    area = float(np.sum(0.5 * (tau[1:] + tau[:-1]) * np.diff(s)))
    if abs(area - 1.0) > 1e-6:
        raise ValueError(f"tabulated_law: the area under tau(s) is {area:.8g}, must be 1 (unit work of adhesion)")
    pts = tuple(zip(s.tolist(), tau.tolist()))
    inner = tuple(sorted(set(s[1:].tolist())))
    pin = 0.0 if tau[0] > 0 else float(s[int(np.argmax(tau))])
    return TractionLaw(name=name, kind="piecewise", wall=True, features=inner, reach=float(s[-1]), points=pts, pin=pin)


_LAWS = {
    "dugdale": TractionLaw("dugdale", "piecewise", True, (1.0,), 1.0, ((0.0, 1.0), (1.0, 1.0), (1.0, 0.0))),
    "tri1": TractionLaw("tri1", "piecewise", True, (0.5, 1.0), 1.0, ((0.0, 0.0), (0.5, 2.0), (1.0, 0.0)), pin=0.5),
    "tri2": TractionLaw("tri2", "piecewise", True, (1.0, 2.0), 2.0, ((0.0, 0.0), (1.0, 1.0), (2.0, 0.0)), pin=1.0),
    # L-J: refine around the repulsive/attractive boundary, the peak (d = 3^(1/6) z0) and the tail
    "lj": TractionLaw("lj", "lj", False, (0.0, _LJ_PEAK, 1.0, 2.0), 1.0e3, pin=_LJ_PEAK),
}


def get_law(law):
    """The TractionLaw for a name ("dugdale", "lj", "tri1", "tri2") or a TractionLaw itself."""
    if isinstance(law, TractionLaw):
        return law
    from . import _validate as V

    return _LAWS[V.potential(law)]
