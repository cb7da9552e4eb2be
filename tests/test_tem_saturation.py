"""A saturated detector (the vacuum above full scale): clipped pixels are censored in the silhouette
fit and the noise is read from the unclipped ones (``edges.saturated_pixels``,
``edges.flatten_background``, ``silhouette_fit`` "Saturated detector"), tested on images of the
INDEPENDENT wave-optical simulator (``pipeline.synth.tem_wave``), which clips an over-exposed 16-bit
image at 65535 as a camera does."""

from __future__ import annotations

from unittest import mock

import numpy as np
import pytest


def _saturated_tip(seed, layer, background_level):
    """A clean wave-simulator tip (``wave_images.clean_tip``: in focus, SNR 20, 16 bit, R 12 nm) at
    0.3 nm px whose vacuum is ``background_level`` x full scale: (TemImage, truth)."""
    from wave_images import clean_tip

    image, truth, _ = clean_tip(seed, layer, 0.3e-9, 384, background_level=background_level)
    return image, truth


def test_clipped_plateau_is_found_and_the_noise_read_beside_it():
    """A plateau at the maximum is the clipped part; an image that only touches its maximum in a few
    pixels (or a float image) is not saturated; the noise at the flattened level 1 is read from the
    unclipped pairs (Poisson: sd ~ sqrt(level)) within 5 % where the vacuum is clipped."""
    from pipeline.tem.edges import flatten_background, saturated_pixels

    rng = np.random.default_rng(3)
    H, W = 200, 240
    cols = np.arange(W)[None, :]
    level = np.where(cols < 120, 1.2, 0.3 + 0.4 * (cols - 120) / 120.0) * np.ones((H, 1))  # vacuum | tip
    noise = 0.02  # at level 1
    img = level + noise * np.sqrt(level) * rng.standard_normal((H, W))
    clipped = np.minimum(img, 1.0)
    sat = saturated_pixels(clipped)
    assert sat is not None and sat[:, :110].mean() > 0.99 and not sat[:, 130:].any()
    assert saturated_pixels(img) is None  # a float image: its maximum is one pixel
    few = img.copy()
    few.flat[:20] = few.max()
    assert saturated_pixels(few) is None
    _, est = flatten_background(clipped, sat)
    assert est == pytest.approx(noise, rel=0.05)
    _, plain = flatten_background(clipped)
    assert plain < 0.1 * noise  # read on the plateau, the noise vanishes: what the fit had before


def test_a_quantised_noise_tail_is_not_a_plateau():
    """An 8-bit vacuum at 0.7 x full scale with 0.5 DN of noise holds its maximum grey level in ~1 %
    of the pixels, but fewer than at the level below: not clipped (it was taken for saturation by
    the fraction alone).  The same vacuum at 1.02 x full scale is."""
    from pipeline.tem.edges import saturated_pixels

    rng = np.random.default_rng(0)
    cols = np.arange(300)[None, :]
    level = np.where(cols < 120, 0.3, 1.0) * np.ones((300, 1))
    for vac, clipped in ((0.7, False), (1.02, True)):
        img = np.clip(np.round(255 * vac * level + 0.5 * np.sqrt(level) * rng.standard_normal((300, 300))), 0, 255)
        assert (saturated_pixels(img) is not None) is clipped, vac


def test_noise_beside_a_nearly_opaque_tip():
    """A clipped vacuum (1.3 x full scale) and a tip transmitting 0-3 %: what is neither clipped nor
    dark lies on the edge.  The noise is still read within 1.4x (pair differences there read the
    edge's slope, 10-28x too high)."""
    from scipy import ndimage

    from pipeline.tem.edges import flatten_background, saturated_pixels

    rng = np.random.default_rng(7)
    R, C = np.mgrid[0:200, 0:200].astype(float)
    inside = R < 150 - (C - 100) ** 2 / 60
    for core in (0.0, 0.03):
        for blur in (1.0, 2.0):
            lv = ndimage.gaussian_filter(np.where(inside, 1.3 * core, 1.3), blur)
            img = np.clip(np.round(255 * (lv + 0.02 * np.sqrt(lv) * rng.standard_normal(lv.shape))), 0, 255)
            _, est = flatten_background(img, saturated_pixels(img))
            assert 0.7 < est / 0.02 < 1.4, (core, blur, est)


