"""Global silhouette fit (``extract_profile(..., refine="global")``): accuracy vs truth."""

from __future__ import annotations

import numpy as np
import pytest

from pipeline.fits.profile_fit import fit_power_law
from pipeline.synth.tem_image import render_tem_image
from pipeline.synth.tem_truth import profile_errors
from pipeline.tem.profiles import extract_profile
from pipeline.tem.reading import TemImage

pytestmark = pytest.mark.filterwarnings("error")


def _fit_n(prof, px):
    r, z = prof.flank_rz("both")
    m = prof.z <= prof.profile_height
    groups = prof.flank[m][np.argsort(prof.z[m], kind="stable")]
    return fit_power_law(r, z, 6e-9, pixel_size=px, groups=groups).n


@pytest.mark.parametrize("coat", [0.0, 1.5e-9])
def test_clean_image_edge_within_0p02_nm(coat):
    n, px, R = 4.0, 0.25e-9, 20e-9
    img, truth = render_tem_image(
        n,
        R ** (n - 1),
        px,
        shape=(384, 384),
        blur_sigma_px=0.5,
        edge_snr=None,
        rotation_deg=-8.0,
        coating_thickness=coat,
        orientation="up",
        seed=3,
    )
    prof = extract_profile(TemImage(img.astype(np.float64), px, "synthetic"), refine="global")
    e = profile_errors(prof, truth, 6e-9)
    assert e["rms_normal"] < 0.02e-9
    # the coated model's own error (core erosion on a 0.1 px table, edge sub-samples) puts the
    # least-squares apex of this flat, coated face 0.034-0.045 nm off on two arithmetic paths
    # (uncoated 0.0003); with the core table on the outer grid it stopped at a jump of the
    # model (n 4.024 or 4.013 depending on the CPU's BLAS kernels)
    assert abs(e["apex_dz"]) < (0.08e-9 if coat else 0.02e-9)
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
            return render_tem_image(
                n,
                t.Q(n),
                t.pixel_size,
                shape=(512, 512),
                blur_sigma_px=t.blur_sigma_px,
                edge_snr=t.edge_snr,
                rotation_deg=rot,
                coating_thickness=t.coating,
                orientation="down",
                seed=seed,
                S=t.S,
                contamination=(i == len(t.n) - 1),
            )
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


def _ring_sum_chord(x, z, zm, r_edges):
    """Path length through the body of revolution {z >= zm(r)} along the beam at lateral
    x, height z: the sum over thin rings r_j..r_j+1 with zm <= z (independent of _Body)."""
    ra, rb = r_edges[:-1], r_edges[1:]
    inside = zm(0.5 * (ra + rb)) <= z
    seg = np.sqrt(np.maximum(rb**2 - x**2, 0)) - np.sqrt(np.maximum(ra**2 - x**2, 0))
    return 2.0 * np.sum(seg * inside)


def test_dimpled_face_projects_like_a_body_of_revolution():
    """A face with a central dimple (the meridian rises by ~0.6 px towards r = 0): the
    section is a disc minus a central hole, so the beam through the dimple loses the hole's
    chord.  Checked against a ring-sum integral of the same body of revolution."""
    from pipeline.tem.silhouette_fit import _Body

    def zm(r):
        r = np.abs(r)
        return np.where(r < 3, np.cos(np.pi * r / 6) ** 2, 0.0) + 0.05 * r**2

    x = np.linspace(-12, 12, 9601)
    body = _Body(x, zm(x), 0.0)
    assert len(body.holes) == 1  # the half that starts at the lowest point sees the dimple as a gap
    r_edges = np.linspace(0, 13, 26001)
    for xq, zq in [(0.0, 0.6), (0.0, 0.8), (1.0, 0.7), (-1.5, 0.55), (2.5, 0.9), (0.0, 1.5), (4.0, 1.2)]:
        t_ref = _ring_sum_chord(xq, zq, zm, r_edges)
        t, _ = body.chords(np.array([xq]), np.array([zq]))
        assert t[0] == pytest.approx(t_ref, abs=0.15), (xq, zq, t[0], t_ref)
    # the filled envelope (no hole) would put material where the dimple is
    filled = _ring_sum_chord(0.0, 0.7, lambda r: np.where(np.abs(r) < 2.6, zm(2.6), zm(r)), r_edges)
    t, _ = body.chords(np.array([0.0]), np.array([0.7]))
    assert filled - t[0] > 2.0


