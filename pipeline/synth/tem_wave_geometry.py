"""Tip geometry of the independent TEM simulator (``pipeline.synth.tem_wave``): the worn
apex, its shank, an outer layer, contamination particles, and their projected thicknesses.

Written for the simulator alone: it shares no code with the edge fit's forward model
(``pipeline.tem``) or with ``pipeline.synth.tem_image``.

Tip frame (SI metres): z along the tip axis, 0 at the apex and increasing away from the
sample; x lateral in the image plane; y along the electron beam.

Outer surface (what touches the sample, coating included): a section at height z is
  rho(z, phi) = r(z) (1 + e cos phi),      phi = azimuth from +x,
a limacon of Pascal; e = 0 is a body of revolution.  Its silhouette in the image is
x = r (1 + e) on the right (x > 0) flank and x = -r (1 - e) on the left, so the two flanks
differ by 2e in radius at every height (|e| <= 0.05 for "up to 10 %"), both power laws of
the same n.  The section's cross-sectional area is pi r^2 (1 + e^2 / 2) (Eq. 12 needs
the area: the true rigid pull-off).  The chord of the section along the beam (y) at x is
closed-form (``limacon_chord``), so no numerical quadrature is needed; the tests check it
against brute-force integration.

Meridian r(z): the worn apex z = r^n / (n Q) (paper Eq. 1, Q = S^(n-2) R^(n-1), Eq. 2) up
to z_join, then the tangent line there, whose slope eases (C^2 from the join on, smoothstep
in the slope) over ``blend_length`` to the shank slope tan(half angle) (never below the
tangent slope, so the radius keeps growing).

Outer layer (native oxide, DLC) of normal thickness t: the core is the morphological
erosion of the outer body of revolution by a ball of radius t,
  r_core(z) = min_{|d| <= t} [ r(z + d) - sqrt(t^2 - d^2) ]
(exact for any meridian: a ball centred at distance rho from the axis fits inside iff every
one of its horizontal discs does), evaluated on a circle of 181 angles with a parabolic
refinement; the asymmetric body scales the core section by the same (1 + e cos phi).

Contamination particles: ellipsoids of amorphous carbon with one principal axis along the
beam, partly sunk into the surface; where a particle and the tip overlap, the tip's material
is counted (the chord of the particle minus its overlap with the tip's chord).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np

__all__ = ["TipBody", "Particle", "limacon_chord", "eroded_radius_table", "projected_thickness", "place_particle"]


def limacon_chord(x, r, e):
    """Chord (m) along y through the section rho(phi) = r (1 + e cos phi) at lateral x.

    (x, y) is inside iff s < r (1 + e x / s) with s = sqrt(x^2 + y^2), i.e. s^2 - r s - e r x < 0,
    i.e. s < R_eff = (r + sqrt(r^2 + 4 e r x)) / 2; chord = 2 sqrt(R_eff^2 - x^2).  r <= 0
    (no material at that height) gives 0.  e = 0: 2 sqrt(r^2 - x^2).
    """
    x = np.asarray(x, float)
    r = np.asarray(r, float)
    with np.errstate(invalid="ignore"):
        disc = r * r + 4.0 * e * r * x
        reff = 0.5 * (r + np.sqrt(np.maximum(disc, 0.0)))
        c2 = reff * reff - x * x
    ok = (r > 0) & (disc >= 0) & (c2 > 0)
    return np.where(ok, 2.0 * np.sqrt(np.where(ok, c2, 0.0)), 0.0)


def eroded_radius_table(z, radius, t, n_angles=181):
    """Core radius (m) at heights ``z`` of the body of revolution with outer radius
    ``radius(z)`` (callable, negative where there is no material) eroded by a ball of radius t.

    r_core(z) = min over the ball's discs at z + d, d = t sin(a), of r(z + d) - t cos(a);
    minimum over ``n_angles`` angles in [-pi/2, pi/2], refined by a parabola through the
    best sample and its neighbours.  -1 where no core exists (e.g. within t of the apex).
    """
    z = np.asarray(z, float)
    if t <= 0:
        return np.asarray(radius(z), float)
    a = np.linspace(-0.5 * np.pi, 0.5 * np.pi, n_angles)
    r_disc = radius(z[:, None] + t * np.sin(a)[None, :])
    cand = np.where(r_disc < 0, -np.inf, r_disc - t * np.cos(a)[None, :])
    k = np.argmin(cand, axis=1)
    best = cand[np.arange(z.size), k]
    # parabolic refinement where the neighbours exist and are finite
    inner = (k > 0) & (k < n_angles - 1) & np.isfinite(best)
    i = np.nonzero(inner)[0]
    if i.size:
        f0, f1, f2 = cand[i, k[i] - 1], best[i], cand[i, k[i] + 1]
        fin = np.isfinite(f0) & np.isfinite(f2)
        den = f0 - 2 * f1 + f2
        good = fin & (den > 0)
        h = np.where(good, 0.5 * (f0 - f2) / np.where(good, den, 1.0), 0.0)
        a_ref = a[k[i]] + h * (a[1] - a[0])
        zd = z[i] + t * np.sin(a_ref)
        rd = radius(zd)
        ref = np.where(rd >= 0, rd - t * np.cos(a_ref), -np.inf)
        best[i] = np.where(good, np.minimum(best[i], ref), best[i])
    return np.where(np.isfinite(best) & (best > 0), best, -1.0)


@dataclass
class TipBody:
    """Outer meridian r(z) (power-law apex, eased into a cone), asymmetry e, outer layer t.

    n, Q (m^(n-1)): apex z = r^n/(nQ) (Eq. 1) below ``z_join`` (m); ``shank_slope``: dr/dz
    of the shank cone far up (tan of its half angle; raised to the tangent slope at the
    join if lower); ``blend_length`` (m): height over which the slope eases from the
    tangent slope to the shank slope; ``asymmetry`` e: section rho = r (1 + e cos phi);
    ``layer_thickness`` (m): normal thickness of the outer layer (0: none).
    """

    n: float
    Q: float
    z_join: float = 15e-9
    shank_slope: float = math.tan(math.radians(15.0))
    blend_length: float = 20e-9
    asymmetry: float = 0.0
    layer_thickness: float = 0.0
    z_max: float = 600e-9
    _core_table: tuple = field(default=None, init=False, repr=False)

    def __post_init__(self):
        self.r_join = float((self.n * self.Q * self.z_join) ** (1.0 / self.n))
        self.tangent_slope = self.r_join / (self.n * self.z_join)  # dr/dz of the power law at z_join
        self.cone_slope = max(float(self.shank_slope), self.tangent_slope)
        if self.layer_thickness > 0:
            self._core_table = self._build_core_table()

    # --- outer meridian -------------------------------------------------------------
    def radius(self, z):
        """Outer radius r(z) (m) of the axisymmetric meridian; -1 below the apex (z < 0)."""
        z = np.asarray(z, float)
        r = np.full(z.shape, -1.0)
        low = (z >= 0) & (z <= self.z_join)
        r[low] = np.power(self.n * self.Q * z[low], 1.0 / self.n)
        high = z > self.z_join
        u = z[high] - self.z_join
        L = self.blend_length
        x = np.minimum(u / L, 1.0)
        ease = L * (x**3 - 0.5 * x**4) + np.maximum(u - L, 0.0)  # integral of smoothstep(u/L)
        r[high] = self.r_join + self.tangent_slope * u + (self.cone_slope - self.tangent_slope) * ease
        return r

    def flank_radii(self, z):
        """(r_left, r_right) (m): distance of the left and right outer silhouette from the axis."""
        r = self.radius(z)
        return r * (1.0 - self.asymmetry), r * (1.0 + self.asymmetry)

    def cross_section_area(self, z):
        """Area (m^2) of the outer section at height z: pi r^2 (1 + e^2/2)."""
        r = np.maximum(self.radius(z), 0.0)
        return np.pi * r**2 * (1.0 + 0.5 * self.asymmetry**2)

    # --- core ------------------------------------------------------------------------
    def _build_core_table(self):
        t = self.layer_thickness
        dense = np.arange(0.0, 40e-9 + t, 0.005e-9)  # fine where the core apex and flanks curve most
        coarse = np.arange(dense[-1] + 0.05e-9, self.z_max + 0.05e-9, 0.05e-9)
        zt = np.concatenate([dense, coarse])
        rc = eroded_radius_table(zt, self.radius, t)
        # tabulate r^2 (linear in z at a rounded core apex), a tiny negative value where there
        # is no core: the interpolated core apex is then within one table step (5 pm)
        return zt, np.where(rc > 0, rc * rc, -1e-24)

    def core_radius(self, z):
        """Core radius (m) at height z (the outer radius without a layer); -1 where no core."""
        if self._core_table is None:
            return self.radius(z)
        zt, q = self._core_table
        qi = np.interp(np.asarray(z, float), zt, q, left=-1.0, right=q[-1])
        return np.where(qi > 0, np.sqrt(np.maximum(qi, 0.0)), -1.0)

    # --- projections ---------------------------------------------------------------
    def outer_chord(self, x, z):
        """Chord (m) along the beam through the outer body at (x, z)."""
        return limacon_chord(x, self.radius(z), self.asymmetry)

    def core_chord(self, x, z):
        """Chord (m) along the beam through the core at (x, z)."""
        return limacon_chord(x, self.core_radius(z), self.asymmetry)

    def silhouette(self, z_top, spacing=0.01e-9):
        """Outer silhouette in the tip frame: (x, z) arrays (m), from the left flank's top
        through the apex to the right flank's top, points at most ~``spacing`` apart
        (sampled in z and, near a flat apex, in r)."""
        zs = np.arange(0.0, z_top + spacing, spacing)
        rmax = float(self.radius(min(z_top, self.z_join)))
        rs = np.arange(0.0, rmax, spacing)
        zr = rs**self.n / (self.n * self.Q)
        zr = zr[zr < min(z_top, self.z_join)]
        z = np.unique(np.concatenate([zs, zr]))
        rl, rr = self.flank_radii(z)
        return np.concatenate([-rl[::-1], rr[1:]]), np.concatenate([z[::-1], z[1:]])


@dataclass
class Particle:
    """Ellipsoidal particle: centre (x, y, z) in the tip frame (m), semi-axes (a, b) in the
    x-z plane rotated by ``tilt`` (rad) and c along the beam (m), its material and where
    it sits ("apex": 3-20 nm above the apex, "shank": far up), flank +1 right / -1 left."""

    centre: tuple
    semi_axes: tuple
    tilt: float
    material: str
    kind: str
    flank: int

    def chord_interval(self, x, z):
        """(y_low, y_high) of the particle along the beam at (x, z); empty where low >= high."""
        xc, yc, zc = self.centre
        a, b, c = self.semi_axes
        ct, st = math.cos(self.tilt), math.sin(self.tilt)
        u = (x - xc) * ct + (z - zc) * st
        v = -(x - xc) * st + (z - zc) * ct
        q = 1.0 - (u / a) ** 2 - (v / b) ** 2
        half = c * np.sqrt(np.maximum(q, 0.0))
        return yc - half, yc + half

    def bounding_radius(self):
        return max(self.semi_axes)


def place_particle(body, height, azimuth, semi_axes, sink, tilt, material, kind):
    """Particle touching the outer surface at ``height`` (m) and ``azimuth`` (rad, 0 = +x):
    its centre lies on the outward surface normal of that meridian at a distance
    ``sink`` x (its semi-axis a) from the surface (sink < 1: partly sunk in)."""
    dz = 1e-12
    r = float(body.radius(height)) * (1.0 + body.asymmetry * math.cos(azimuth))
    drdz = (float(body.radius(height + dz)) - float(body.radius(height - dz))) / (2 * dz)
    drdz *= 1.0 + body.asymmetry * math.cos(azimuth)
    nr, nz = 1.0 / math.hypot(1.0, drdz), -drdz / math.hypot(1.0, drdz)  # outward normal (rho, z)
    d = sink * semi_axes[0]
    rho, zc = r + d * nr, height + d * nz
    centre = (rho * math.cos(azimuth), rho * math.sin(azimuth), zc)
    return Particle(centre, tuple(semi_axes), tilt, material, kind, 1 if math.cos(azimuth) > 0 else -1)


def projected_thickness(body, particles, x, z):
    """Projected thickness (m) of each material at tip-frame points (x, z).

    Returns dict: "core", "layer" (outer minus core; zeros without a layer) and one entry
    per particle material (summed over particles, minus their overlap with the tip).
    """
    outer = body.outer_chord(x, z)
    core = body.core_chord(x, z) if body.layer_thickness > 0 else outer
    out = {"core": core, "layer": np.maximum(outer - core, 0.0)}
    half = 0.5 * outer  # the limacon (e along x) is symmetric in y: the tip occupies [-half, half]
    for p in particles:
        R = p.bounding_radius()
        xc, _, zc = p.centre
        near = (np.abs(x - xc) < R) & (np.abs(z - zc) < R)
        if not near.any():
            continue
        idx = np.nonzero(near)
        lo, hi = p.chord_interval(x[idx], z[idx])
        length = np.maximum(hi - lo, 0.0)
        overlap = np.maximum(np.minimum(hi, half[idx]) - np.maximum(lo, -half[idx]), 0.0)
        t = out.setdefault(p.material, np.zeros_like(outer))
        t[idx] += np.maximum(length - overlap, 0.0)
    return out
