"""Elastic adhesive contact of a power-law tip for any traction law (the paper's FE part, Sec. 3.3, 4.3).

Problem.  A rigid power-law tip z = r^n/(nQ) (Eq. 1) above an elastic half-space of reduced
modulus E* (Eq. 7; equivalently an elastic tip on a rigid flat, as in the paper's FE), interacting
through a traction law sigma(s) of the separation s from the zero-stress gap
(:mod:`.traction_laws`: Dugdale, L-J 3-9 with z0 = h/0.974, Tri1, Tri2, tables).  Axisymmetric,
frictionless, small slopes.  The gap at radius r is

    g(r) = Delta + r^n/(nQ) - w(r),   w(r) = (1/(pi E*)) int int sigma(g(r')) / |r - r'| dA'

(Delta: rigid approach offset, w: Boussinesq surface displacement of the tensile traction).

Non-dimensional form.  Radii in c_h = (n Q h)^(1/n) (where the undeformed tip is h above its
apex), gaps in h, tractions in sigma_0 = W_A/h:

    gamma(x) = D + x^n - kappa v(x),   v(x) = (1/pi) int int tau(gamma(x')) / |x - x'| dA'
    kappa = sigma_0 c_h / (E* h) = n^(1/n) Lambda^((2n-1)/n)           (Lambda: Eq. 8, ERRATA)
    f = F / (pi sigma_0 c_h^2) = 2 int_0^inf tau x dx,    F_rigid,Dugdale = pi sigma_0 c_h^2 (Eq. 12)

so one solve per (law, n, Lambda) serves the whole family (Q, E*, W_A, h), and
P~ = F/(pi P*) (Eq. 6) = f n^(2/n) Lambda^((n-2)/n).  kappa -> 0 is the rigid limit (f -> the
closed forms of :mod:`.rigid`), kappa -> inf the power-law JKR limit.

Discretisation.  Nodes 0 = x_0 < ... < x_N (graded, :func:`make_grid`); the law's unified
variable y (gap, or the contact pressure for a law with a hard wall) linear between nodes;
tractions constant on the cells [b_j, b_j+1] (b = mid-points), equal to the EXACT area mean of
the law over the linear y (:meth:`TractionLaw.segment_moments`), so the kinks and jumps of the
law and the contact edge sit where they are, not on a node.  v at the nodes from the closed-form
displacement of a uniformly loaded disk (complete elliptic integrals; the log-singular self term
is integrated analytically):

    int_{|rho| < b} dA / |r - rho| = 4 b E(r/b)                        (r <= b)
                                   = 4 r [E(b/r) - (1 - b^2/r^2) K(b/r)]  (r > b),

an annulus being the difference of two disks.  Equations: gap(y_i) - D - x_i^n + kappa (A t(y))_i
= 0 at every node, exact Jacobian, semi-smooth Newton with backtracking.

Path and pull-off.  The equilibrium path folds in D (jump-in, jump-out), so it is followed in a
parameter psi that does not fold: while the apex is in the zone, the radius r = -psi at which
the gap equals the law's marker separation ``law.pin`` (0 = the contact edge for Dugdale; the
peak-stress separation for laws with zero stress at contact, where the contact edge itself is
ill-defined on the JKR side); after that, psi = apex gap - pin.  That radius is a node of a grid
rebuilt for every state and refined around it and around every radius where the gap crosses a
break point of the law (the grid is rebuilt until those stop moving), so the cohesive zone is
resolved however thin it is (JKR side) and no edge snaps across the mesh.  Laws with a hard wall
are followed outwards from a compressed contact (non-adhesive contact first, the attraction
switched on by homotopy); L-J, without a wall, inwards from far apart.  The pull-off is the
largest tension on the path (the load-controlled pull-off of a soft cantilever and the maximum a
displacement-controlled retraction records, as in the M-D-n model and the paper); it is found by
Brent's bounded maximisation in psi around the best scanned state.  For Tri1, Tri2 and L-J on the
DMT side that maximum lies out of contact (apex gap > 0), as in the rigid limit.

Accuracy.  ``level`` scales every spacing of the grid; the error is about first order in 1/level
(measured against M-D-n: < 0.3 % at level 2 for n in [2, 20], Lambda in [0.01, 30]; see
tests/test_elastic_contact.py and benchmarks/bench_elastic_contact.py); ``error_estimate``
repeats the solve at level/2 and reports the difference (conservative for first order).
"""

from __future__ import annotations

import copy
import warnings
from dataclasses import dataclass, replace

import numpy as np
from scipy import linalg
from scipy import special as sp
from scipy.optimize import minimize_scalar
from threadpoolctl import threadpool_limits

