"""Defocus-fringe correction of the silhouette fit (``pipeline.tem.fringe_correction``) on an image of
the INDEPENDENT wave-optical simulator (``pipeline.synth.tem_wave``): an uncoated tip 1.5 um from
focus, whose Fresnel fringes put the Beer-Lambert edge 1.5 nm outside,
and the same tip in focus, where nothing may move."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest


def _profile(defocus, fringe_correction=True, defocus_given="auto"):
    from pipeline.synth.tem_wave import draw_params, simulate
    from pipeline.synth.tem_wave_truth import edge_errors
    from pipeline.tem.profiles import extract_profile
    from pipeline.tem.reading import TemImage

    p = draw_params(
        3,
        layer="none",
        apex_particles=False,
        shank_contamination=False,
        defocus=defocus,
        pixel_size=0.3e-9,
        snr=20.0,
        bits=16,
        shape=(320, 320),
        R=12e-9,
    )
    img, truth = simulate(p)
    image = TemImage(img.astype(float), p.pixel_size, "synthetic")
    prof = extract_profile(image, fringe_correction=fringe_correction, defocus=defocus_given)
    sel = (prof.z >= 0.0) & (prof.z <= 10e-9)
    err = edge_errors(prof.edge_px, truth, sel)
    return prof, err, truth, p


@pytest.fixture(scope="module")
def defocused():
    return _profile(-1.5e-6)  # Kirkland's sign: overfocus, the larger outward bias


def test_defocused_edge_is_moved_onto_the_true_silhouette(defocused):
    prof, err, truth, p = defocused
    flags = prof.edge_model["global_flags"]
    assert any(f.startswith("defocus fringes: edge moved") for f in flags), flags
    # uncorrected (main c558501): bias +1.48 nm, RMS 1.49 nm; corrected -0.19 / 0.26 nm
    assert abs(err["bias"]) < 0.4e-9, err["bias"]
    assert err["rms"] < 0.5e-9, err["rms"]


def test_fitted_defocus_is_the_simulated_one(defocused):
    prof, _, truth, p = defocused
    fr = prof.edge_model["global_fringe"]
    lam_df = fr["A_px2"] * p.pixel_size**2
    true = truth["optics"]["wavelength"] * p.defocus
    # the sign (over / underfocus) and the size within 40 % (pixel-centre sampling of the wave,
    # no Cs, aperture or detector tail in the rendering)
    assert np.sign(lam_df) == np.sign(true)
    assert abs(lam_df / true - 1.0) < 0.4, (lam_df, true)
    # the offset's standard error is part of the edge covariance, and so is its model error, half the move
    assert 0.0 < fr["offset_sd_px"] < 0.3
    assert fr["model_sd_px"] == pytest.approx(0.5 * abs(fr["offset_px"]), rel=1e-12)
    from pipeline.synth.tem_wave_truth import common_offset_sd

    sel = (prof.z >= 0.0) & (prof.z <= 6e-9)
    assert common_offset_sd(prof, sel) >= fr["model_sd_px"] * p.pixel_size


def test_in_focus_edge_is_not_moved():
    # (its Beer-Lambert edge lies 0.71 nm inside, on main too: not a fringe, left alone here)
    prof, err, _, p = _profile(0.0)
    fr = prof.edge_model.get("global_fringe") or {}
    moved = fr["offset_px"] * p.pixel_size if fr.get("applied") else 0.0
    assert abs(moved) < 0.03e-9, fr


def test_switched_off_keeps_the_beer_lambert_edge(defocused):
    """``tem.fringe_correction: false``: no correction, the Beer-Lambert edge (1.5 nm out here),
    and the switch is the only difference: the corrected edge is the same curve moved by the
    correction's move (its uniform offset, then its shape refitted: ``fringe_shape``)."""
    prof, err, _, p = _profile(-1.5e-6, fringe_correction=False)
    assert not prof.edge_model.get("global_fringe")
    assert not any(f.startswith("defocus fringes") for f in prof.edge_model["global_flags"])
    assert err["bias"] > 1.0e-9, err["bias"]
    on = defocused[0]
    fr = on.edge_model["global_fringe"]
    sel = (on.z >= 0.0) & (on.z <= 10e-9)  # the points ``_profile`` grades
    moved = float(np.mean(np.asarray(on.offset_basis)[sel] @ np.asarray(fr["shape_move_px"]))) * p.pixel_size
    assert abs(np.mean(fr["shape_move_px"]) - fr["offset_px"]) * p.pixel_size < 0.3e-9  # the shape's part is small
    assert abs((defocused[1]["bias"] - err["bias"]) - moved) < 0.03e-9


def test_switch_is_in_the_tip_schema(tmp_path, monkeypatch):
    """The tip YAML's ``tem.fringe_correction`` defaults to true and must be a boolean."""
    from pipeline.config import ConfigError, load_tip_config

    root = Path(__file__).resolve().parents[1]
    monkeypatch.chdir(root)  # the YAML's data_dir is relative to where snakemake runs
    src = (root / "config" / "tips" / "tipB_Si.yaml").read_text()
    ok = tmp_path / "t.yaml"
    ok.write_text(src)
    assert load_tip_config(ok)["tem"]["fringe_correction"] is True
    bad = tmp_path / "bad.yaml"
    bad.write_text(src.replace("tem:", "tem:\n  fringe_correction: maybe", 1))
    with pytest.raises(ConfigError, match="fringe_correction"):
        load_tip_config(bad)


def test_offset_error_is_finite_where_the_phase_is_not_determined():
    """In focus (A ~ 0) the phase column of J^T J is zero: the offset's standard error is taken over
    the determined parameters (the reduced block's inverse), not NaN (which made the whole edge
    covariance NaN on 10 of the 120 grid images); an undetermined offset gives NaN."""
    from pipeline.tem.fringe_correction import _offset_sd

    rng = np.random.default_rng(1)
    J = rng.normal(size=(200, 4))
    J[:, 2] = 0.0  # ln eta: no effect without propagation
    JTJ = J.T @ J
    keep = [0, 1, 3]
    expect = np.sqrt(np.linalg.inv(JTJ[np.ix_(keep, keep)])[0, 0] * 2.0)
    assert _offset_sd(JTJ, 2.0) == pytest.approx(expect, rel=1e-12)
    J[:, 0] = 0.0
    assert np.isnan(_offset_sd(J.T @ J, 2.0))


def _knife_edge(x, A, tau, x0):
    """Closed-form intensity of a half-plane of transmission ``tau`` (x < x0; vacuum beyond)
    propagated with the kernel exp(i pi A f^2) (f cycles/px): the field of the open half
    (1 + i)/2 [(C(w) + 1/2) - i (S(w) + 1/2)], w = (x - x0) sqrt(2 / A), Fresnel integrals C, S;
    its complex conjugate for A < 0."""
    from scipy.special import fresnel

    S, C = fresnel((x - x0) * np.sqrt(2.0 / abs(A)))
    U = (1 + 1j) / 2 * ((C + 0.5) - 1j * (S + 0.5))
    U = U if A > 0 else np.conj(U)
    return np.abs(tau + (1 - tau) * U) ** 2


@pytest.mark.parametrize("sigma", [0.3, 0.6])
@pytest.mark.parametrize("A", [-150.0, -60.0, -20.0, -5.0, -2.0, 2.0, 5.0, 20.0, 60.0, 150.0])
def test_edge_profile_model_is_the_fresnel_knife_edge(A, sigma):
    """The 1-D model that screens the starts (``_profile_model``) against the closed-form Fresnel
    knife edge of a slab with absorption and phase (amplitude e^-0.5, phase 1 rad), both blurred by
    the same Gaussian (the closed form on a 1/64 px grid), where the fringes are resolved (|x| <= |A|
    px: local fringe frequency <= 1 cycle/px).  Measured: within 0.008; the other sign of the
    defocus differs by 0.18-0.49, so the test sees a sign error.  |A| = 150 px^2 (2 um at 0.2 nm px)
    needs the model's padding to grow with |A| (a fixed 64 px was 0.13 off at 138 px^2)."""
    from scipy.ndimage import gaussian_filter1d

    from pipeline.tem.fringe_correction import _profile_model

    d = np.arange(-30.0, 30.0 + 1e-9, 0.25)  # bins (px, outward +); the 1-D model samples 4 / px
    kt, t_o = np.where(d <= 0, 1.0, 0.0), np.where(d <= 0, 10.0, 0.0)
    tau = np.exp(-0.5 + 1j * 0.1 * 10.0)
    xf = np.arange(-80.0, 80.0, 1.0 / 64)
    sel = np.abs(d) <= min(20.0, abs(A))
    for delta in (0.0, 1.0):
        model = _profile_model(np.array([delta, A, 0.0, 0.0]), d, kt, t_o, 0.1, sigma)
        # the sampled edge lies between the samples at 0 and 0.25 px (+ delta)
        ref = np.interp(d, xf, gaussian_filter1d(_knife_edge(xf, A, tau, 0.125 + delta), sigma * 64))
        assert np.max(np.abs(model - ref)[sel]) < 0.015