@pytest.mark.slow
def test_blunt_tip_power_index_unbiased_over_noise_seeds():
    """Flat faces under noise: the mean n over 12 seeds of a blunt DLC-coated tip (n 6,
    0.25 nm px, SNR 10) stays within 0.04 of the truth (a hard monotone constraint on the
    face gave -0.05, a filled envelope with no constraint +0.2)."""
    from pipeline.synth.tem_truth import evaluate_case

    dn = [
        evaluate_case(
            6.0,
            0.25e-9,
            1.0,
            10.0,
            [4.7, -3.1, 9.0, -11.0][s % 4],
            15e-9,
            seed=s,
            R=25e-9,
            orientation="up" if s % 2 else "down",
        )["dn"]
        for s in range(12)
    ]
    assert abs(np.mean(dn)) < 0.04, dn


@pytest.mark.slow
def test_sigma_n_matches_the_scatter_on_a_sharp_tip_at_coarse_pixels():
    """n 2, R 10 nm at 0.5 nm px, 2 px blur, SNR 10: the reported sigma_n (edge covariance
    from finite-difference shape columns) matches the scatter of n over 12 seeds within
    a factor 1.4 (the local-translation columns had given 0.6 x the scatter).  The tip is
    declared uncoated: at these pixels and blur the image cannot exclude a thin light layer,
    and "auto" widens sigma_n for that (tested in test_tem_profiles)."""
    from pipeline.synth.tem_truth import evaluate_case

    es = [
        evaluate_case(
            2.0,
            0.5e-9,
            2.0,
            10.0,
            [4.7, -3.1, 9.0, -11.0][s % 4],
            0.0,
            seed=s,
            R=10e-9,
            orientation="up" if s % 2 else "down",
            coating="none",
        )
        for s in range(12)
    ]
    sd = np.std([e["dn"] for e in es], ddof=1)
    sn = np.median([e["sigma_n"] for e in es])
    assert 1 / 1.4 < sd / sn < 1.4, (sd, sn)


def _fitter_at_solution(img, px, coating="auto"):
    """(fitter, state) of the final silhouette fit of ``img`` (captured from its polish step)."""
    import pipeline.tem.silhouette_fit as sf

    cap = {}
    orig = sf._Fitter.polish

    def polish(self, st, lb, ub, max_step):
        cap["fit"] = (self, st)
        return orig(self, st, lb, ub, max_step)

    sf._Fitter.polish = polish
    try:
        extract_profile(TemImage(img.astype(np.float64), px, "synthetic"), coating=coating)
    finally:
        sf._Fitter.polish = orig
    return cap["fit"]


@pytest.mark.parametrize("n,coat", [(2.0, 1.5e-9), (6.0, 0.0)])
def test_exact_jacobian_matches_one_knot_at_a_time(n, coat):
    """The shape columns of ``_Fitter.exact_jacobian`` (knots with disjoint height bands
    perturbed together, each pixel credited to the knot whose band holds its height) equal
    finite differences of one knot at a time, the independent reference, within 2 % per
    column (the nearest-point attribution it replaced was 50-240 % off near the apex)."""
    R = 10e-9 if n == 2 else 25e-9
    img, _ = render_tem_image(
        n,
        R ** (n - 1),
        0.25e-9,
        shape=(384, 384),
        blur_sigma_px=1.0,
        edge_snr=20.0,
        rotation_deg=4.0,
        coating_thickness=coat,
        seed=5,
    )
    f, st = _fitter_at_solution(img, 0.25e-9, coating="auto" if coat else "none")
    st, Jc, _, _ = f.exact_jacobian(st)
    p, K = f.p, f.K
    c, sigma, k_o, k_c, thick = f.unpack(st.v)
    M0 = st.B @ st.lin
    for k in range(0, K, 3):
        v = st.v.copy()
        v[k] += 0.05
        col = -(p.blurred(p.transmission(p.chords(v[:K], thick), k_o, k_c), sigma) @ st.lin - M0) * p.w / 0.05
        assert np.linalg.norm(Jc[:, k] - col) <= 0.02 * np.linalg.norm(col) + 1e-9, k
    assert f.n_groups < K  # and it costs fewer renderings than one per knot