from .rigid import LJ_H_OVER_Z0
from .traction_laws import TractionLaw, get_law

__all__ = [
    "Grid",
    "ElasticPulloff",
    "RAMP_WIDTH",
    "kappa_from_lambda",
    "influence_matrix",
    "make_grid",
    "elastic_pulloff",
    "elastic_path",
]


def kappa_from_lambda(n, lam):
    """kappa = sigma_0 c_h / (E* h) = n^(1/n) Lambda^((2n-1)/n) (see module docstring)."""
    n = np.asarray(n, float)
    return np.exp(np.log(n) / n + (2.0 * n - 1.0) / n * np.log(lam))


# ------------------------------------------------------------------------------ kernel
def _disk_integral(b, r):
    """int_{|rho|<b} dA/|r - rho| for a disk of radius b at a point at radius r (broadcasting)."""
    b, r = np.broadcast_arrays(np.asarray(b, float), np.asarray(r, float))
    out = np.zeros(b.shape)
    inside = (r <= b) & (b > 0)
    if np.any(inside):
        out[inside] = 4.0 * b[inside] * sp.ellipe((r[inside] / b[inside]) ** 2)
    outside = r > b
    if np.any(outside):
        ro, bo = r[outside], b[outside]
        m = (bo / ro) ** 2
        p = (ro - bo) * (ro + bo) / (ro * ro)  # 1 - m without cancellation
        out[outside] = 4.0 * ro * (sp.ellipe(m) - p * sp.ellipkm1(p))
    return out


def influence_matrix(x, b):
    """A[i, j]: v at node x_i from unit uniform traction on the annulus [b_j, b_j+1] (v as above)."""
    d = _disk_integral(b[None, :], x[:, None])
    return (d[:, 1:] - d[:, :-1]) / np.pi


# -------------------------------------------------------------------------------- grid
@dataclass
class Grid:
    """Nodes x, cell bounds b (b_0 = 0, mid-points, b_N+1 = x_N) and the influence matrix."""

    x: np.ndarray
    b: np.ndarray
    A: np.ndarray

    @classmethod
    def from_nodes(cls, x):
        x = np.asarray(x, float)
        b = np.concatenate([[0.0], 0.5 * (x[1:] + x[:-1]), [x[-1]]])
        return cls(x, b, influence_matrix(x, b))

    @property
    def half_area(self):
        """int x dx over each cell = (b_j+1^2 - b_j^2)/2."""
        return 0.5 * (self.b[1:] ** 2 - self.b[:-1] ** 2)


def make_grid(x_cover, x_max, spacing, features=(), growth=0.25, outer_growth=0.3):
    """Graded nodes on [0, x_max].

    Local spacing: ``spacing`` on [0, x_cover], at most dx_f + growth |x - x_f| near every
    feature (x_f, dx_f), and growing by ``outer_growth`` per unit distance beyond x_cover.
    Built by equidistributing int dx / spacing(x) on a dense auxiliary grid (no loops over nodes).
    """
    aux = [np.linspace(0.0, x_cover, 4001), x_cover + (x_max - x_cover) * np.linspace(0, 1, 4001) ** 2]
    for xf, dxf in features:
        off = dxf * (np.geomspace(1.0, 1.0 + 4.0 * x_max / dxf, 600) - 1.0)
        aux += [xf + off, xf - off]
    aux = np.unique(np.clip(np.concatenate(aux), 0.0, x_max))
    dx = np.where(aux <= x_cover, spacing, spacing + outer_growth * (aux - x_cover))
    for xf, dxf in features:
        dx = np.minimum(dx, dxf + growth * np.abs(aux - xf))
    dens = 1.0 / dx
    cum = np.concatenate([[0.0], np.cumsum(0.5 * (dens[1:] + dens[:-1]) * np.diff(aux))])
    count = max(int(np.ceil(cum[-1])), 8)
    return np.interp(np.linspace(0.0, cum[-1], count + 1), cum, aux)


# ----------------------------------------------------------------------------- system
#: Width (units of h) of the linear ramp that replaces a jump of a law (the Dugdale edge): W_A
#: and the peak stay the same, the pull-off changes by O(width^2) (not measurable at 0.01 against
#: M-D-n), and the equations stay Lipschitz where the gap is flat (apex of a high-n tip).
RAMP_WIDTH = 0.01