@pytest.fixture(scope="module")
def fitted_problem():
    """(prob, fitter, st, pixel_size) as ``fringe_offset`` receives them on the defocused test image
    (its vacuum is clipped: about half of the fitted pixels are censored)."""
    import pipeline.tem.silhouette_fit as sf

    captured = {}
    original = sf.fringe_offset

    def grab(prob, fitter, st, pixel_size, **kw):
        captured["args"] = (prob, fitter, st, pixel_size)
        return original(prob, fitter, st, pixel_size, **kw)

    with pytest.MonkeyPatch.context() as mp:
        mp.setattr(sf, "fringe_offset", grab)
        _profile(-1.5e-6)
    return captured["args"]


def test_coherent_model_is_a_function_of_its_parameters(fitted_problem):
    """The coherent model at an offset is the same whatever offsets were evaluated before: its
    supersampled pixels come from the fitted curve's own map (``_Problem.offset_map``).  A map
    refreshed along the optimiser's path (at 1.2 px, then kept for 1.6 px) made the model, so the
    fitted offset, depend on the path (grid image 106 moved n by 1.79 under a 1e-12 change of the
    image)."""
    from pipeline.tem.fringe_correction import _Coherent

    q = np.array([1.6, -30.0, 0.0, 0.0, 0.1])
    fresh = _Coherent(*fitted_problem).residual(q)
    co = _Coherent(*fitted_problem)
    for delta in (-6.0, 3.0, 1.2):
        co.residual(np.array([delta, -30.0, 0.0, 0.0, 0.1 * delta]))
    assert np.array_equal(co.residual(q), fresh)


def test_the_held_layer_screen_starts_at_the_correction_s_solution(fitted_problem):
    """``held_layer``'s start is the one-material correction's solution in ``_Coherent``'s parameters:
    the correction started there alone (``fringe_offset(start=...)``, no screen of starts) stays at its
    chi^2 and offset."""
    from pipeline.tem.fringe_correction import fringe_offset
    from pipeline.tem.held_layer import _start

    prob, fitter, st, pixel_size = fitted_problem
    fr = fringe_offset(prob, fitter, st, pixel_size)
    q = _start(fr, fitter.unpack(st.v)[1], pixel_size)
    there = fringe_offset(prob, fitter, st, pixel_size, iters=0, start=q)  # no step: the start itself
    for key in ("chi2", "offset_px", "A_px2", "eta", "sigma_px", "attenuation_scale"):
        assert there[key] == pytest.approx(fr[key], rel=1e-9, abs=1e-12), key
    again = fringe_offset(prob, fitter, st, pixel_size, start=q)
    assert again["chi2"] <= fr["chi2"] * (1 + 1e-6), (again["chi2"], fr["chi2"])
    # the correction stops where chi^2 falls by < 1e-4 of itself per step; continued, the offset moved 0.046 px
    # (0.014 nm, 2 % of the correction's model SD): within 0.1 px, far inside the edge's 0.15 nm
    assert abs(again["offset_px"] - fr["offset_px"]) < 0.1, (again["offset_px"], fr["offset_px"])
    assert abs(again["offset_px"] - fr["offset_px"]) < 0.1 * fr["model_sd_px"]
    assert abs(again["A_px2"] - fr["A_px2"]) < 0.1 * abs(fr["A_px2"]), (again["A_px2"], fr["A_px2"])  # 4 %


def test_a_layer_that_beats_only_a_poorly_converged_one_material_fit_is_not_taken(fitted_problem):
    """On the uncoated defocused tip, told that the one-material correction ended at 3 x its chi^2 (as an
    uncoated end-to-end interval's did, in a poor basin of the fringes, on one thread): the best held
    layer beats that, but one material refitted from where the layer's fit ended beats the layer, so
    none is taken (``held_layer``, "The same start for both")."""
    import pipeline.tem.held_layer as hl
    from pipeline.tem.silhouette_fit import _bounds

    prob, fitter, st, pixel_size = fitted_problem
    fr = hl.fringe_offset(prob, fitter, st, pixel_size)
    poor = dict(fr, chi2=3.0 * fr["chi2"])
    calls = []

    def spy(prob, fitter, *a, **k):
        out = hl_fringe_offset(prob, fitter, *a, **k)
        calls.append((fitter.coated, out["chi2"]))
        return out

    hl_fringe_offset = hl.fringe_offset
    with pytest.MonkeyPatch.context() as mp:
        mp.setattr(hl, "fringe_offset", spy)
        alt = hl.held_layer(prob, fitter, st, poor, pixel_size, _bounds(prob.K, 0.02, 12.0, True))
    assert [coated for coated, _ in calls] == [True, False], calls  # the layer passed the first gate
    assert calls[0][1] < 0.9 * poor["chi2"], calls
    assert alt is None
    assert calls[1][1] < calls[0][1], calls  # one material, refitted, fits better than the layer


def test_a_held_layer_not_taken_changes_nothing(defocused):
    """On the uncoated defocused tip the held layers are tried (the one-material fit's correction is
    applied) and none is taken; the profile is then the same to the bit as with none tried (the problem's
    pixel map is put back, ``_Problem.restore_map``, and what follows maps afresh anyway)."""
    import pipeline.tem.silhouette_fit as sf

    prof, _, _, _ = defocused
    assert not any("seen by the coherent rendering" in f for f in prof.edge_model["global_flags"])
    calls = []
    with pytest.MonkeyPatch.context() as mp:
        mp.setattr(sf, "held_layer", lambda *a, **k: calls.append(1))
        untried, _, _, _ = _profile(-1.5e-6)
    assert calls, "the held layers were not tried"
    assert np.array_equal(untried.edge_px, prof.edge_px)
    assert np.array_equal(untried.z, prof.z)


def test_the_exit_wave_is_the_simulator_s_for_a_core_in_a_layer():
    """The rendering's exit wave of a coated body, phi = eta t_outer + (eta_c - eta) t_core, is the
    wave-optical simulator's sum over materials (``tem_wave._wave``: the core's chord at its own
    potential, the layer's, t_outer - t_core, at the layer's), to rounding; one material (eta_c = eta,
    t_core = t_outer) is exp(-k t / 2 + i eta t) exactly."""
    from types import SimpleNamespace

    from pipeline.synth.tem_wave import _wave
    from pipeline.tem.fringe_correction import CORE_PHASE_RATIO, _exit_wave

    rng = np.random.default_rng(7)
    t_o = rng.uniform(0.0, 80.0, 500)
    t_c = t_o * rng.uniform(0.0, 1.0, 500)  # the core's chord lies within the outer one
    k_o, k_c, eta = 0.004, 0.03, 0.02
    eta_c = CORE_PHASE_RATIO * eta
    pot, lam_abs = {"Si": eta_c, "SiO2": eta}, {"Si": 1.0 / k_c, "SiO2": 1.0 / k_o}
    sim = _wave({"core": t_c, "layer": t_o - t_c}, pot, lam_abs, 1.0, SimpleNamespace(layer="oxide"))
    np.testing.assert_allclose(_exit_wave(t_o, t_c, k_o, k_c, eta, eta_c), sim, rtol=0, atol=1e-12)
    one = _exit_wave(t_o, t_o, k_c, k_c, eta, eta)
    assert np.array_equal(one, np.exp(-0.5 * (k_c * t_o) + 1j * (eta * t_o)))


