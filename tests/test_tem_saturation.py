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


def test_over_exposed_uncoated_tip_keeps_its_edge():
    """Vacuum 1.1 and 1.15 x full scale (46-58 % of the image clipped): the censored fit puts the edge
    within 0.3 nm of the true silhouette (bias and RMS in the 6 nm window; the clipped pixels fitted
    as data put it 0.13 and 1.18 nm inside), and the words say the detector saturated."""
    from pipeline.synth.tem_wave_truth import edge_errors
    from pipeline.tem.profiles import extract_profile

    for seed, bg in ((7, 1.1), (11, 1.15)):
        image, truth = _saturated_tip(seed, "none", bg)
        prof = extract_profile(image)
        e = edge_errors(prof.edge_px, truth, prof.z <= 6e-9)
        assert abs(e["bias"]) < 0.3e-9 and e["rms"] < 0.35e-9, (seed, e)
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
