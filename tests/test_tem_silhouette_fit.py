"""Global silhouette fit (``extract_profile(..., refine="global")``): accuracy vs truth."""
from __future__ import annotations

import numpy as np
import pytest

from pipeline.fits import fit_power_law
from pipeline.synth.tem_image import render_tem_image
from pipeline.tem.profiles import extract_profile
from pipeline.tem.reading import TemImage
from pipeline.tem.truth import profile_errors

pytestmark = pytest.mark.filterwarnings("error")


def _fit_n(prof, px):
    r, z = prof.flank_rz("both")
    m = prof.z <= prof.profile_height
    groups = prof.flank[m][np.argsort(prof.z[m], kind="stable")]
    return fit_power_law(r, z, 6e-9, pixel_size=px, groups=groups).n


@pytest.mark.parametrize("coat", [0.0, 1.5e-9])
def test_clean_image_edge_within_0p02_nm(coat):
    n, px, R = 4.0, 0.25e-9, 20e-9
    img, truth = render_tem_image(n, R ** (n - 1), px, shape=(384, 384), blur_sigma_px=0.5, edge_snr=None,
                                  rotation_deg=-8.0, coating_thickness=coat, orientation="up", seed=3)
    prof = extract_profile(TemImage(img.astype(np.float64), px, "synthetic"), refine="global")
    e = profile_errors(prof, truth, 6e-9)
    assert e["rms_normal"] < 0.02e-9
    assert abs(e["apex_dz"]) < 0.02e-9
    assert abs(_fit_n(prof, px) - n) < 0.02
    em = prof.edge_model
    assert em["refine"] == "global" and em["global_n_pixels"] > 1000
    assert (prof.flank < 0).any() and (prof.flank > 0).any()
    if coat:
        assert em["coating_thickness"] == pytest.approx(coat, abs=0.05e-9)


def _tip_b_image(index):
    """Sample tip B interval ``index`` exactly as ``wear_test.generate_tip`` draws it
    (same as benchmarks/bench_profiles.py tip_b_images)."""
    from pipeline.synth.wear_test import sample_tips

    t = sample_tips()[1]
    rng = np.random.default_rng(t.seed)
    for i, n in enumerate(t.n):
        rot = t.rotation_deg + rng.normal(0, 0.5)
        seed = int(rng.integers(2**31))
        if i == index:
            return render_tem_image(n, t.Q(n), t.pixel_size, shape=(512, 512), blur_sigma_px=t.blur_sigma_px,
                                    edge_snr=t.edge_snr, rotation_deg=rot, coating_thickness=t.coating,
                                    orientation="down", seed=seed, S=t.S, contamination=(i == len(t.n) - 1))
        rng.standard_normal(t.curves_per_interval)
        for _ in range(t.curves_per_interval):
            rng.integers(2**31), rng.normal(0.0, 0.05), rng.normal(0.0, 2e5)
    raise IndexError(index)


def test_tip_b_flat_tip_power_index_closer_than_per_normal_path():
    img, truth = _tip_b_image(4)
    assert truth["n"] == pytest.approx(5.8)
    px = truth["pixel_size"]
    im = TemImage(img.astype(np.float64), px, "synthetic")
    old = extract_profile(im, refine="normals")
    new = extract_profile(im, refine="global")
    dn_old = abs(_fit_n(old, px) - truth["n"])
    dn_new = abs(_fit_n(new, px) - truth["n"])
    assert dn_new < dn_old
    assert profile_errors(new, truth, 6e-9)["rms_normal"] < profile_errors(old, truth, 6e-9)["rms_normal"]
    assert profile_errors(new, truth, 6e-9)["rms_normal"] < 0.1e-9


def test_refine_option_is_validated():
    img, _ = render_tem_image(3.0, 15e-9**2, 0.3e-9, shape=(128, 128), edge_snr=None, seed=1)
    with pytest.raises(ValueError, match="refine"):
        extract_profile(TemImage(img.astype(np.float64), 0.3e-9, "synthetic"), refine="bogus")