def test_edge_profile_keeps_the_body_where_the_vacuum_is_clipped(fitted_problem):
    """The 1-D screen's body profile comes from every fitted pixel (chords do not depend on the data),
    its data from the unclipped ones only.  Built from the unclipped pixels alone, the body stopped
    inside the material (the clipped vacuum beside the edge), and the 1-D model jumped every 0.25 px
    of offset.  With too few bins of data, the screen ranks the starts themselves."""
    import pipeline.tem.fringe_correction as fc
    from pipeline.tem.fringe_correction import _Coherent, _edge_profile, _screened_starts

    prob, fitter, st, px = fitted_problem
    co = _Coherent(*fitted_problem)
    dg, kt, t_o, dd, y, se = _edge_profile(prob, co, st)
    assert dg.max() > 3.0 and kt[-1] == 0.0 and t_o[-1] == 0.0  # into the vacuum
    assert kt[0] > 0.1  # and into the material (attenuation x chord 0.19 at the inner end)
    assert dd.max() < 0.0  # the clipped vacuum gives no data
    assert np.all(se > 0) and np.all(np.isfinite(y))
    starts = [np.zeros(5), np.array([-5.0, -40.0, 0.0, 0.0, 0.0]), np.array([-1.2, 16.0, 0.0, 0.0, 0.0])]
    with pytest.MonkeyPatch.context() as mp:  # as if too few bins held data
        mp.setattr(fc, "SCREEN_MIN_BINS", 10**6)
        assert _edge_profile(prob, co, st) is None
        kept = _screened_starts(prob, st, co, starts, 66.0)
    # the two best and the best of the sign they lack (``_with_each_sign``): here all three starts
    assert len(kept) == 3 and all(any(np.array_equal(k, q) for q in starts) for k in kept)


def _graded(tmp_path, p, **kw):
    """The independent wave-optical image of ``p`` through the stage (``kw``: ``evaluate_file``'s, e.g.
    ``defocus``), graded against its true silhouette (``wave_images.graded_wave_image``), and the
    correction's flag."""
    from wave_images import graded_wave_image

    g = graded_wave_image(tmp_path, p, **kw)
    return g, [f for f in g["edge_flags"] if f.startswith("defocus fringes: edge moved")]


def test_a_slight_overfocus_at_fine_pixels_is_found(tmp_path):
    """Held-out image 51 (``bench_tem_independent --seed0 1000``, its parameters exactly): uncoated,
    87 nm overfocus at 0.118 nm px (lambda df = -18 px^2).  The starts of the defocus used to be no
    smaller than 8 % of the largest (34 px^2 here): from none of them did the 1-D screen reach this
    basin, the correction returned to A ~ 0 and the edge stayed 0.32 nm outside at an SD of 0.08 nm.
    With starts from 2 % of the largest it is found.  (Which basin a start reaches is a matter of
    its neighbourhood: with the parameters rounded to 5 digits the old starts reach it too.  On the
    260 images of the three benchmark sets the finer starts moved 4 edges by more than 0.05 nm, all
    closer to the truth.)"""
    from pipeline.synth.tem_wave import ParticleSpec, TemWaveParams

    parts = (
        ParticleSpec(
            1.3195889069221033e-08, 193.26630524339805,
            (2.150559466293252e-09, 1.4172346590607874e-09, 1.5274307368276645e-09), 0.5135859877538752,
            9.5036390474027, "apex",
        ),
        ParticleSpec(
            8.662421283898741e-08, 161.66402679359192,
            (9.755605296706238e-09, 9.142387485669894e-09, 5.527863492126111e-09), 0.5, 0.0, "shank",
        ),
        ParticleSpec(
            3.270252684489766e-08, 206.53949906273942,
            (8.879425318492262e-09, 6.367790574485504e-09, 7.977508472536845e-09), 0.5, 0.0, "shank",
        ),
        ParticleSpec(
            4.816190816593559e-08, 174.3160472194205,
            (7.829407429783178e-09, 1.0316956294144193e-08, 4.561454830732741e-09), 0.5, 0.0, "shank",
        ),
    )  # fmt: skip
    p = TemWaveParams(
        n=5.084334048530689, R=1.336718441420709e-08, S=1.1948495256392322, z_join=1.2153003275467566e-08,
        shank_half_angle_deg=20.741914280021852, blend_length=2.5248496255609438e-08,
        asymmetry=-0.044711454246073985, layer="none", layer_thickness=0.0,
        core_absorption_length_200kv=2.6604864060860537e-08, layer_contrast=0.2,
        contamination_contrast=0.2569757982828149, particles=parts, pixel_size=1.1845296570480564e-10,
        shape=(1024, 1024), apex_px=(355.76539155476405, 547.8332330524252), rotation_deg=8.86678988843138,
        orientation="up", kv=147.9519698282035, defocus=-8.656223022692319e-08, cs=0.0010966627867855195,
        aperture=0.006782093617173482, illumination_angle=0.00023290898935297347, cc=0.0012408883591431491,
        energy_spread_ev=0.3771175819036949, snr=27.796974742077207, bits=16, background_level=0.5650379299255658,
        float_gain=15.779610526055981, offset=12.914115526452974, read_noise=5.884059358641107,
        psf_sigma=0.5481937102637796, psf_tail_weight=0.05409880651916577, psf_tail_length=4.5835964871638035,
        illumination_gradient=0.028394705964453006, gradient_angle_deg=260.2796928031899,
        vignetting=0.08821306088619113, seed=1051,
    )  # fmt: skip
    g, flag = _graded(tmp_path, p)
    assert not g["lost"], g["lost_reason"]
    assert flag and "lambda x defocus -0." in flag[0], flag  # -0.3 nm^2: overfocus, the true sign
    assert abs(g["edge_bias"]) < 0.1e-9, g["edge_bias"]  # 0.32 nm with the old starts; 0.01 nm now
    assert abs(g["edge_bias"]) <= 2 * g["edge_bias_sd"] and g["pulloff_covered_mc"]


def test_the_attenuation_follows_the_moved_edge(tmp_path):
    """Held-out image 27 (parameters to 5 digits): uncoated, 1.3 um overfocus, 0.194 nm px, three
    particles on one flank.  The fringes put the Beer-Lambert edge 1.7 nm outside.  Moving it with the
    fit's attenuations held changed every chord inside, and the illumination took the difference: the
    offset stopped 0.21 nm short.  With the attenuations' common scale g fitted along with it, the
    edge lay within 0.1 nm of the true silhouette; with the shape refitted and the exit wave averaged
    over the pixel it lies 0.22 nm outside, n within 0.04 and the pull-off within 4 %."""
    from pipeline.synth.tem_wave import ParticleSpec, TemWaveParams

    parts = (
        ParticleSpec(1.0158e-08, 171.82, (1.4394e-09, 2.0943e-09, 1.7177e-09), 0.79697, 27.712, "apex"),
        ParticleSpec(1.1424e-08, 168.83, (1.4949e-09, 9.0162e-10, 1.3349e-09), 0.55201, 177.85, "apex"),
        ParticleSpec(1.9298e-08, 163.92, (1.9888e-09, 2.1341e-09, 2.2791e-09), 0.50459, 145.61, "apex"),
    )
    p = TemWaveParams(
        n=2.1119, R=2.3178e-08, S=1.5652, z_join=8.2533e-09, shank_half_angle_deg=23.587, blend_length=3.9757e-08,
        asymmetry=0.0, layer="none", core_absorption_length_200kv=5.3403e-08, contamination_contrast=0.2773,
        particles=parts, pixel_size=1.9418e-10, shape=(832, 832), apex_px=(604.7, 343.66), rotation_deg=9.1751,
        orientation="down", kv=288.0, defocus=-1.3185e-06, cs=0.0008258, aperture=0.0056261,
        illumination_angle=5.4677e-05, cc=0.0012649, energy_spread_ev=0.30189, snr=17.236, bits=16,
        background_level=1.1902, float_gain=17.369, offset=86.779, read_noise=2.9515, psf_sigma=0.4125,
        psf_tail_weight=0.078878, psf_tail_length=4.3778, illumination_gradient=0.058892, gradient_angle_deg=57.172,
        vignetting=0.015526, seed=1027,
    )  # fmt: skip
    g, flag = _graded(tmp_path, p)
    assert not g["lost"], g["lost_reason"]
    assert flag and "lambda x defocus -" in flag[0], flag  # overfocus, the true sign
    # -0.21 nm with g held; -0.07 nm with g fitted; +0.13 nm with the edge's shape refitted (``fringe_shape``),
    # which takes n from +0.19 to +0.04 and the pull-off error from +17 % to +4 %; +0.22 nm with the exit
    # wave averaged over the pixel (n +0.03, pull-off +3.5 %)
    assert abs(g["edge_bias"]) < 0.25e-9, g["edge_bias"]  # 0.222 / 0.223 / 0.222 nm on the three arithmetic paths
    assert abs(g["dn"]) < 0.1 and abs(g["pulloff_error"]) < 0.06, (g["dn"], g["pulloff_error"])
    assert abs(g["edge_bias"]) <= 2 * g["edge_bias_sd"] and g["n_covered"] and g["pulloff_covered_mc"]


