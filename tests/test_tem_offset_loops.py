"""Loops of the silhouette fit's offset curve cut off (``pipeline.tem.offset_loops``)."""

import numpy as np
import pytest

from pipeline.tem.offset_loops import trimmed_loops
from pipeline.tem.silhouette_model import reference_curve


def _parabola(R=2.0, half_width=20.0):
    """Reference meridian (S, x, z, nx, nz) of z = x^2 / (2 R) (px), apex radius of curvature R."""
    x = np.linspace(-half_width, half_width, 4001)
    return reference_curve((x, x**2 / (2 * R)), step=0.25, smooth_px=0.0)


def _crossings(x, z):
    """Pairs of non-adjacent segments of the polyline that cross (zero-length segments skipped)."""
    P = np.column_stack([x, z])
    seg = [k for k in range(len(P) - 1) if np.any(P[k + 1] != P[k])]
    out = []
    for a_i, a in enumerate(seg):
        p, r = P[a], P[a + 1] - P[a]
        for b in seg[a_i + 2 :]:
            q, s = P[b], P[b + 1] - P[b]
            den = r[0] * s[1] - r[1] * s[0]
            if den == 0:
                continue
            t = ((q - p)[0] * s[1] - (q - p)[1] * s[0]) / den
            u = ((q - p)[0] * r[1] - (q - p)[1] * r[0]) / den
            if 0 < t < 1 and 0 < u < 1:
                out.append((a, b))
    return out


def test_a_move_inward_beyond_the_apex_radius_loses_its_loop():
    """A parabola of apex radius 2 px moved 4 px inward along its normals folds into a swallowtail;
    cut off, the curve does not cross itself, its corner lies on the axis 4 px from the parabola (the
    boundary of the body eroded by 4 px), and the points away from the loop are untouched."""
    S, x0, z0, nx, nz = _parabola(R=2.0)
    d = -4.0  # outward normals: inward is negative
    x, z = x0 + d * nx, z0 + d * nz
    assert _crossings(x[::4], z[::4]), "the moved curve must loop for this test to mean something"
    xt, zt = trimmed_loops(x, z, nx, nz)
    assert not _crossings(xt[::4], zt[::4])
    moved = (xt != x) | (zt != z)
    assert moved.any() and np.all(np.abs(S[moved]) < 12.0)  # only the loop near the apex
    corner = np.argmin(zt)
    assert xt[corner] == pytest.approx(0.0, abs=1e-3)  # symmetric: on the axis (to the sampling)
    dist = np.min(np.hypot(x0[:, None] - xt[None, moved], z0[:, None] - zt[None, moved]), axis=0)
    assert dist == pytest.approx(4.0, abs=0.02)  # the crossing point is 4 px from the parabola


def test_a_curve_that_does_not_loop_is_returned_as_it_is():
    """Moved less than its radius of curvature anywhere, the curve is the same arrays (no number of a
    fit without a loop changes)."""
    _, x0, z0, nx, nz = _parabola(R=8.0)
    x, z = x0 - 3.0 * nx, z0 - 3.0 * nz
    xt, zt = trimmed_loops(x, z, nx, nz)
    assert xt is x and zt is z
    x, z = x0 + 5.0 * nx, z0 + 5.0 * nz  # outward: never a loop on a convex curve
    assert trimmed_loops(x, z, nx, nz)[0] is x


def test_nested_loops_are_cut_at_the_outermost_crossing():
    """A wavy inward move that folds the apex twice leaves one corner, no crossing."""
    S, x0, z0, nx, nz = _parabola(R=1.0)
    d = -3.0 - 1.5 * np.cos(S / 1.5) * np.exp(-((S / 4.0) ** 2))
    x, z = x0 + d * nx, z0 + d * nz
    xt, zt = trimmed_loops(x, z, nx, nz)
    assert not _crossings(xt[::4], zt[::4])


def test_two_loops_apart_are_two_cuts():
    """A flat worn apex (45 degree flanks) moved 3 px in folds at both rounded corners: each loop is cut
    at its own crossing (merged into one search, neither was)."""
    for width in (4.0, 25.0):
        xs = np.array([-width / 2 - 20, -width / 2, width / 2, width / 2 + 20])
        xx = np.linspace(xs[0], xs[-1], 20001)
        _, x0, z0, nx, nz = reference_curve((xx, np.interp(xx, xs, [20, 0, 0, 20])), step=0.25, smooth_px=0.7)
        x, z = x0 - 3.0 * nx, z0 - 3.0 * nz
        assert len(_crossings(x[::2], z[::2])) >= 2
        xt, zt = trimmed_loops(x, z, nx, nz)
        assert not _crossings(xt[::2], zt[::2]), width


def _sphere_cone(R, half_angle_deg, height=80.0):
    """Reference meridian of a cone of the half-angle with a spherical apex of radius R (px)."""
    a = np.radians(half_angle_deg)
    phi = np.linspace(-(np.pi / 2 - a), np.pi / 2 - a, 2001)
    xs, zs = R * np.sin(phi), R - R * np.cos(phi)
    L = np.linspace(0, height, 4001)[1:]
    xr, zr = xs[-1] + L * np.sin(a), zs[-1] + L * np.cos(a)
    return reference_curve((np.r_[-xr[::-1], xs, xr], np.r_[zr[::-1], zs, zr]), step=0.25, smooth_px=0.0)


@pytest.mark.parametrize("half_angle, R, d", [(10, 3, -12), (5, 5, -9.5), (15, 3, -15)])
def test_a_sharp_tip_moved_in_far_is_cut_where_its_flanks_cross(half_angle, R, d):
    """On a sharp tip the crossing lies ~(|d| - R) / tan(half-angle) up the flanks, beyond the fine
    search's 40 px: the coarse search finds it."""
    _, x0, z0, nx, nz = _sphere_cone(R, half_angle)
    x, z = x0 + d * nx, z0 + d * nz
    xt, zt = trimmed_loops(x, z, nx, nz)
    assert not _crossings(xt[::2], zt[::2])
    corner = np.argmin(zt)
    assert xt[corner] == pytest.approx(0.0, abs=0.05)