class _System:
    """Discrete equations R(y, D) = 0 on one grid for one law, n and kappa."""

    def __init__(self, grid: Grid, law: TractionLaw, n: float, kappa: float, contact_scale=1.0, ramp=RAMP_WIDTH):
        law = law.with_ramps(ramp)
        if law.wall:
            law = replace(law, contact_scale=float(contact_scale))
        self.grid, self.law, self.n, self.kappa = grid, law, float(n), float(kappa)
        x, b = grid.x, grid.b
        self.tip = x**self.n
        mid = b[1:-1]
        # half-segments: right half of cell j = [x_j, m_j], left half of cell j+1 = [m_j, x_j+1]
        self.ra = np.concatenate([x[:-1], mid])
        self.len = np.concatenate([mid - x[:-1], x[1:] - mid])
        self.area = grid.half_area
        self.N = x.size

    def tractions(self, y):
        """S_j = int_cell T(y) x dx and its tridiagonal derivatives dS_j/dy_(j-1, j, j+1)."""
        N = self.N
        ym = 0.5 * (y[:-1] + y[1:])
        I, da, db = self.law.segment_moments(
            self.ra, self.len, np.concatenate([y[:-1], ym]), np.concatenate([ym, y[1:]])
        )
        m = N - 1
        S = np.zeros(N)
        S[:-1] += I[:m]
        S[1:] += I[m:]
        diag = np.zeros(N)
        diag[:-1] += da[:m] + 0.5 * db[:m]
        diag[1:] += 0.5 * da[m:] + db[m:]
        sup = np.zeros(N)
        sup[:-1] = 0.5 * db[:m]
        sub = np.zeros(N)
        sub[1:] = 0.5 * da[m:]
        return S, sub, diag, sup

    def evaluate(self, y, D, jacobian=True):
        """Residual R, force f = 2 sum S and (optionally) the Jacobian dR/dy."""
        S, sub, diag, sup = self.tractions(y)
        A = self.grid.A
        R = self.law.gap(y) - D - self.tip + self.kappa * (A @ (S / self.area))
        f = 2.0 * S.sum()
        if not jacobian:
            return R, f, None
        inv = 1.0 / self.area
        J = A * (diag * inv)[None, :]
        J[:, 1:] += A[:, :-1] * (sup[:-1] * inv[:-1])[None, :]
        J[:, :-1] += A[:, 1:] * (sub[1:] * inv[1:])[None, :]
        J *= self.kappa
        J[np.diag_indices_from(J)] += self.law.gap_slope(y)
        return R, f, J

    def with_attraction(self, theta):
        """The same system with the attractive stress scaled by theta (homotopy)."""
        other = copy.copy(self)
        other.law = replace(self.law, attraction=float(theta))
        return other


# --------------------------------------------------------------------------- Newton
class _NoConvergenceError(RuntimeError):
    pass


_LJ_FLOOR = -0.8 / LJ_H_OVER_Z0  # s = -0.8 z0: L-J gaps are kept above this (d = 0 is singular)


def _newton(sys: _System, y, D, row, rhs, tol=1e-10, max_iter=30, patient=False):
    """Semi-smooth Newton on R(y, D) = 0 and row . (y, D) = rhs; backtracking on ||R||^2 (the
    contact edge and the law's kinks make R piecewise smooth).  Returns (y, D, f, iterations).
    Residuals are weighted by 1/(1 + |D| + x^n) (x^n is huge far out for large n).  Gives up
    early (step below 1/1000 of the Newton step, or no halving of the residual in 8 iterations):
    the callers then take a shorter step along the path.  ``patient`` (a start far from the
    solution, no shorter step possible): 60 iterations, 30 halvings, no early exit."""
    if patient:
        max_iter = 60
    y = np.array(y, float)
    D = float(D)
    weight = 1.0 / (1.0 + abs(D) + sys.tip)

    def resid(y, D, jac):
        R, f, J = sys.evaluate(y, D, jacobian=jac)
        return R, row[:-1] @ y + row[-1] * D - rhs, f, J

    R, c, f, J = resid(y, D, True)
    M = np.empty((sys.N + 1, sys.N + 1))
    history = []
    for it in range(1, max_iter + 1):
        res = max(float(np.max(np.abs(R) * weight)), abs(c))
        if res <= tol:
            return y, D, f, it
        history.append(res)
        if not np.isfinite(res) or (not patient and len(history) > 8 and res > 0.5 * history[-9]):
            break
        M[:-1, :-1] = J
        M[:-1, -1] = -1.0
        M[-1] = row
        try:
            with warnings.catch_warnings():
                warnings.simplefilter("ignore", linalg.LinAlgWarning)
                du = linalg.solve(M, -np.concatenate([R, [c]]), check_finite=False)
        except (linalg.LinAlgError, ValueError):
            break
        dy, dD = du[:-1], du[-1]
        alpha = 1.0
        if not sys.law.wall:
            neg = dy < 0
            if np.any(neg):
                alpha = min(1.0, 0.9 * float(np.min((y[neg] - _LJ_FLOOR) / -dy[neg])))
        merit = float(R @ R + c * c)
        for _ in range(30 if patient else 10):
            yn, Dn = y + alpha * dy, D + alpha * dD
            Rn, cn, _, _ = resid(yn, Dn, False)
            if float(Rn @ Rn + cn * cn) <= (1.0 - 1e-4 * alpha) * merit:
                break
            alpha *= 0.5
        else:
            break
        y, D = yn, Dn
        R, c, f, J = resid(y, D, True)
    raise _NoConvergenceError("Newton did not converge")