def _grid_119():
    """Grid image 119 of ``bench_tem_independent``, its parameters exactly: a 4.4 nm DLC layer of 27 %
    contrast, 121 nm underfocus, 0.345 nm px."""
    from pipeline.synth.tem_wave import ParticleSpec, TemWaveParams

    parts = (
        ParticleSpec(
            9.50125478680705e-09, 163.06514863351893,
            (1.566968547346903e-09, 1.7253837730070076e-09, 1.6158721294125021e-09), 0.5383955740303652,
            122.26216487806325, "apex",
        ),
        ParticleSpec(
            1.3391488540441453e-07, 209.11238421949497,
            (9.955931766671963e-09, 3.072897191418122e-09, 3.811784829116368e-09), 0.5, 0.0, "shank",
        ),
    )  # fmt: skip
    return TemWaveParams(
        n=5.824961597498439, R=2.776702973689934e-08, S=1.8190175107825273, z_join=1.1158194865646262e-08,
        shank_half_angle_deg=21.349554746282152, blend_length=1.0716264396271931e-08,
        asymmetry=0.032396582724843415, layer="DLC", layer_thickness=4.433517298369366e-09,
        core_absorption_length_200kv=3.587706228819322e-08, layer_contrast=0.27023631587987323,
        contamination_contrast=0.2342289301324302, particles=parts, pixel_size=3.4459625470141835e-10, shape=(672, 672),
        apex_px=(469.31227036838925, 371.8438302901963), rotation_deg=-11.184503337737297, orientation='down',
        kv=147.66013911168568, defocus=1.2096877282235763e-07, cs=0.0006294775609929036,
        aperture=0.014791670068304327, illumination_angle=2.149048673369272e-05, cc=0.00249791678779686,
        energy_spread_ev=0.5180827863592632, snr=22.31952312974915, bits=16,
        background_level=0.6830948572543538, float_gain=12.536108618063611, offset=39.88239966347973,
        read_noise=2.600522715980002, psf_sigma=0.6059042289624439, psf_tail_weight=0.007201411445028494,
        psf_tail_length=4.681314533933355, illumination_gradient=0.07536616213654145,
        gradient_angle_deg=191.93604004971232, vignetting=0.06072941213728616, seed=119,
    )  # fmt: skip


def test_a_light_layer_read_as_a_fringe_is_fitted_as_a_layer(tmp_path):
    """Grid image 119 (``bench_tem_independent``, its parameters exactly): a 4.4 nm DLC layer of 27 %
    contrast, 121 nm underfocus, 0.345 nm px.  Phase contrast sharpens the edge, the fitted blur sits
    at its floor and the coating search tried no layer; fitted as one material (its edge on the outer
    surface, 0.03 nm), the fringe correction explained the layer as the dark fringe of a 2.8 um
    overfocus (the wrong sign) and moved the edge 1.65 nm inwards (n 4.53 for 5.82).  The coated model,
    searched over every thickness and rendered coherently as well, fits the image better (chi^2 6.2e4
    against 1.37e5): the edge stays on the outer surface.  (Since the fit of both signs continues the best
    start of each sign, the one-material correction takes underfocus here, chi^2 2.31e5, an overfocus
    0.2 % behind it after the screen's steps; that closeness, ``silhouette_fit.OVERFOCUS_MARGIN``, is what
    tries the coated model now: 6.1e4.)"""
    p = _grid_119()
    g, _ = _graded(tmp_path, p)
    assert not g["lost"], g["lost_reason"]
    assert g["coating_model"] == "coated" and 3.0e-9 < g["coating_found"] < 5.5e-9, g["coating_found"]
    assert any(f.startswith("a light layer, not a fringe") for f in g["edge_flags"]), g["edge_flags"]  # in words
    assert abs(g["edge_bias"]) < 0.15e-9, g["edge_bias"]  # -1.62 nm read as a fringe; +0.03 nm now
    assert g["n_covered"] and g["pulloff_covered_mc"], (g["dn"], g["sigma_n"])


def _grid_4():
    """Grid image 4 of ``bench_tem_independent``, its parameters exactly: n 5.77, a 1.90 nm oxide, 0.82 um
    underfocus at 136 kV, 0.494 nm px, a particle 13 nm above the apex."""
    from pipeline.synth.tem_wave import ParticleSpec, TemWaveParams

    part = ParticleSpec(
        height=1.3400679378510925e-08, azimuth_deg=197.24394066827463,
        semi_axes=(1.9431687573964224e-09, 8.081938225614317e-10, 1.4908339551470591e-09),
        sink=0.6796112846539215, tilt_deg=30.995831039310943, kind="apex",
    )  # fmt: skip
    return TemWaveParams(
        n=5.7722244222894705, R=2.1805843925987763e-08, S=1.976243705707704, z_join=9.778392525703249e-09,
        shank_half_angle_deg=19.110337479925445, blend_length=2.129459753131818e-08, asymmetry=0.04486541096750626,
        layer="oxide", layer_thickness=1.9022150797159884e-09, core_absorption_length_200kv=4.867729527511772e-08,
        layer_contrast=0.3431460571517619, contamination_contrast=0.25778934350886584, particles=(part,),
        pixel_size=4.936611999724486e-10, shape=(448, 448), apex_px=(146.11064081334268, 199.4956161344049),
        rotation_deg=14.067986079487046, orientation="up", kv=135.53851715239622, defocus=8.194589822589702e-07,
        cs=0.001914205518693751, aperture=0.014984861254486302, illumination_angle=2.8702225862161612e-05,
        cc=0.0018472278784209869, energy_spread_ev=0.44808595018683445, snr=17.505654733718647, bits=0,
        background_level=0.21782836008366196, float_gain=18.81258754176817, offset=0.0,
        read_noise=5.4881964677551975, psf_sigma=0.5910079003235229, psf_tail_weight=0.04017500854373827,
        psf_tail_length=4.789324085924201, illumination_gradient=0.03933802276899812,
        gradient_angle_deg=243.28831137606932, vignetting=0.047603891047540196, seed=4,
    )  # fmt: skip


def test_a_light_layer_against_the_sign_given_keeps_the_conflict_term(tmp_path):
    """Grid image 4 with the operator's ``tem.defocus: underfocus`` (the true sign): the one-material fit
    of both signs takes overfocus (lambda df -2.1 nm^2: its layer read as the dark fringe), so the fringes
    are fitted at the sign given, and the coated model (a 2.3 nm layer), rendered at that sign, is taken.
    The conflict between the two signs stays with it, in words and as the common uncertainty (half the two
    one-material edges' distance, 0.31 nm), as on a one-material edge (the flag and the covariance's term
    come together in ``silhouette_fit._result``): the coated body's own fit of both signs is not made, so
    the sign given is as open as before.  Before stop 44 the coated edge dropped it (on grid 4, 64, 94 and
    119 then; grid 119, this test's image until stop 45, now takes underfocus in the fit of both signs, its
    best start of each sign continued, so no conflict arises there)."""
    g, _ = _graded(tmp_path, _grid_4(), defocus="underfocus")
    assert not g["lost"], g["lost_reason"]
    assert g["coating_model"] == "coated", g["coating_model"]
    assert any(f.startswith("a light layer, not a fringe") and "against the sign given" in f for f in g["edge_flags"])
    against = [f for f in g["edge_flags"] if f.startswith("defocus given as underfocus")]
    assert against and "took lambda x defocus -" in against[0], g["edge_flags"]
    sd = float(against[0].split("the two fits' edges, ")[1].split(" nm")[0]) * 1e-9
    assert 0.15e-9 < sd < 0.6e-9, sd  # 0.31 nm
    assert g["edge_bias_sd"] > sd, g["edge_bias_sd"]  # 1.28 nm
    assert abs(g["edge_bias"]) < 2 * g["edge_bias_sd"] and g["n_covered"], (g["edge_bias"], g["dn"], g["sigma_n"])