def test_thin_oxide_on_a_blunt_tip_is_found_at_coarse_pixels():
    """Noise-free 1.5 nm light oxide on an n = 6 tip, 0.5 nm pixels, 2 px blur: the single-layer
    fit puts the edge ~0.9 nm inside (on the core) and shifted uniformly outwards it fits
    worse than without a layer (the flat face sees the layer through a longer chord than the
    flanks), so only the full-shape coated search finds it."""
    from pipeline.synth.tem_truth import evaluate_case

    e = evaluate_case(6.0, 0.5e-9, 2.0, np.inf, 7.0, 1.5e-9, seed=208)
    em = e["profile"].edge_model
    assert em["coating_test"]["model"] == "coated"
    assert em["coating_thickness"] == pytest.approx(1.5e-9, abs=0.1e-9)
    assert e["rms_normal"] < 0.03e-9 and abs(e["dn"]) < 0.05


def test_no_phantom_layer_on_a_flat_face():
    """Noise-free uncoated n = 6 tip, 0.5 nm pixels, 2 px blur: no layer is accepted (with 4 x 4
    sub-samples at the edge the model error on the flat face let a 0.8 nm phantom layer
    lower chi^2 by 592 and moved the edge 0.48 nm out)."""
    from pipeline.synth.tem_truth import evaluate_case

    e = evaluate_case(6.0, 0.5e-9, 2.0, np.inf, 7.0, 0.0, seed=207, orientation="up")
    assert e["profile"].edge_model["coating_test"]["model"] == "single"
    assert e["rms_normal"] < 0.03e-9 and abs(e["dn"]) < 0.05


def test_undecidable_layer_is_flagged_and_covered_by_the_reported_uncertainty():
    """1.5 nm light oxide, 0.5 nm pixels, 2 px blur, SNR 10: the image cannot say whether the
    layer is there (a layered fit changes chi^2 by less than the threshold either way).  The
    single-layer edge (~0.9 nm inside the true surface) is kept, flagged, and its covariance
    widened so that the reported uncertainty covers the error (here ~1.3 sd)."""
    from pipeline.synth.tem_truth import evaluate_case

    e = evaluate_case(3.0, 0.5e-9, 2.0, 10.0, 5.0, 1.5e-9, seed=2, R=15e-9)
    ct = e["profile"].edge_model["coating_test"]
    assert ct["model"] == "single" and ct["ambiguous"]
    assert any(f.startswith("coating ambiguous") for f in e["edge_flags"])
    u = e["reported"]
    assert e["rms_normal"] > 0.5e-9  # the layer is really missed
    assert e["rms_normal"] < 2.0 * u["edge_sd"]
    assert abs(e["dn"]) < 2.0 * u["sigma_n"] and e["force_err_max"] < 2.0 * u["sigma_force"]