# ------------------------------------------------------------------- path states
@dataclass
class _Solution:
    """One equilibrium: control psi, grid nodes x, unified variable y, offset D, force f,
    the radii where the gap crosses the law's break points (``feats``) and Newton iterations."""

    psi: float
    x: np.ndarray
    y: np.ndarray
    D: float
    f: float
    feats: np.ndarray
    iters: int = 0

    @property
    def a(self):
        """Radius of the pinned node (psi < 0), 0 when the apex is controlled."""
        return max(-self.psi, 0.0)

    def contact_radius(self):
        """Outermost radius where y crosses 0 (edge of the contact, or of L-J's repulsive zone)."""
        neg = np.nonzero(self.y < 0)[0]
        if not neg.size:
            return 0.0
        i = int(neg[-1])
        if i + 1 >= self.y.size:
            return float(self.x[-1])
        t = self.y[i] / (self.y[i] - self.y[i + 1])
        return float(self.x[i] + t * (self.x[i + 1] - self.x[i]))

    def knots(self):
        """Radii that mark the structure of this state: pinned radius and feature crossings."""
        return np.sort(np.concatenate([[self.a] if self.a > 0 else [], self.feats]))

    def warped(self, x_new, knots_new):
        """y moved onto nodes x_new so that its knots land on ``knots_new`` (piecewise-linear map
        of the radius through matched knots; plain interpolation when the knots do not match)."""
        old = self.knots()
        far = 2.0 * max(float(np.max(old, initial=0.0)), float(np.max(knots_new, initial=0.0)), 1e-300)
        kn = np.concatenate([[0.0], knots_new, [far]])
        ko = np.concatenate([[0.0], old, [far]])
        x_old = x_new
        if kn.size == ko.size and np.all(np.diff(kn) > 0) and np.all(np.diff(ko) > 0):
            x_old = np.where(x_new < far, np.interp(x_new, kn, ko), x_new)
        return np.interp(x_old, self.x, self.y, right=np.nan)