def _grid_100():
    """Grid image 100 of ``bench_tem_independent``, its parameters exactly: a 2.0 nm oxide of 29 %
    contrast, 0.50 um underfocus, 0.34 nm px, SNR 22."""
    from pipeline.synth.tem_wave import ParticleSpec, TemWaveParams

    parts = (
        ParticleSpec(
            7.349606395293278e-09, 14.52033892163576,
            (1.3955660583285924e-09, 8.687840693990819e-10, 1.3068566801805784e-09), 0.4057355760081291,
            0.1359362620650617, "apex",
        ),
        ParticleSpec(
            1.3109263469472118e-08, -2.081227538241208,
            (1.4268863839332554e-09, 7.44984908689796e-10, 1.1032004194874041e-09), 0.3758698963670719,
            94.24990214567542, "apex",
        ),
    )  # fmt: skip
    p = TemWaveParams(
        n=5.339926522008035, R=2.410695872813296e-08, S=1.2888632416912036, z_join=8.944934555272651e-09,
        shank_half_angle_deg=24.60481592659321, blend_length=2.7894151121940656e-08,
        asymmetry=-0.037526177903669806, layer="oxide", layer_thickness=1.9814789806272664e-09,
        core_absorption_length_200kv=5.961002433619776e-08, layer_contrast=0.28542201500529457,
        contamination_contrast=0.21620729575607128, particles=parts, pixel_size=3.3996490925290917e-10,
        shape=(544, 544), apex_px=(397.7612033460974, 228.53024359925425), rotation_deg=14.873313126556546,
        orientation="down", kv=254.2045152805015, defocus=4.976744931721894e-07, cs=0.0019679328820543392,
        aperture=0.010903520674500494, illumination_angle=4.782373413070608e-05, cc=0.0023208348464550245,
        energy_spread_ev=0.5397974686106848, snr=22.285765817874967, bits=16,
        background_level=0.14873629669494243, float_gain=5.854173279640904, offset=187.64924632606926,
        read_noise=1.5768095930705472, psf_sigma=0.6280585135613133, psf_tail_weight=0.0022014045428084992,
        psf_tail_length=4.503596515948592, illumination_gradient=0.005791926243876704,
        gradient_angle_deg=188.6834963883052, vignetting=0.0546550515530424, seed=100,
    )  # fmt: skip
    return p


def test_a_wrong_sign_of_the_defocus_is_covered_by_the_move(tmp_path):
    """Grid image 100 (``bench_tem_independent``, its parameters exactly): a 2.0 nm oxide of 29 %
    contrast, 0.50 um underfocus, 0.34 nm px, read as one material (no coated fit is found, also with
    every thickness tried).  Its fringe correction takes the wrong sign (lambda x df -1.5 nm^2) and moves
    an edge that lay 0.19 nm outside 0.76 nm inwards, where its noise SD (0.00 nm) and the model-error
    term (0.24 nm) did not cover it.  Half the move as the correction's model error covers it; the
    edge itself stays wrong (found and left open: README)."""
    p = _grid_100()
    g, flag = _graded(tmp_path, p)
    assert not g["lost"], g["lost_reason"]
    assert flag and "lambda x defocus -" in flag[0] and "half the move" in flag[0], flag  # the wrong sign
    move = float(flag[0].split("edge moved ")[1].split(" ")[0]) * 1e-9
    assert move < -0.5e-9 and g["edge_bias"] < -0.4e-9, (move, g["edge_bias"])  # the known fault, as found
    assert abs(g["edge_bias"]) <= 2 * g["edge_bias_sd"], (g["edge_bias"], g["edge_bias_sd"])
    assert g["edge_bias_sd"] >= 0.5 * abs(move)


def test_the_sign_given_keeps_the_fringes_to_it(tmp_path):
    """Grid image 100 again, with the operator's ``tem.defocus: underfocus``: the fit of both signs still
    takes overfocus (-1.5 nm^2, the oxide read as the dark fringe), the flag says so, and the fringes
    fitted at the given sign (+0.9 nm^2 against the true +1.3 nm^2) move the edge only 0.12 nm: it lies
    +0.07 nm from the true silhouette (-0.57 nm without the sign), within its SD, which carries the two
    fits' disagreement."""
    g, flag = _graded(tmp_path, _grid_100(), defocus="underfocus")
    assert not g["lost"], g["lost_reason"]
    against = [f for f in g["edge_flags"] if f.startswith("defocus given as underfocus")]
    assert against and "took lambda x defocus -" in against[0] and "(overfocus;" in against[0], g["edge_flags"]
    assert flag and "lambda x defocus +" in flag[0] and "the sign of the defocus was given (underfocus)" in flag[0]
    assert abs(g["edge_bias"]) < 0.2e-9, g["edge_bias"]
    assert abs(g["edge_bias"]) <= 2 * g["edge_bias_sd"], (g["edge_bias"], g["edge_bias_sd"])
    # the two fits disagree: half their edges' distance (0.32 nm) joins the edge's SD (0.25 -> 0.41 nm), which
    # also covers the other fit's edge, in case the sign given was the wrong one
    assert "half the distance between the two fits' edges, 0.3" in against[0], against[0]
    assert g["edge_bias_sd"] > 0.35e-9, g["edge_bias_sd"]


def test_the_sign_given_finds_a_strong_overfocus_at_fine_pixels(tmp_path):
    """Held-out image 33 (``bench_tem_independent --seed0 1000``, its parameters exactly): uncoated,
    1.59 um overfocus at 0.117 nm px.  The fit of both signs takes underfocus (+3.2 nm^2): there the
    rendering fits better by ~2e4 in chi^2, and the edge stays 0.92 nm outside, outside its SD.  Given
    the overfocus, the 1-D screen's optimum in the right basin (A ~ -290 px^2) ranks low in 2-D until
    the fit has moved its blur and attenuation scale, so every distinct candidate goes on
    (``SCREEN_KEEP_SIGNED``): the edge lies 0.11 nm from the true silhouette."""
    from pipeline.synth.tem_wave import ParticleSpec, TemWaveParams

    parts = (
        ParticleSpec(
            9.33228214077726e-09, 160.819143657244,
            (1.699009594435103e-09, 1.2026332386478029e-09, 1.5009537440849512e-09), 0.3334250105622962,
            118.43212996024376, "apex",
        ),
    )  # fmt: skip
    p = TemWaveParams(
        n=5.312552508523679, R=1.3590251291040496e-08, S=1.9206617489745534, z_join=2.1764910382180943e-08,
        shank_half_angle_deg=18.32963090658611, blend_length=3.65751446605772e-08,
        asymmetry=0.025875493464081502, layer="none", layer_thickness=0.0,
        core_absorption_length_200kv=3.4969719214042904e-08, layer_contrast=0.2,
        contamination_contrast=0.1750280579939341, particles=parts, pixel_size=1.1655125389411759e-10,
        shape=(1024, 1024), apex_px=(292.5137796228962, 544.5902564594061), rotation_deg=-10.75653258166869,
        orientation="up", kv=233.27869261852751, defocus=-1.586521128673421e-06, cs=0.0009190005722519705,
        aperture=0.014780501921797876, illumination_angle=8.165591215316156e-05, cc=0.002277663125622836,
        energy_spread_ev=0.5040598908906715, snr=20.984650505362715, bits=16,
        background_level=0.2786349595562093, float_gain=7.155889186541616, offset=245.46174896260223,
        read_noise=1.4410018288167508, psf_sigma=0.35878029030940367, psf_tail_weight=0.12108972808960143,
        psf_tail_length=4.614723447749515, illumination_gradient=0.03271708218420806,
        gradient_angle_deg=16.670756247762547, vignetting=0.06630611132704431, seed=1033,
    )  # fmt: skip
    g, flag = _graded(tmp_path, p, defocus="overfocus")
    assert not g["lost"], g["lost_reason"]
    against = [f for f in g["edge_flags"] if f.startswith("defocus given as overfocus")]
    assert against and "took lambda x defocus +" in against[0], g["edge_flags"]
    assert flag and "lambda x defocus -" in flag[0], flag
    lam_df = float(flag[0].split("lambda x defocus ")[1].split(" ")[0]) * 1e-18
    assert 0.6 < lam_df / (2.29e-12 * p.defocus) < 1.4, lam_df  # lambda 2.29 pm at 233 kV
    assert abs(g["edge_bias"]) < 0.3e-9, g["edge_bias"]  # 0.11 nm; without the sign +0.92 nm


def test_the_sign_given_that_the_fit_finds_changes_nothing(defocused, tmp_path):
    """Where the fit of both signs takes the sign given (the defocused image: 1.5 um overfocus), nothing
    more is done: the same edge to the last bit; only the flag's words say the sign was given, and the
    profile file (``/edge_model`` attributes)."""
    import h5py

    from pipeline.synth.tem_wave import simulate
    from pipeline.tem.io import write_profile_h5
    from pipeline.tem.reading import TemImage

    prof = defocused[0]
    given, _, _, p = _profile(-1.5e-6, defocus_given="overfocus")
    write_profile_h5(tmp_path / "p.h5", TemImage(simulate(p)[0].astype(float), p.pixel_size, "synthetic"), given)
    with h5py.File(tmp_path / "p.h5") as f:
        assert f["edge_model"].attrs["fringe_defocus_sign_given"] == -1
        assert not f["edge_model"].attrs["fringe_layer_taken_back"]
        assert "fringe_free_lambda_defocus" not in f["edge_model"]  # the fit of both signs agreed
    assert np.array_equal(given.edge_px, prof.edge_px)
    assert np.array_equal(given.offset_cov, prof.offset_cov)
    assert given.edge_model["global_fringe"]["sign"] == -1 and prof.edge_model["global_fringe"]["sign"] == 0
    words = [f for f in given.edge_model["global_flags"] if f.startswith("defocus fringes")]
    assert words and "the sign of the defocus was given (overfocus)" in words[0]
    assert not any(f.startswith("defocus given as") for f in given.edge_model["global_flags"])