def test_illumination_minimises_the_censored_residual():
    """``_Problem.linear`` with censored pixels: the censored residual (value - model where the model is
    below a censored value, 0 above) is at its minimum over the illumination (no perturbation of it
    lowers the sum of squares), and ``n_data`` counts every pixel but the censored ones above."""
    from types import SimpleNamespace

    from pipeline.tem.silhouette_model import _Problem

    rng = np.random.default_rng(2)
    n = 4000
    B = np.column_stack([rng.uniform(0.3, 1.0, n), rng.uniform(-0.5, 0.5, n), rng.uniform(-0.5, 0.5, n)])
    B[:, 1:] *= B[:, :1]
    truth = np.array([1.15, 0.05, -0.03])
    I = B @ truth + 0.01 * rng.standard_normal(n)
    cens = I >= 1.0
    I = np.minimum(I, 1.0)
    p = SimpleNamespace(w=np.full(n, 100.0), I=I, cens=cens, idx=np.arange(n))
    lin = _Problem.linear(p, B)

    def cost(v):
        r = (I - _Problem.model(p, B, v)) * p.w
        return float(r @ r)

    c0 = cost(lin)
    for d in np.vstack([np.eye(3), -np.eye(3)]) * 1e-4:
        assert cost(lin + d) >= c0 - 1e-9 * c0
    assert np.allclose(lin, truth, atol=0.01)
    assert _Problem.n_data(p, B, lin) == int(np.count_nonzero(~cens | (B @ lin < I)))


def test_over_exposed_uncoated_tip_keeps_its_edge():
    """Vacuum 1.1 and 1.15 x full scale (46-58 % of the image clipped): the censored fit puts the edge
    within 0.35 nm of the true silhouette (bias, and RMS within 0.4 nm, in the 6 nm window; measured
    -0.02 and +0.24 nm; the clipped pixels fitted as data put it 0.13 and 1.18 nm inside), and the
    words say the detector saturated."""
    from pipeline.synth.tem_wave_truth import edge_errors
    from pipeline.tem.profiles import extract_profile

    for seed, bg in ((7, 1.1), (11, 1.15)):
        image, truth = _saturated_tip(seed, "none", bg)
        prof = extract_profile(image)
        e = edge_errors(prof.edge_px, truth, prof.z <= 6e-9)
        assert abs(e["bias"]) < 0.35e-9 and e["rms"] < 0.4e-9, (seed, e)
        words = [f for f in prof.edge_model["global_flags"] if f.startswith("saturated detector")]
        assert words and "fitted as lower bounds" in words[0] and "vacuum beside the edge is clipped" in words[0]


def test_unsaturated_image_is_fitted_as_before():
    """The same tip at 0.8 x full scale: no pixel is censored, the fit is the one without censoring
    (the same numbers) and no saturation words."""
    from pipeline.tem.profiles import extract_profile

    image, _ = _saturated_tip(7, "none", 0.8)
    prof = extract_profile(image)
    with mock.patch("pipeline.tem.profiles.saturated_pixels", lambda win: None):
        plain = extract_profile(image)
    assert np.array_equal(prof.edge_px, plain.edge_px)
    assert not [f for f in prof.edge_model["global_flags"] if f.startswith("saturated detector")]


def test_saturation_term_widens_the_edge_covariance():
    """Where the vacuum beside the edge is clipped, a light layer or the tip's rim brighter than full
    scale is not in the image: the edge covariance gets a common offset of SATURATED_EDGE_SD_NM
    (its variance, in m^2, added to every entry of the edge's offset covariance)."""
    from pipeline.tem.profiles import extract_profile
    from pipeline.tem.silhouette_fit import SATURATED_EDGE_SD_NM

    image, _ = _saturated_tip(11, "oxide", 1.1)
    with_term = extract_profile(image)
    with mock.patch("pipeline.tem.silhouette_fit.SATURATED_EDGE_SD_NM", 0.0):
        without = extract_profile(image)
    assert np.array_equal(with_term.edge_px, without.edge_px)
    added = with_term.offset_cov - without.offset_cov
    assert np.allclose(added, (SATURATED_EDGE_SD_NM * 1e-9) ** 2, rtol=1e-6)