class _PathSolver:
    """Equilibria at prescribed psi for one (n, kappa, law), each on its own adapted grid.

    Grid: spacing x_cover/(24 level) on [0, x_cover], growing by 0.3 per unit length beyond; near
    every knot r_k at most dx_k + (0.25/level)|x - r_k| with dx_k = 0.1 (distance to the nearest
    other knot or the axis)/level (>= 2e-6 x_cover), i.e. ~10 level cells across the thinnest
    cohesive zone.
    """

    def __init__(self, n, kappa, law: TractionLaw, x_cover, x_max, level=2.0, ramp=RAMP_WIDTH):
        self.n, self.kappa, self.level, self.ramp, self.law = float(n), float(kappa), float(level), ramp, law
        self.x_cover, self.x_max = float(x_cover), float(x_max)
        self.spacing = self.x_cover / (24.0 * self.level)
        self.growth = 0.25 / self.level
        self.floor = 2e-6 * self.x_cover
        # contact pressure = -y/contact_scale: a node's own elastic response kappa A_ii/contact_scale
        # is then of order one, like the slope of the gap out of contact (no active-set cycling)
        self.contact_scale = self.kappa * self.x_cover / 50.0
        self.pin = float(law.pin)
        values = set(law.features) | ({0.0} if law.wall and self.pin > 0 else set())
        self.values = np.array(sorted(v for v in values if v != self.pin and (v > 0 or self.pin > 0 or not law.wall)))
        self.evaluations = 0

    def _knot_spacing(self, radii):
        pts = np.concatenate([[0.0], np.sort(np.asarray(radii, float))])
        gaps = np.diff(pts)
        d = np.minimum(gaps, np.concatenate([gaps[1:], [np.inf]]))
        return np.clip(0.1 * d, self.floor, 0.5 * self.spacing * self.level) / self.level

    def grid(self, a, feats):
        """Grid refined around the knots, with a node exactly at the pinned radius a (if > 0)."""
        radii = [float(v) for v in feats if 0 < v < self.x_max] + ([float(a)] if a > 0 else [])
        radii = np.unique(np.round(np.asarray(radii, float), 14))
        dx = self._knot_spacing(radii) if radii.size else []
        x = make_grid(self.x_cover, self.x_max, self.spacing, list(zip(radii, dx)), growth=self.growth)
        if a > 0:
            k = min(max(int(np.argmin(np.abs(x - a))), 1), x.size - 2)
            x[k] = a
            if not (x[k - 1] < a < x[k + 1]):
                x = np.sort(np.concatenate([np.delete(x, k), [a]]))
        return Grid.from_nodes(x), (int(np.searchsorted(x, a)) if a > 0 else 0)

    def system(self, grid, theta=1.0):
        sys = _System(grid, self.law, self.n, self.kappa, contact_scale=self.contact_scale, ramp=self.ramp)
        return sys if theta == 1.0 else sys.with_attraction(theta)

    def crossings(self, x, y):
        """Radii where the piecewise-linear y crosses the law's break points (not the pin)."""
        if not self.values.size:
            return np.zeros(0)
        d = y[None, :] - self.values[:, None]
        neg = d < 0
        i, j = np.nonzero(neg[:, :-1] != neg[:, 1:])
        t = d[i, j] / (d[i, j] - d[i, j + 1])
        return np.sort(x[j] + t * (x[j + 1] - x[j]))

    def _predicted_knots(self, psi, guess, prev, r, secant):
        a = max(-psi, 0.0)
        kg = guess.knots()
        if secant:
            knots = kg + r * (kg - prev.knots())
        elif a > 0 and guess.a > 0:  # the zone moves with the pinned radius
            knots = kg + (a - guess.a) * (kg < 3.0 * guess.a)
        else:
            knots = np.concatenate([[a], guess.feats]) if a > 0 else guess.feats
        if a > 0:  # drop the pinned radius itself
            j = int(np.argmin(np.abs(knots - a))) if guess.a > 0 else 0
            knots = np.delete(knots, j)
        return knots

    def solve(self, psi, guess: _Solution, theta=1.0, prev=None, remesh=3, patient=False):
        """Equilibrium at psi from ``guess`` (and the secant through ``prev``, the state before
        it): states are warped so that their knots line up with the predicted ones, and the grid
        is rebuilt until the knots sit in its refined zones."""
        a = max(-psi, 0.0)
        r = 0.0
        if prev is not None and prev.psi != guess.psi:
            r = float(np.clip((psi - guess.psi) / (guess.psi - prev.psi), 0.0, 2.0))
        secant = r > 0 and prev.knots().size == guess.knots().size and (guess.a > 0) == (prev.a > 0) == (a > 0)
        feats = self._predicted_knots(psi, guess, prev, r, secant)
        base = guess
        for _ in range(remesh):
            grid, k_pin = self.grid(a, feats)
            knots = np.sort(np.concatenate([[a], feats])) if a > 0 else feats
            y0, D0 = base.warped(grid.x, knots), base.D
            if base is guess and secant:
                y0 = y0 + r * (y0 - prev.warped(grid.x, knots))
                D0 = D0 + r * (guess.D - prev.D)
            elif psi >= 0:
                shift = psi + self.pin - float(base.y[0])
                y0, D0 = y0 + shift, D0 + shift
            far = ~np.isfinite(y0)
            y0[far] = D0 + grid.x[far] ** self.n
            if not self.law.wall:
                y0 = np.maximum(y0, 0.5 * _LJ_FLOOR)
            elif a > 0 and self.pin == 0:  # inside the contact: on the contact side of the kink y = 0
                inside = grid.x < a
                y0[inside] = np.minimum(y0[inside], -1e-9)
            row = np.zeros(grid.x.size + 1)
            row[k_pin] = 1.0  # psi < 0: y = pin at r = a;  psi >= 0: y = pin + psi at the apex
            y, D, f, it = _newton(self.system(grid, theta), y0, D0, row, self.pin + max(psi, 0.0), patient=patient)
            self.evaluations += 1
            new = self.crossings(grid.x, y)
            sol = _Solution(psi, grid.x, y, D, f, new, it)
            if self._settled(feats, new, a):
                return sol
            feats, base = new, sol
        return sol

    def _settled(self, old, new, a):
        if new.size != old.size:
            return False
        if not new.size:
            return True
        dx = self._knot_spacing(np.concatenate([new, [a]] if a > 0 else [new]))[: new.size]
        return bool(np.all(np.abs(new - old) <= 3.0 * dx))

    def start(self, a0):
        """Compressed contact with the pinned radius a0 (laws with a wall): the non-adhesive
        contact (Hertz power-law approach D = -(n/2) B(n/2, 1/2) a0^n as first guess; a linear
        complementarity problem), then the attraction switched on at fixed a0.  Should that fail
        on a fine grid, the start is made on the coarsest grid and carried over."""
        try:
            return self._start(a0)
        except _NoConvergenceError:
            if self.level <= 1.0:
                raise
        coarse = _PathSolver(self.n, self.kappa, self.law, self.x_cover, self.x_max, level=1.0, ramp=self.ramp)
        return self.solve(-a0, coarse._start(a0))

    def _start(self, a0):
        D_h = -0.5 * self.n * sp.beta(0.5 * self.n, 0.5) * a0**self.n
        x0 = np.array([0.0, a0, self.x_max])
        sol = self.solve(-a0, _Solution(-a0, x0, D_h + x0**self.n, D_h, 0.0, np.zeros(0)), theta=0.0, patient=True)
        theta, dtheta = 0.0, 0.25
        while theta < 1.0:
            nxt = min(1.0, theta + dtheta)
            try:
                sol = self.solve(-a0, sol, theta=nxt)
            except _NoConvergenceError:
                dtheta *= 0.5
                if dtheta < 1e-3:
                    raise
                continue
            theta = nxt
            dtheta = min(2.0 * dtheta, 0.5)
        return sol