def test_fringes_are_fitted_at_the_sign_given(fitted_problem):
    """``fringe_offset(..., sign=...)`` keeps lambda x df on the side given, its starts, its 1-D screen
    and its steps: on the 1.5 um overfocus image, the wrong sign given (+1) ends at A >= 0 and fits worse
    than the right one (-1), which ends where the fit of both signs does."""
    from pipeline.tem.fringe_correction import fringe_offset

    free = fringe_offset(*fitted_problem)
    right = fringe_offset(*fitted_problem, sign=-1)
    wrong = fringe_offset(*fitted_problem, sign=+1)
    assert free["A_px2"] < 0 and right["A_px2"] <= 0.0 and wrong["A_px2"] >= 0.0
    assert (right["sign"], wrong["sign"], free["sign"]) == (-1, 1, 0)
    assert wrong["chi2"] > right["chi2"]
    # here lower (79491 against 80510): fewer starts, another basin of the same sign, the offset 0.16 px
    # (0.05 nm) apart
    assert right["chi2"] <= free["chi2"] * (1 + 1e-3)
    assert right["offset_px"] == pytest.approx(free["offset_px"], abs=0.3)


def test_defocus_sign_is_in_the_tip_schema(tmp_path, monkeypatch):
    """``tem.defocus`` (auto by default) and an interval's own ``defocus``: auto, underfocus or overfocus;
    anything else is refused naming the field, and ``extract_profile`` refuses it too."""
    from pipeline.config import ConfigError, load_tip_config
    from pipeline.tem.profiles import extract_profile
    from pipeline.tem.reading import TemImage

    root = Path(__file__).resolve().parents[1]
    monkeypatch.chdir(root)
    src = (root / "config" / "tips" / "tipB_Si.yaml").read_text()
    ok = tmp_path / "t.yaml"
    given = src.replace("tem:", "tem:\n  defocus: underfocus", 1)
    ok.write_text(given.replace("  scans: 0\n", "  scans: 0\n  defocus: overfocus\n", 1))
    tip = load_tip_config(ok)
    assert tip["tem"]["defocus"] == "underfocus" and tip["intervals"][0]["defocus"] == "overfocus"
    plain = tmp_path / "p.yaml"
    plain.write_text(src)
    assert load_tip_config(plain)["tem"]["defocus"] == "auto"
    for bad_src in (
        src.replace("tem:", "tem:\n  defocus: under", 1),
        src.replace("  scans: 0\n", "  scans: 0\n  defocus: -1.2 um\n", 1),
    ):
        bad = tmp_path / "bad.yaml"
        bad.write_text(bad_src)
        with pytest.raises(ConfigError, match="defocus"):
            load_tip_config(bad)
    with pytest.raises(ValueError, match="defocus must be one of auto, underfocus, overfocus"):
        extract_profile(TemImage(np.ones((64, 64)), 0.3e-9, "synthetic"), defocus="+1 um")


def _grid_60():
    """Grid image 60 of ``bench_tem_independent``, its parameters exactly: uncoated, 41 nm overfocus,
    0.341 nm px, SNR 30."""
    from pipeline.synth.tem_wave import TemWaveParams

    p = TemWaveParams(
        n=3.297135250805106, R=8.732952581165123e-09, S=1.0547208874422234, z_join=2.9790813468634023e-08,
        shank_half_angle_deg=22.94934938526368, blend_length=2.6515905053597115e-08,
        asymmetry=-0.02573017995852478, layer="none", layer_thickness=0.0,
        core_absorption_length_200kv=5.623124631892766e-08, layer_contrast=0.2,
        contamination_contrast=0.25590209576501965, particles=(), pixel_size=3.412828737287849e-10,
        shape=(448, 448), apex_px=(351.22781112662466, 234.12591634917692), rotation_deg=0.7203834038044619,
        orientation="down", kv=186.25100790451827, defocus=-4.129449772673339e-08, cs=0.0012514978786032228,
        aperture=0.005018219209862615, illumination_angle=8.780344682505383e-05, cc=0.002499031117614823,
        energy_spread_ev=0.5739455194851104, snr=29.58103815810744, bits=0, background_level=0.48087172568689024,
        float_gain=4.242729192693947, offset=0.0, read_noise=1.4755596572156398, psf_sigma=0.40044192807503876,
        psf_tail_weight=0.030923652580131508, psf_tail_length=4.014895973439877,
        illumination_gradient=0.006117979695792455, gradient_angle_deg=180.35867501361835,
        vignetting=0.003877487165109639, seed=60,
    )  # fmt: skip
    return p


def test_a_light_layer_that_is_the_dark_fringe_is_taken_back_with_the_overfocus_given(tmp_path):
    """Grid image 60 with ``tem.defocus: overfocus``: the 0.93 nm light layer the fit reads from the dark
    fringe (chi^2 under the correction's gate) is taken back by the outer curve rendered as one material
    at the given sign (chi^2 -523 against the coated body rendered), and the edge lies on the true
    silhouette (-0.01 nm; +0.44 nm without the sign, the expected failure above)."""
    g, flag = _graded(tmp_path, _grid_60(), defocus="overfocus")
    assert not g["lost"], g["lost_reason"]
    words = [f for f in g["edge_flags"] if f.startswith("a fringe, not a light layer")]
    assert words and "(0.93 nm)" in words[0], g["edge_flags"]
    assert flag and "lambda x defocus -" in flag[0], flag
    assert abs(g["edge_bias"]) < 0.1e-9, g["edge_bias"]
    assert abs(g["edge_bias"]) <= 2 * g["edge_bias_sd"]


@pytest.mark.xfail(
    strict=True,
    reason="known, not fixed without the sign of the defocus: the dark fringe of a slight overfocus is read as "
    "a light layer (README, 'a slight overfocus pushes the edge out'); a one-material coherent body fixes this "
    "image but was not kept at either sign (cost on thin oxides, or oxides in underfocus moved inward); with "
    "tem.defocus: overfocus it is fixed (the test above)",
)
def test_a_light_layer_that_is_the_dark_fringe_is_taken_back(tmp_path):
    """Grid image 60 (``bench_tem_independent``, parameters exactly): uncoated, 41 nm overfocus,
    0.341 nm px, SNR 30.  The dark Fresnel fringe just outside the edge is read by the fit as a light
    layer (0.93 nm at half the core's attenuation) and the edge is its outer surface, 0.44 nm outside
    the true silhouette; the reduced chi^2 (1.4) is below the correction's gate, and a coherent
    rendering of the coated body cannot take the layer back.  A body of one material rendered
    coherently fits better (scratch: chi^2 -459 against the coated fit) and its edge lies on the true
    silhouette (-0.01 nm); not in main (README), so this fails on purpose until it is."""
    LAYER_AS_FRINGE_MAX = 2.5e-9  # m: the thin light layers a fringe can read as (0.65-2.2 nm seen)

    p = _grid_60()
    g, flag = _graded(tmp_path, p)
    assert not g["lost"], g["lost_reason"]
    assert g["chi2_red"] < 5.0  # below the gate: the correction ran for the thin layer
    assert 0.0 < g["coating_found"] < LAYER_AS_FRINGE_MAX  # the fringe read as a layer (0.93 nm)
    assert flag and "is read as this fringe" in flag[0], g["edge_flags"]
    assert abs(g["edge_bias"]) < 0.1e-9, g["edge_bias"]  # +0.44 nm at the layer's outer surface; -0.01 now
    assert g["n_covered"] and g["pulloff_covered_mc"] and abs(g["pulloff_error"]) < 0.03


