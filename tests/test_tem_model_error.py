"""The edge model's error (``pipeline.tem.model_error``): a smooth edge offset that grows with the misfit
of the Beer-Lambert model. Its part common to both flanks is in stage 1's edge covariance (so that the
covariance covers the edge's real error on images the model does not render), the rest in stage 2's;
none where the model fits to the noise."""

import math

import numpy as np
import pytest

from pipeline.fits.power_law import _systematic_cov
from pipeline.tem.model_error import EDGE_SYSTEMATIC_PX, LAYER_SD, common_offset_sd_px, misfit_gain


def test_the_gain_allows_for_the_reduced_chi2s_own_noise_and_saturates():
    n = 5000  # the reduced chi^2 of a model-true image scatters by sqrt(2 / n) = 0.02
    assert misfit_gain(1.05, n) == 0.0 and misfit_gain(0.9, n) == 0.0
    assert misfit_gain(None, n) == 0.0 and misfit_gain(float("nan"), n) == 0.0
    allow = 3 * math.sqrt(2 / n)
    assert misfit_gain(1.25 + allow, n) == pytest.approx(0.5, rel=1e-12)
    assert misfit_gain(3.0, n) == misfit_gain(300.0, n) == 1.0


def test_the_common_offset_is_the_flanks_mean_plus_half_a_found_layer():
    assert common_offset_sd_px(300.0, 5000) == pytest.approx(EDGE_SYSTEMATIC_PX / math.sqrt(2))
    assert common_offset_sd_px(300.0, 5000, 2.0) == pytest.approx(
        math.hypot(EDGE_SYSTEMATIC_PX / math.sqrt(2), 2 * LAYER_SD)
    )
    assert common_offset_sd_px(1.0, 5000, 2.0) == 0.0


def test_stage_two_leaves_out_exactly_the_mode_stage_one_carries():
    """The per-flank constant offsets (independent, SD s each) are the same covariance as their
    difference plus a common offset of SD s / sqrt 2 (a rotation of the pair): stage 2's term without
    the common mode plus that common offset propagated through the same fit is its full term."""
    rng = np.random.default_rng(3)
    N = 80
    side = np.where(np.arange(N) < N // 2, -1, 1)
    t = rng.random(N)
    J = rng.normal(size=(N, 4))
    s = 0.7
    full = _systematic_cov(J, t, side, s)
    rest = _systematic_cov(J, t, side, s, common_in_edge=True)
    M = np.linalg.solve(J.T @ J, J.T @ np.ones(N))  # a common offset of the whole edge
    common = (s / math.sqrt(2)) ** 2 * np.outer(M, M)
    assert np.allclose(rest + common, full, rtol=1e-12, atol=1e-15)
    assert not np.allclose(rest, full)


def test_no_model_error_on_the_models_own_rendering():
    """A Beer-Lambert image (``synth.tem_image``, the fit's own physics): reduced chi^2 below 1, no
    term, no flag (the sigma_n tests on such images measure the noise alone)."""
    from pipeline.synth.tem_truth import evaluate_case

    e = evaluate_case(4.0, 0.25e-9, 1.0, 15.0, -3.1, 0.0, seed=0)
    assert e["profile"].edge_model["global_chi2_red"] < 1.0
    assert e["profile"].edge_model["global_model_error_px"] == 0.0
    assert not [f for f in e["edge_flags"] if f.startswith("edge model misfit")]


def test_a_light_layer_read_from_phase_contrast_is_covered(tmp_path):
    """Independent wave-optical image (grid image 60 of ``bench_tem_independent``: uncoated, 0.34 nm px,
    near focus): phase contrast at the edge reads as a light layer and moves the edge out. The edge's
    mean error is within 2 of its reported SD (noise alone: 0.01 nm against a 0.4 nm error), the flag
    says why, and the profile file carries the term for stage 2."""
    import h5py

    from pipeline.synth.tem_wave import draw_params, simulate, write_image
    from pipeline.synth.tem_wave_truth import evaluate_file
    from pipeline.tem.io import write_profile_h5
    from pipeline.tem.profiles import extract_profile
    from pipeline.tem.reading import read_tem_image

    p = draw_params(60, layer="none", apex_particles=False)
    img, truth = simulate(p)
    path = tmp_path / "tip.tif"
    write_image(str(path), img, p.pixel_size)
    g = evaluate_file(str(path), truth)
    assert not g["lost"]
    assert abs(g["edge_bias"]) <= 2.0 * g["edge_bias_sd"], (g["edge_bias"], g["edge_bias_sd"])
    assert any(f.startswith("edge model misfit") for f in g["edge_flags"])
    image = read_tem_image(str(path))
    prof = extract_profile(image)
    write_profile_h5(tmp_path / "p.h5", image, prof)
    with h5py.File(tmp_path / "p.h5") as f:
        sd = f["edge_model/model_error_offset_sd"]
        assert sd.attrs["units"] == "m"
        assert sd[()] == pytest.approx(prof.edge_model["global_model_error_px"] * p.pixel_size) and sd[()] > 0.1e-9