# ------------------------------------------------------------------------ scans
def _scan_out(solver: _PathSolver, plan, steps=10, max_solves=80):
    """States from the compressed contact (pinned radius plan.a_start) out along psi, ordered by
    psi, until psi >= plan.psi_end (an apex gap past the law's rigid optimum, beyond which the
    force only falls) and the force is 3 % below the best so far.  Returns (states, i_best)."""
    sols = [solver.start(plan.a_start)]
    targets = [-plan.a_start * (1.0 - k / steps) for k in range(1, steps)] + [0.0]
    dpsi = 0.02 * max(plan.psi_end, 0.05)
    i_best = 0
    while len(sols) < max_solves:
        psi = targets.pop(0) if targets else sols[-1].psi + dpsi
        if not targets and sols[-1].psi >= 0:
            dpsi *= 1.5
        try:
            sol = solver.solve(psi, sols[-1], prev=sols[-2] if len(sols) > 1 else None)
        except _NoConvergenceError:
            if abs(psi - sols[-1].psi) < 1e-6 * max(plan.a_start, 1.0):
                raise
            targets[:0] = [0.5 * (psi + sols[-1].psi), psi]
            continue
        sols.append(sol)
        if sol.f > sols[i_best].f:
            i_best = len(sols) - 1
        fb = sols[i_best].f
        if sol.psi >= plan.psi_end and fb > 0 and len(sols) - i_best >= 2 and sol.f < fb - 0.03 * max(fb, plan.f_scale):
            return sols, i_best
    raise _NoConvergenceError(f"no maximum of the tensile force within {max_solves} path points")


def _scan_in(solver: _PathSolver, plan, max_solves=150):
    """States from the apex gap plan.psi_far (nearly traction-free) in along psi to contact and
    on with a growing pinned radius until the force is compressive and 3 % below the largest
    tension met; ordered by psi.  Steps that change the force by more than 8 % are retried
    shorter, so no maximum is stepped over.  Returns (states, i_best)."""
    x0 = np.array([0.0, solver.x_max])
    top = plan.psi_far + solver.pin
    sols = [solver.solve(plan.psi_far, _Solution(plan.psi_far, x0, top + x0**solver.n, top, 0.0, np.zeros(0)))]
    step = -0.1 * plan.psi_far
    i_best = 0
    while len(sols) < max_solves:
        cur = sols[-1]
        psi = cur.psi + step
        if cur.psi > 0 > psi:
            psi = 0.0
        scale = max(plan.f_scale, abs(cur.f))
        try:
            sol = solver.solve(psi, cur, prev=sols[-2] if len(sols) > 1 else None)
            ok = abs(sol.f - cur.f) <= 0.08 * scale
        except _NoConvergenceError:
            ok = False
        if not ok:
            step *= 0.5
            if abs(step) < 1e-7 * max(plan.a_scale, plan.psi_far):
                raise _NoConvergenceError("path stalled")
            continue
        sols.append(sol)
        if sol.f > sols[i_best].f:
            i_best = len(sols) - 1
        fb = sols[i_best].f
        if sol.psi < 0 and sol.f < 0 < fb and sol.f < fb - 0.03 * max(fb, plan.f_scale):
            sols.reverse()
            return sols, len(sols) - 1 - i_best
        if sol.iters <= 5 and abs(sol.f - cur.f) < 0.03 * scale:
            step *= 1.5
        if sol.psi <= 0:  # in contact: steps of a fraction of the pinned radius
            step = -min(abs(step), 0.15 * max(sol.a, 0.2 * plan.a_scale))
    raise _NoConvergenceError(f"no compressive state within {max_solves} path points")


