"""Synthetic TEM image generator: determinism, exact outer profile, contrast physics, TIFF tags;
the projection helpers' erosions (eroded_radius, core_radius_sq_table)."""

from __future__ import annotations

import math

import numpy as np
import pytest

from pipeline.synth.tem_image import outer_radius, power_law_radius, render_tem_image, write_tem_tiff
from pipeline.tem.projection import chord, core_radius_sq_table, eroded_radius
from pipeline.tem.reading import read_tem_image


def test_deterministic_by_seed():
    a, ta = render_tem_image(3, 15e-9**2, 0.3e-9, shape=(128, 128), seed=4)
    b, tb = render_tem_image(3, 15e-9**2, 0.3e-9, shape=(128, 128), seed=4)
    c, _ = render_tem_image(3, 15e-9**2, 0.3e-9, shape=(128, 128), seed=5)
    assert np.array_equal(a, b) and ta == tb and not np.array_equal(a, c)
    assert a.dtype == np.uint16


def test_truth_and_eq2():
    _, t = render_tem_image(4, 20e-9**3, 0.25e-9, shape=(96, 96), S=1.0)
    assert t["R"] == pytest.approx(20e-9) and t["n"] == 4 and t["pixel_size"] == 0.25e-9
    _, t2 = render_tem_image(4, 2.0**2 * (10e-9) ** 3, 0.25e-9, shape=(96, 96), S=2.0)
    assert t2["R"] == pytest.approx(10e-9)  # Q = S^(n-2) R^(n-1)


def test_outer_profile_is_power_law_then_tangent_cone():
    n, Q = 4.0, 20e-9**3
    z = np.linspace(0, 25e-9, 200)
    assert np.allclose(outer_radius(z, n, Q), (n * Q * z) ** (1 / n))
    zb, dz = 25e-9, 1e-12
    slope_below = (outer_radius(zb, n, Q) - outer_radius(zb - dz, n, Q)) / dz
    slope_above = (outer_radius(zb + dz, n, Q) - outer_radius(zb, n, Q)) / dz
    assert slope_above == pytest.approx(slope_below, rel=1e-3)  # C1 join


def test_erosion_is_normal_offset():
    """Erosion of a cone by d: radius shrinks by d / cos(half angle) -- an exact offset."""
    z = np.linspace(-5, 50, 5501)
    alpha = np.radians(20)
    r = np.where(z >= 0, z * np.tan(alpha), -1.0)
    rc = eroded_radius(z, r, 2.0)
    zz = z > 20
    expect = z[zz] * np.tan(alpha) - 2.0 / np.cos(alpha)
    assert np.allclose(rc[zz], expect, atol=2e-3)


def _disk_offsets(dz, t):
    """The offsets s of the core table's definition: the grid offsets m dz strictly inside the
    disk and its two ends -t and +t."""
    m = range(-math.ceil(t / dz) - 1, math.ceil(t / dz) + 2)
    return [-t] + [i * dz for i in m if abs(i * dz) < t] + [t]


def _core_table_by_rows(rho_sq, dz, t):
    """Reference: every core row z0 + t + j dz on its own, r(z) by np.interp of rho_sq (its ends
    held beyond the table), min over s of r(z + s) - sqrt(t^2 - s^2)."""
    s = np.array(_disk_offsets(dz, t))
    cap = np.sqrt(np.maximum(t * t - s * s, 0.0))
    grid = np.arange(len(rho_sq), dtype=float)
    out = np.zeros(len(rho_sq))
    for j in range(len(rho_sq)):
        r = np.sqrt(np.maximum(np.interp(j + (t + s) / dz, grid, rho_sq), 0.0))
        out[j] = max(np.min(r - cap), 0.0) ** 2
    return out