def test_the_interval_s_defocus_reaches_the_stage(tmp_path, monkeypatch):
    """``python -m pipeline profiles``: an interval's own ``defocus`` overrides the tip's ``tem.defocus``,
    and the tip's applies to the other intervals."""
    import pipeline.tem.stage as stage
    from pipeline.cli import main

    root = Path(__file__).resolve().parents[1]
    monkeypatch.chdir(root)
    src = (root / "config" / "tips" / "tipB_Si.yaml").read_text()
    given = src.replace("tem:", "tem:\n  defocus: underfocus", 1)
    cfg = tmp_path / "t.yaml"
    cfg.write_text(given.replace("  scans: 0\n", "  scans: 0\n  defocus: overfocus\n", 1))
    seen = {}
    monkeypatch.setattr(stage, "run_profiles", lambda *a, **kw: seen.update({kw["interval"]: kw["defocus"]}))
    for interval in ("scan000", "scan010"):
        assert (
            main(["profiles", "--tip-config", str(cfg), "--interval", interval, "--out-h5", "x", "--out-png", "y"]) == 0
        )
    assert seen == {"scan000": "overfocus", "scan010": "underfocus"}


def _grid_112():
    """Grid image 112 of ``bench_tem_independent``, its parameters exactly: a 1.05 nm oxide, 1.56 um
    overfocus at 297 kV, 0.49 nm px, SNR 17, three particles on one flank near the apex."""
    from pipeline.synth.tem_wave import ParticleSpec, TemWaveParams

    parts = (
        ParticleSpec(1.1661454167364865e-08, 185.94070699073598,
                     (1.8246652657648488e-09, 1.7072736062757713e-09, 1.9981736815696147e-09), 0.8646480499197329,
                     31.93404896252315, "apex"),
        ParticleSpec(7.171601158390481e-09, 173.38378401314515,
                     (2.3393265163536843e-09, 5.8578861084106e-10, 1.6197224555211978e-09), 0.4496375459140477,
                     98.06246327865594, "apex"),
        ParticleSpec(8.180065531225966e-09, 188.25787576450423,
                     (1.0634767061922976e-09, 1.8241078297034527e-09, 1.6001291046884788e-09), 0.4185290514037121,
                     158.8739321611444, "apex"),
        ParticleSpec(1.4814901541329126e-07, 21.76696120570378,
                     (9.212209183260107e-09, 1.0142581021379221e-08, 1.038893379770357e-08), 0.5, 0.0, "shank"),
        ParticleSpec(1.5787993928417383e-07, 182.13813739742142,
                     (1.0473548311222426e-08, 7.209928182364327e-09, 1.1440820555979013e-08), 0.5, 0.0, "shank"),
        ParticleSpec(9.890059062107295e-08, 209.64962672321658,
                     (6.5929117820536796e-09, 8.103296699319857e-09, 7.637611850414955e-09), 0.5, 0.0, "shank"),
    )  # fmt: skip
    return TemWaveParams(
        n=2.4658360520306215, R=3.0792146470614916e-08, S=1.7986734243246567, z_join=8.382725536537577e-09,
        shank_half_angle_deg=11.154200777495554, blend_length=2.4893690373959638e-08,
        asymmetry=0.02251572215920643, layer="oxide", layer_thickness=1.049427151010692e-09,
        core_absorption_length_200kv=7.815735391795643e-08, layer_contrast=0.4465917335421378,
        contamination_contrast=0.25882050468546947, particles=parts, pixel_size=4.937972986352704e-10,
        shape=(416, 416), apex_px=(99.64830116854586, 225.91454688477884), rotation_deg=-9.35126781186104,
        orientation="up", kv=296.60911689552483, defocus=-1.5558424146216215e-06, cs=0.0009880256283171596,
        aperture=0.008385866028349783, illumination_angle=0.00015734227667631238, cc=0.0014485141129799324,
        energy_spread_ev=0.3106041732377201, snr=17.126393002879052, bits=16, background_level=0.4658134976395653,
        float_gain=8.125311530098777, offset=201.99110199316965, read_noise=4.958750614907958,
        psf_sigma=0.31069173860825294, psf_tail_weight=0.10793191630909084, psf_tail_length=2.7764257528403578,
        illumination_gradient=0.007172847745172497, gradient_angle_deg=284.45085453464606,
        vignetting=0.017098467788609507, grid_step=1e-10, noise=True, seed=112,
    )  # fmt: skip


def test_the_edge_s_shape_is_refitted_with_the_fringes(tmp_path):
    """Grid image 112: with the uniform offset alone the apex lay 0.2 nm inside and the flank 1-2 nm
    above it 0.5 nm outside (edge RMS 0.42 nm), n +0.85 off at sigma_n 0.63, the pull-off +42 %; with the
    shape refitted to the coherent rendering (``pipeline.tem.fringe_shape``) 0.15 nm, -0.08, -4 %; with
    the exit wave averaged over the pixel 0.135 nm, -0.085, +5.1 %, the same to 0.001 in n on the three
    arithmetic paths (-0.055 / -0.085 / -0.098 with the wave sampled at the pixel centres)."""
    g, fringe = _graded(tmp_path, _grid_112())
    assert fringe and "the edge's shape refitted with that rendering" in fringe[0], g["edge_flags"]
    assert g["edge_rms"] < 0.25e-9, g["edge_rms"]
    assert abs(g["dn"]) < 0.25, g["dn"]
    assert abs(g["pulloff_error"]) < 0.1, g["pulloff_error"]
    assert g["n_covered"] and g["pulloff_covered_mc"]


@pytest.mark.slow
def test_a_blunt_oxide_tip_read_as_one_material_is_fitted_with_a_held_layer(tmp_path):
    """Held-out image 31 (``bench_tem_independent --seed0 1000``, its parameters exactly): n 4.77, a 1.22 nm
    oxide, 0.48 um underfocus at 101 kV, 0.135 nm px, SNR 23.  Fitted as one material, the flat face lay
    +0.23 nm outside the true silhouette, the flanks +0.01 to +0.10 nm, and n came out 0.40 low at a
    reported sigma_n of 0.24 (covered): the phase step between the oxide and the core makes a fringe at the
    face.  The one-material fit's outer curve with a held 1.2 nm layer, rendered coherently, fits with
    chi^2 1.2e5 against 2.7e5 (``pipeline.tem.held_layer``): edge bias +0.005 nm, dn +0.04."""
    from pipeline.synth.tem_wave import TemWaveParams

    p = TemWaveParams(
        n=4.770267657838894, R=1.7890023874102682e-08, S=1.6621546713394848, z_join=2.2919985309158974e-08,
        shank_half_angle_deg=12.976930210929474, blend_length=3.129811734846841e-08, asymmetry=0.0, layer="oxide",
        layer_thickness=1.2221002501158593e-09, core_absorption_length_200kv=4.0749372890502456e-08,
        layer_contrast=0.2468056455822959, contamination_contrast=0.2865010206833828, particles=(),
        pixel_size=1.3494211524055034e-10, shape=(1024, 1024), apex_px=(698.3432641782922, 596.6552273524655),
        rotation_deg=11.990812899785702, orientation="down", kv=101.0793159871413, defocus=4.769601655567905e-07,
        cs=0.0011808214403477737, aperture=0.015892061573900485, illumination_angle=5.3961744289170064e-05,
        cc=0.0017656438498680177, energy_spread_ev=0.5596204155861415, snr=22.817707968214826, bits=16,
        background_level=0.5151490095459585, float_gain=12.500783851674687, offset=113.09042802321098,
        read_noise=1.847710315018297, psf_sigma=0.4308076709114407, psf_tail_weight=0.10839949527635821,
        psf_tail_length=3.0003986107550245, illumination_gradient=0.019239984542116523,
        gradient_angle_deg=238.66974243803276, vignetting=0.013978151877753787, seed=1031,
    )  # fmt: skip
    g, _ = _graded(tmp_path, p)
    assert not g["lost"], g["lost_reason"]
    assert any("a light layer seen by the coherent rendering" in f for f in g["fit_flags"] + g["edge_flags"])
    assert g["n_covered"]
    assert abs(g["dn"]) <= 0.15, g["dn"]  # -0.40 as one material, +0.04 with the held layer
    assert abs(g["edge_bias"]) < 0.1e-9, g["edge_bias"]  # +0.005 nm (one material: +0.11 nm)


def test_the_held_layers_reach_the_native_oxides_at_fine_pixels():
    """The held layers tried at grid 82's 0.142 nm px include 1.7 nm (11.99 px), which 0.95 x the coated
    model's thickness bound (11.4 px) cut off; at 0.1 nm px (binned to 0.2 nm) all four; the thickest stays
    inside the fitted band."""
    from pipeline.tem.held_layer import HELD_MAX_PX, layers_tried_px
    from pipeline.tem.silhouette_model import BAND_INSIDE_PX

    assert np.allclose(np.array(layers_tried_px(0.14181e-9)) * 0.14181, [0.8, 1.2, 1.7])
    assert np.allclose(np.array(layers_tried_px(0.2e-9)) * 0.2, [0.8, 1.2, 1.7, 2.4])
    assert 12.0 < HELD_MAX_PX < BAND_INSIDE_PX