def _solve_towards(solver: _PathSolver, psi, known, depth=6):
    """Solve at psi from the nearest known state; where Newton fails, first at the midpoint
    (recursively), so hard stretches of the path are crossed in shorter steps.  New states are
    appended to ``known``."""
    near = min(known, key=lambda s: abs(s.psi - psi))
    try:
        sol = solver.solve(psi, near)
    except _NoConvergenceError:
        if depth == 0:
            raise
        _solve_towards(solver, 0.5 * (near.psi + psi), known, depth - 1)
        sol = solver.solve(psi, min(known, key=lambda s: abs(s.psi - psi)))
    known.append(sol)
    return sol


def _maximise(solver: _PathSolver, sols, i_best, rel_tol=1e-4):
    """Brent's bounded maximisation of f(psi) between the neighbours of the best scanned state."""
    lo = sols[max(i_best - 1, 0)].psi
    hi = sols[min(i_best + 1, len(sols) - 1)].psi
    known = list(sols)

    def neg_f(psi):
        try:
            sol = _solve_towards(solver, psi, known)
        except _NoConvergenceError:
            return -min(known, key=lambda s: abs(s.psi - psi)).f
        return -sol.f

    if hi > lo:
        minimize_scalar(neg_f, bounds=(lo, hi), method="bounded", options={"xatol": rel_tol * (hi - lo)})
    return max(known, key=lambda s: s.f)


# ---------------------------------------------------------------------- planning
@dataclass(frozen=True)
class _Plan:
    a_start: float  # pinned radius of the compressed start (outward scans)
    x_cover: float  # uniformly resolved disk
    x_max: float  # end of the grid
    f_scale: float  # expected pull-off f (step and stop criteria)
    psi_end: float  # outward scans stop past this psi
    psi_far: float  # inward scans start here
    a_scale: float  # expected pinned radius at pull-off


def _plan(n, lam, law: TractionLaw):
    """Scales of the problem from the M-D-n (Dugdale) solution at the same (n, Lambda)."""
    from .mdn import mdn_branch
    from .rigid import rigid_optimal_gap, rigid_pulloff_ratio

    kappa = float(kappa_from_lambda(n, lam))
    b = mdn_branch(n, lam, num=60, a_factor=2.0)
    i = b.i_pulloff
    a_po = float(b.a[i]) * (lam / n) ** (1.0 / n)  # x = a~ (Lambda/n)^(1/n)
    c_po = a_po * float(b.m[i])
    zone = max(law.features) if law.features else law.reach
    c_est = max(c_po, zone ** (1.0 / n))
    # compressed start: where the M-D-n load is compressive (half the pull-off), outside the flat
    # apex of a high-n tip (where the radius hardly moves the approach) and past a pinned
    # separation > 0; not further (a high-n tip pressed to 1.6 a_po is 1.6^n times the approach)
    comp = np.nonzero((b.P >= 0.5 * b.pulloff) & (b.a > b.a[i]))[0]
    a_comp = float(b.a[comp[-1]]) * (lam / n) ** (1.0 / n) if comp.size else 1.6 * a_po
    a_start = max(a_comp, 0.25 * c_est, 0.05 ** (1.0 / n), (law.pin + 0.3) ** (1.0 / n) if law.pin > 0 else 0.0)
    d_hertz = 0.5 * n * sp.beta(0.5 * n, 0.5) * a_start**n  # |D| of the start (Hertz)
    # zone edge at the start: carried with the contact edge (JKR side) or set by the tip shape
    c_start = max(c_est, (zone + d_hertz) ** (1.0 / n), a_start + (c_po - a_po) if b.m[i] < 3.0 else 0.0)
    x_cover = 1.25 * c_start
    named = law.name in ("dugdale", "lj", "tri1", "tri2")
    ratio = float(rigid_pulloff_ratio(n, law.name)) if named else 1.0
    f_scale = max(b.pulloff / (n ** (2.0 / n) * lam ** ((n - 2.0) / n)) * min(ratio, 1.0), 1e-3)
    # far end: traction-free (walls) or below 1e-8 of the force (L-J's tail), elastic pull included
    need = (1e4 if not law.wall else 10.0 * (law.reach + 1.0)) + 2.0 * d_hertz
    x_max = max(1.5 * x_cover, need ** (1.0 / n))
    x_max = max(x_max, (need + 4.0 * kappa * f_scale / x_max) ** (1.0 / n))
    gap_opt = float(rigid_optimal_gap(n, law.name)) if named else 0.9 * zone
    psi_end = max(gap_opt + 0.25 * zone - law.pin, 0.05 * zone)
    psi_far = (1.02 * law.reach if law.wall else 3.0) - law.pin
    return _Plan(a_start, x_cover, x_max, f_scale, psi_end, psi_far, max(a_po, 0.25 * c_est))


