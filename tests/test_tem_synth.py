"""Synthetic TEM image generator: determinism, exact outer profile, contrast physics, TIFF tags."""

from __future__ import annotations

import numpy as np
import pytest

from pipeline.synth.tem_image import outer_radius, power_law_radius, render_tem_image, write_tem_tiff
from pipeline.tem.projection import chord, eroded_radius
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