@pytest.mark.slow
def test_a_held_layer_is_not_cut_off_at_the_coated_model_s_bound(tmp_path):
    """Grid image 82 (``bench_tem_independent``, its parameters exactly): n 5.99, a 1.52 nm oxide, 0.24 um
    underfocus at 221 kV, 0.142 nm px (fitted unbinned), SNR 23, 1024 px.  Read as one material, n came out
    0.45 low.  The held layers stopped at 0.95 x the coated model's bound on a fitted thickness (11.4 px):
    0.8 and 1.2 nm were tried (chi^2 5 % below one material's at best, not taken), 1.7 nm (11.99 px) was
    not.  Tried up to what the fitted band holds (``held_layer.HELD_MAX_PX``, 14 px), the 1.7 nm layer fits
    with chi^2 3.2e5 against 4.8e5 and is taken: dn -0.02, edge RMS 0.14 -> 0.05 nm, the pull-off 4.5 % ->
    0.2 % off.  (What this checks is that the limit is no longer 11.4 px: a limit of 12 px would pass too.
    Slow, a 1024 px image: the default suite checks the thicknesses tried, above.)"""
    from pipeline.synth.tem_wave import ParticleSpec, TemWaveParams

    apex_particle = ParticleSpec(
        height=1.6055002887269207e-08, azimuth_deg=187.36896689043147,
        semi_axes=(1.1264237957003262e-09, 1.3560438557278068e-09, 1.3998217235640084e-09),
        sink=0.38710241495029074, tilt_deg=61.36424704987443, kind="apex",
    )  # fmt: skip
    p = TemWaveParams(
        n=5.99055500954106, R=2.5174212443022503e-08, S=1.2176863993359395, z_join=2.9563199085098467e-08,
        shank_half_angle_deg=16.128834707285037, blend_length=3.817215744524668e-08, asymmetry=0.0, layer="oxide",
        layer_thickness=1.5181521697726181e-09, core_absorption_length_200kv=7.244644539831778e-08,
        layer_contrast=0.30786374386389803, contamination_contrast=0.11578972655674316, particles=(apex_particle,),
        pixel_size=1.4181139871598703e-10, shape=(1024, 1024), apex_px=(618.7725727042347, 527.4270562332637),
        rotation_deg=7.792720842305123, orientation="down", kv=220.78087196013024, defocus=2.356840487856765e-07,
        cs=0.001186693584577206, aperture=0.008936379624373264, illumination_angle=7.913801259555174e-05,
        cc=0.0022369744562155394, energy_spread_ev=0.39712950787501267, snr=22.967150058791603, bits=16,
        background_level=0.5092439997904101, float_gain=1.2680719292415672, offset=44.13995162080022,
        read_noise=6.59259262988269, psf_sigma=0.4322954001482691, psf_tail_weight=0.08554075058192387,
        psf_tail_length=2.4622433417646334, illumination_gradient=0.013033950985127402,
        gradient_angle_deg=274.26388593371, vignetting=0.04980513802202059, seed=82,
    )  # fmt: skip
    g, _ = _graded(tmp_path, p)
    assert not g["lost"], g["lost_reason"]
    held = [f for f in g["fit_flags"] + g["edge_flags"] if f.startswith("a light layer seen by the coherent rendering")]
    assert held and "held 1.70 nm layer" in held[0], held
    assert g["n_covered"]
    assert abs(g["dn"]) <= 0.1, g["dn"]  # -0.45 as one material, -0.02 with the held layer
    assert abs(g["pulloff_error"]) < 0.03, g["pulloff_error"]  # 4.5 % as one material, 0.2 %


def test_the_fit_of_both_signs_keeps_a_start_of_each_sign():
    """The 2-D fit of both signs continues the two best starts of the screen and, where both are of one
    sign of the defocus (or one is the Beer-Lambert state, A = 0), the best start of the other sign."""
    from pipeline.tem.fringe_correction import _with_each_sign

    def kept(*A):
        return [float(q[1]) for q in _with_each_sign([np.array([0.0, a, 0.0, 0.0, 0.0]) for a in A])]

    assert kept(1.7, 0.0, 23.8, -2.5, -9.0) == [1.7, 0.0, -2.5]
    assert kept(-99.6, -167.4, 146.8, 58.6) == [-99.6, -167.4, 146.8]
    assert kept(4.9, -3.8, 62.3) == [4.9, -3.8]
    assert kept(0.0, 5.0, 7.0) == [0.0, 5.0]  # no start of the other sign: none added
    assert kept(3.0) == [3.0]
    assert kept(-1.0, 0.0, 5.0) == [-1.0, 0.0, 5.0]  # A = 0 (the Beer-Lambert state) is of neither sign


def test_an_overfocus_ranked_low_in_the_screen_is_fitted_without_the_sign(tmp_path):
    """Grid image 57 (``bench_tem_independent``, its parameters exactly): uncoated, n 4.74, 154 nm
    overfocus at 211 kV, 0.32 nm px, SNR 11, three particles near the apex.  The screen's two best starts
    were both in underfocus, so the fit of both signs ended there (chi^2 45189 at lambda df +3.1 px^2) with
    the edge 0.41 nm outside the true silhouette, while the fit at the true sign alone reached 28507 at
    -6.1 px^2.  With the best overfocus start continued too, the fit of both signs ends there: the edge
    0.11 nm inside, dn +0.06 (+0.09 before)."""
    from pipeline.synth.tem_wave import ParticleSpec, TemWaveParams

    parts = (
        ParticleSpec(
            height=1.8818823174758638e-08, azimuth_deg=13.862693106171466,
            semi_axes=(8.787551640005407e-10, 1.8132936121304188e-09, 1.3056047425164345e-09),
            sink=0.5730112836302987, tilt_deg=163.31269581516557, kind="apex",
        ),
        ParticleSpec(
            height=1.930179470123623e-08, azimuth_deg=7.05365864726796,
            semi_axes=(1.9556248466143173e-09, 1.7366362262204276e-09, 1.8777514735638342e-09),
            sink=0.41768410131665246, tilt_deg=10.876871546774558, kind="apex",
        ),
        ParticleSpec(
            height=1.2054254571174714e-08, azimuth_deg=12.75220485546047,
            semi_axes=(2.1381548784044603e-09, 8.102125381432264e-10, 1.2238869524277158e-09),
            sink=0.35649130332102746, tilt_deg=93.26128815213103, kind="apex",
        ),
        ParticleSpec(
            height=1.3087644496484267e-07, azimuth_deg=157.114081086488,
            semi_axes=(1.0323107377948187e-08, 1.0615882072374402e-08, 9.959722338238871e-09),
            sink=0.5, tilt_deg=0.0, kind="shank",
        ),
    )  # fmt: skip
    p = TemWaveParams(
        n=4.7366668126221665, R=2.064442314187435e-08, S=1.8412336697518783, z_join=1.5487035772891217e-08,
        shank_half_angle_deg=15.90732379327447, blend_length=1.4693259538333918e-08, asymmetry=0.0, layer="none",
        core_absorption_length_200kv=7.71799454779487e-08, contamination_contrast=0.29223853638014774,
        particles=parts, pixel_size=3.199799388638746e-10, shape=(512, 512),
        apex_px=(375.6836637853015, 268.0273893972472), rotation_deg=-12.868997880529273, orientation="down",
        kv=210.76417664391096, defocus=-1.535104054690477e-07, cs=0.0016948692717483722,
        aperture=0.019391317754447912, illumination_angle=9.855305675975593e-05, cc=0.0018847071260310144,
        energy_spread_ev=0.5048015950957105, snr=10.92070355601183, bits=0, background_level=0.6134003165305161,
        float_gain=19.55120512878217, read_noise=6.396207050778458, psf_sigma=0.5468976576800784,
        psf_tail_weight=0.02965179853472638, psf_tail_length=3.976297857669609,
        illumination_gradient=0.04953825777688009, gradient_angle_deg=74.67336336145856,
        vignetting=0.09367491499624946, seed=57,
    )  # fmt: skip
    g, fringe = _graded(tmp_path, p)
    assert not g["lost"], g["lost_reason"]
    assert fringe and "lambda x defocus -" in fringe[0], fringe  # overfocus found without the sign
    assert abs(g["edge_bias"]) < 0.2e-9, g["edge_bias"]  # +0.41 nm before, -0.11 nm now
    assert abs(g["dn"]) <= 0.1, g["dn"]