def _solve(n, lam, law, plan, level):
    """(best state, solver, path) at one level; walls outwards, L-J inwards (module docstring).
    BLAS runs single-threaded: the systems are small (N ~ 50-300), and threads only wait for
    each other on a loaded machine (8x slower measured on 2 shared cores)."""
    solver = _PathSolver(n, kappa_from_lambda(n, lam), law, plan.x_cover, plan.x_max, level=level)
    with threadpool_limits(limits=1, user_api="blas"):
        sols, i_best = (_scan_out if law.wall else _scan_in)(solver, plan)
        best = _maximise(solver, sols, i_best)
    if float(solver.law.gap(best.y[-1:])[0]) <= law.reach:
        raise _NoConvergenceError("solution domain too small (traction at the last node)")
    return best, solver, sols


# ------------------------------------------------------------------------ public API
@dataclass(frozen=True)
class ElasticPulloff:
    """Pull-off of one (law, n, Lambda) from the direct elastic solve (non-dimensional).

    ratio: F_p / F_p,rigid,Dugdale (Eq. 12), the f of the module docstring;  pulloff_nd:
    P~ = F_p/(pi P*) (Eq. 6);  error_estimate: |P~(level) - P~(level/2)| / P~ (NaN if not asked);
    contact_radius: a/c_h at pull-off (0: out of contact);  apex_gap: apex gap / h;  approach:
    D / h (> 0: apart);  nodes, solves: size of the last grid and number of Newton solves.
    """

    law: str
    n: float
    Lambda: float
    kappa: float
    ratio: float
    pulloff_nd: float
    error_estimate: float
    contact_radius: float
    apex_gap: float
    approach: float
    nodes: int
    solves: int


def elastic_pulloff(n, Lambda, law="dugdale", level=2.0, estimate_error=False):
    """Pull-off of a power-law tip on an elastic half-space for any traction law (scalar inputs).

    n in [2, 20], Lambda in (0, 30] (Eq. 8, ERRATA; larger Lambda: the JKR limit, where every law
    gives the M-D-n value), law: "dugdale", "lj", "tri1", "tri2" or a :class:`TractionLaw` (e.g.
    from :func:`tabulated_law`).  ``level``: grid density (2 = default, < 0.3 % against M-D-n);
    ``estimate_error``: also solve at level/2 (or 3 level/4 if that path stalls) and report the
    difference (NaN if neither solves).
    """
    law = get_law(law)
    n, lam = float(n), float(Lambda)
    if not (2.0 <= n <= 20.0 and 0.0 < lam <= 30.0 * (1 + 1e-12)):
        raise ValueError(f"elastic_pulloff: need n in [2, 20] and Lambda in (0, 30] (got n = {n:g}, Lambda = {lam:g})")
    plan = _plan(n, lam, law)
    best, solver, _ = _solve(n, lam, law, plan, level)
    err = np.nan
    for coarse_level in (0.5 * level, 0.75 * level) if estimate_error else ():
        try:
            err = abs(best.f - _solve(n, lam, law, plan, coarse_level)[0].f) / abs(best.f)
            break
        except _NoConvergenceError:
            continue
    return ElasticPulloff(
        law=law.name,
        n=n,
        Lambda=lam,
        kappa=float(kappa_from_lambda(n, lam)),
        ratio=float(best.f),
        pulloff_nd=float(best.f * n ** (2.0 / n) * lam ** ((n - 2.0) / n)),
        error_estimate=float(err),
        contact_radius=best.contact_radius(),
        apex_gap=max(float(best.y[0]), 0.0),
        approach=float(best.D),
        nodes=int(best.x.size),
        solves=solver.evaluations,
    )


def elastic_path(n, Lambda, law="dugdale", level=2.0):
    """The traced equilibrium path (ordered from compressed to apart) as arrays: contact radius
    a/c_h, apex gap / h, approach D / h and f = F/F_rigid,Dugdale (Eq. 12)."""
    law = get_law(law)
    n, lam = float(n), float(Lambda)
    _, _, sols = _solve(n, lam, law, _plan(n, lam, law), level)
    arr = np.array([[s.contact_radius(), float(s.y[0]), s.D, s.f] for s in sols])
    return {"a": arr[:, 0], "apex_gap": arr[:, 1], "D": arr[:, 2], "f": arr[:, 3]}