@pytest.mark.slow
@pytest.mark.xfail(
    strict=True,
    reason="sigma_n over-reported since the flank-disagreement term (issue 16): median 0.0158 against a scatter "
    "of 0.0073 (2.2x; 1.6x allowed). On these images the two flanks' n differ by 0.03-0.04 with opposite signs "
    "(their errors cancel in the combined n), and the term counts the half-difference as independent error; "
    "passing the edge covariance to the per-flank fits brings it to 0.018-0.019 only. Measured (issue 16, B): "
    "the flank n errors correlate by -0.65, the edge covariance predicts -0.1..-0.3 (its axis tilt: 6e-5 rad), "
    "so every noise prediction leaves a 1.4-1.5x excess; a covariance-aware projection gives 1.9x, and a joint "
    "split fit (n +- dn) projected through smooth per-flank edge modes 1.93x but hides real flank n differences.",
)
def test_coated_fit_at_fine_pixels_is_precise_and_its_sigma_honest():
    """A 1.5 nm oxide at 0.1 nm pixels (fitted on 2 x 2 blocks), SNR 20, n 2: over 16 images
    (both orientations, four rotations) the SD of n is within 2x the Cramer-Rao bound (0.0053;
    measured 0.0071; the LM solution alone, short of the optimum, scattered 0.0154) and the
    reported sigma_n within a factor 1.6 of it (measured 0.0093). 16 images, not 8: the SD of
    8 draws scatters by +/-25 %, too much for a 2x bound on a 1.3x fit."""
    from pipeline.synth.tem_truth import evaluate_case

    rotations = [4.7, -3.1, 9.0, -11.0]
    es = [
        evaluate_case(
            2.0, 0.1e-9, 0.5, 20.0, rotations[s % 4], 1.5e-9, seed=400 + s, orientation="up" if s % 2 else "down"
        )
        for s in range(16)
    ]
    sd = np.std([e["dn"] for e in es], ddof=1)
    sn = np.median([e["sigma_n"] for e in es])
    assert sd < 2.0 * 0.0053, sd
    assert 1 / 1.6 < sn / sd < 1.6, (sn, sd)


def test_given_coating_thicker_than_the_fitted_band_fits_the_outer_layer_alone():
    """tem.coating: 15 nm (a DLC-coated tip at 0.25 nm px, 60 px): the core lies outside the
    pixels of the fit, so the outer layer is fitted alone (as with "auto"), with a note; a coated
    model clipped to the band had reported a 2 nm layer of no contrast, "not identifiable"."""
    from pipeline.synth.tem_truth import evaluate_case

    e = evaluate_case(5.4, 0.25e-9, 1.2, 15.0, 3.0, 15e-9, seed=3, R=30e-9, coating=15e-9)
    ct = e["profile"].edge_model["coating_test"]
    assert ct["model"] == "single" and "thicker than the fitted band" in ct["note"]
    # no flag but the layer filling the window's background (2.8 % here), flattened on the vacuum beyond it
    assert all("a faint layer filled it; the window is flattened on that vacuum" in f for f in e["edge_flags"])
    assert e["rms_normal"] < 0.06e-9 and abs(e["dn"]) < 0.05


def test_pixel_map_refresh_is_not_the_step_limit():
    """The pixel map is refreshed once the curve moved > MAP_REFRESH_PX; an LM step at its limit
    moves it by exactly the limit (up to rounding).  With the two equal, rounding decided whether
    the map was refreshed and the fit's path followed (bench_tem_path_dependence: 81 of 120 images
    moved with the window 1e-12 off, 31 by > 0.1 in n).  A full step must refresh it."""
    from pipeline.tem.silhouette_fit import _bounds
    from pipeline.tem.silhouette_model import MAP_REFRESH_PX

    for coated in (False, True):
        _, _, max_step = _bounds(10, 0.02, 12.0, coated)
        assert MAP_REFRESH_PX < 0.9 * max_step[:10].min()


def test_axis_attenuation_rows_do_not_hang_on_rounding():
    """The start of the attenuation (``_axis_attenuation``: a median over the table rows 6-30 px above
    the apex) is the same for the same body wherever it sits: 6 and 30 px lie on the table's 0.1 px
    grid, and compared as heights the row at 6 px read 6.0 or 6.000000000000002 by the rounding of
    the apex height, so it was in or out of the median (0.28 % apart over these 40 positions; on the
    defocused wave test image the two arithmetic paths started the fit from k 0.15 % apart and ended
    46 apart in chi^2)."""
    from pipeline.tem.edges import TipFrame
    from pipeline.tem.silhouette_model import _axis_attenuation, reference_curve

    x = np.linspace(-40.0, 40.0, 801)
    frame = TipFrame(apex=np.array([300.0, 200.0]), angle=0.1)
    uniform = np.full((400, 400), 0.5)  # every row reads the same transmission: k depends on the rows only
    ks = [
        _axis_attenuation(uniform, frame, reference_curve((x, x**2 / 40.0 + o), smooth_px=0.0))
        for o in np.arange(40) * 0.0137
    ]
    assert np.ptp(ks) < 1e-12 * np.mean(ks)