def _core_table_tables(rng, n):
    """Outer tables: monotone (random increments; a power-law tip), and not (zeros, bumps)."""
    z = np.arange(n, dtype=float)
    yield np.cumsum(rng.uniform(0.0, 50.0, n))
    yield (300.0 * (z / max(z[-1], 1.0)) ** 0.2) ** 2
    yield np.maximum(rng.normal(0.0, 1.0, n), 0.0) * 1e4
    yield np.concatenate([np.zeros(n // 3), rng.uniform(0.0, 9e4, n - n // 3)])


CORE_TABLE_THICKNESSES = [0.0, 0.05, 0.3, 0.5, 1.0, 1.5, 7.5, 12.37]  # with the multiples of dz


@pytest.mark.parametrize("dz", [0.1, 0.25])
def test_core_table_is_the_erosion_row_by_row(dz):
    """core_radius_sq_table (one interpolation per fraction of a row, shifted slices) against the
    definition evaluated row by row: random monotone and non-monotone tables, thicknesses on and
    off the grid (t = k dz has no inner offset at |s| = t), thinner than a row, and 0."""
    rng = np.random.default_rng(7)
    thick = CORE_TABLE_THICKNESSES + [k * dz for k in (0.5, 1, 1.5, 2, 3, 5, 10, 15)] + list(rng.uniform(0, 20, 3))
    cases = [(n, thick) for n in (2, 3, 40, 400)] + [(2500, [0.3, 1.5, 12.37])]  # 2500: long rows
    for n, ts in cases:
        for rho_sq in _core_table_tables(rng, n):
            tol = 1e-12 * rho_sq.max()
            for t in ts:
                got, ref = core_radius_sq_table(rho_sq, dz, t), _core_table_by_rows(rho_sq, dz, t)
                assert got.shape == ref.shape
                assert np.abs(got - ref).max() <= tol, (n, t)
                assert np.all(((got > 0) == (ref > 0)) | (np.maximum(got, ref) <= tol)), (n, t)


def test_core_table_is_bitwise_the_per_pair_arithmetic():
    """The shifted slices give the numbers of interpolating r at every (row, offset) pair,
    f = j + (t + s) / dz, bit for bit (a difference of 1e-13 px once changed fits of ill-posed
    images, cda854e)."""
    rng = np.random.default_rng(3)
    rho_sq = np.cumsum(rng.uniform(0.0, 50.0, 60)) * (rng.random(60) > 0.1)
    n = rho_sq.size
    for dz, t in [(0.1, 0.3), (0.1, 1.5), (0.1, 12.37), (0.25, 1.0), (0.1234, 7.5), (0.1, 0.05)]:
        expect = []
        for j in range(n):
            best = math.inf
            for s in _disk_offsets(dz, t):
                f = min(j + (t + s) / dz, n - 1.0)
                i = min(int(f), n - 2)
                w = f - i
                r = math.sqrt(max(rho_sq[i] * (1.0 - w) + rho_sq[i + 1] * w, 0.0))
                best = min(best, r - math.sqrt(max(t * t - s * s, 0.0)))
            expect.append(max(best, 0.0) * max(best, 0.0))
        assert np.array_equal(core_radius_sq_table(rho_sq, dz, t), expect), (dz, t)


def test_projection_contrast_noise_free_profile():
    """Noise-free row through an uncoated, unrotated, unblurred tip matches exp(-2 sqrt(r^2-x^2)/lambda)."""
    px, n, Q, lam = 0.2e-9, 2.0, 10e-9, 40e-9
    img, t = render_tem_image(
        n,
        Q,
        px,
        shape=(160, 160),
        blur_sigma_px=0,
        edge_snr=None,
        rotation_deg=0,
        scale_bar=False,
        gradient=0.0,
        dtype=np.float64,
        supersample=9,
        lambda_core=lam,
    )
    r_a, c_a = t["apex_px"]
    row = int(r_a) - 40
    z = (r_a - row) * px
    x = (np.arange(160) - c_a) * px
    expect = np.exp(-chord(power_law_radius(z, n, Q), x) / lam) * t["background"]
    inner = np.abs(np.abs(x) - power_law_radius(z, n, Q)) > 2 * px  # away from the supersampled edge pixels
    assert np.allclose(img[row][inner], expect[inner], rtol=2e-3)


def test_edge_snr_definition():
    img, t = render_tem_image(2, 10e-9, 0.25e-9, shape=(256, 256), edge_snr=10, seed=2, noise="gaussian", gradient=0.0)
    bg = img[200:240, 180:250].astype(float)  # background below the apex, right of the scale bar
    assert bg.std() == pytest.approx(t["noise_sigma"], rel=0.15)


def test_tiff_roundtrip(tmp_path):
    img, t = render_tem_image(2, 10e-9, 0.3e-9, shape=(96, 96))
    p = tmp_path / "s.tif"
    write_tem_tiff(p, img, t["pixel_size"])
    im = read_tem_image(p)
    assert im.pixel_size == pytest.approx(0.3e-9, rel=1e-6)
    assert np.array_equal(im.data, img.astype(float))
