"""Independent wave-optical TEM simulator (pipeline.synth.tem_wave): its physics against
textbook values and closed forms computed here, its noise and file output, its truth, and
the grader (pipeline.synth.tem_wave_truth)."""

from __future__ import annotations

import json
import math

import numpy as np
import pytest
from scipy.special import fresnel

from pipeline.synth import tem_wave_optics as opt
from pipeline.synth.tem_wave import (
    ParticleSpec,
    TemWaveParams,
    draw_params,
    main,
    simulate,
    simulate_intensity,
    tip_body,
    write_image,
)
from pipeline.synth.tem_wave_geometry import Particle, TipBody, limacon_chord, projected_thickness
from pipeline.synth.tem_wave_truth import edge_errors, grade, ideal_fit, tip_frame, true_section_area

pytestmark = pytest.mark.filterwarnings("error")


# ----------------------------------------------------------------------------- electron optics


@pytest.mark.parametrize(
    "kv, lam_pm, sigma_per_v_nm", [(100.0, 3.7014, 9.2437e-3), (200.0, 2.5079, 7.2884e-3), (300.0, 1.9687, 6.5262e-3)]
)
def test_wavelength_and_interaction_constant(kv, lam_pm, sigma_per_v_nm):
    """Textbook values (Kirkland Table 2.2 / EMsoft EMqg: 200 kV 2.508 pm and 7.288e-3 rad/(V nm),
    i.e. 7.29e-4 rad/(V Angstrom))."""
    assert opt.electron_wavelength(kv) == pytest.approx(lam_pm * 1e-12, rel=2e-4)
    assert opt.interaction_constant(kv) == pytest.approx(sigma_per_v_nm * 1e9, rel=1e-3)


def _clean(**kw):
    """A tip image with no aberrations, envelopes off (coherent), no particles, no asymmetry."""
    base = dict(
        n=2.0,
        R=20e-9,
        S=1.0,
        z_join=40e-9,
        layer="none",
        asymmetry=0.0,
        particles=(),
        pixel_size=0.25e-9,
        shape=(160, 160),
        apex_px=(120.3, 80.2),
        rotation_deg=0.0,
        defocus=0.0,
        cs=0.0,
        aperture=1.0,
        illumination_gradient=0.0,
        vignetting=0.0,
        noise=False,
        bits=0,
    )
    base.update(kw)
    return TemWaveParams(**base)


@pytest.mark.parametrize("v0, tol", [(0.0, 1e-3), (None, 4e-3)])
def test_in_focus_intensity_is_beer_lambert_of_the_chord(v0, tol):
    """In focus, Cs = 0, no aperture (only the grid's band limit): I = exp(-t / lambda) with
    t = 2 sqrt(r^2 - x^2) the chord of the paraboloid's circular section, r^2 = 2 R z.  Without
    a phase (V0 = 0) to 1e-3 from 1.5 nm inside the edge; with Si's 12.1 V the band-limited
    phase edge rings (Gibbs) by up to 4e-3 there, decaying inwards."""
    p = _clean(mean_inner_potential=(("Si", v0),) if v0 is not None else ())
    inten, _ = simulate_intensity(p, coherent=True)
    lam = p.absorption_lengths()["Si"]
    rows, cols = np.mgrid[0:160, 0:160].astype(float)
    x = (cols - p.apex_px[1]) * p.pixel_size
    z = (p.apex_px[0] - rows) * p.pixel_size
    r = np.sqrt(2 * p.R * np.maximum(z, 0))
    expect = np.exp(-2 * np.sqrt(np.maximum(r**2 - x**2, 0)) / lam)
    inner = (r - np.abs(x) > 1.5e-9) & (z > 2e-9) & (z < 30e-9)
    outer = (np.abs(x) - r > 2e-9) | (z < -2e-9)
    assert inner.sum() > 2000
    assert np.max(np.abs(inten[inner] - expect[inner])) < tol
    assert abs(np.mean(inten[inner] - expect[inner])) < 3e-4
    deep = inner & (r - np.abs(x) > 10e-9)
    assert np.max(np.abs(inten[deep] - expect[deep])) < 1e-3
    assert np.max(np.abs(inten[outer] - 1.0)) < 2e-3  # vacuum stays 1
    # the phase really is there: a weak phase object at 1 um defocus shows contrast outside
    p2 = _clean(defocus=1e-6)
    inten2, _ = simulate_intensity(p2, coherent=True)
    assert np.max(np.abs(inten2[outer] - 1.0)) > 0.05


@pytest.mark.parametrize("defocus", [0.5e-6, -0.5e-6, 2e-6])
def test_fresnel_fringes_of_a_straight_edge(defocus):
    """An opaque half-plane: intensity = |Fresnel integral|^2 with w = xi sqrt(2 / (lambda df)),
    first maximum at w = 1.2172, i.e. spacing ~ sqrt(lambda df) (Reimer & Kohl Sec. 3.2)."""
    kv, dx = 200.0, 0.02e-9
    nx = 8192
    x = (np.arange(nx) + 0.5) * dx
    x0, x1 = 60e-9, 120e-9
    psi = np.where((x > x0) & (x < x1), 0.0, 1.0)[None, :].repeat(4, axis=0).astype(complex)
    o = opt.Optics(kv=kv, defocus=defocus, cs=0.0, aperture=1.0)
    inten = opt.image_intensity(psi, dx, o, coherent=True)[0]
    lam = opt.electron_wavelength(kv)
    xi = x0 - x  # distance into the lit side
    w = xi * math.sqrt(2.0 / (lam * abs(defocus)))
    S, C = fresnel(w)
    expect = 0.5 * ((0.5 + C) ** 2 + (0.5 + S) ** 2)
    near = (xi > -2e-9) & (xi < 4 * math.sqrt(lam * abs(defocus)))
    assert np.max(np.abs(inten[near] - expect[near])) < 0.02
    lit = (xi > 0) & (xi < 3 * math.sqrt(lam * abs(defocus)))
    x_max = xi[lit][np.argmax(inten[lit])]
    assert x_max == pytest.approx(1.2172 * math.sqrt(lam * abs(defocus) / 2), rel=0.02)


def test_envelopes_damp_fringes_and_aperture_cuts():
    kv, dx = 200.0, 0.05e-9
    k = np.array([0.0, 2e9, 5e9])
    o = opt.Optics(kv=kv, defocus=1e-6, cs=1e-3, aperture=10e-3, illumination_angle=0.2e-3, focal_spread=4e-9)
    tf = opt.transfer_function((1, 4096), dx, o)[0]
    kx = np.fft.fftfreq(4096, dx)
    lam = opt.electron_wavelength(kv)
    for kk in k:
        i = int(np.argmin(np.abs(kx - kk)))
        kr = kx[i]
        reach = o.cs * lam**3 * kr**3 - o.defocus * lam * kr
        es = math.exp(-((math.pi * o.illumination_angle / lam) ** 2) * reach**2)
        et = math.exp(-0.5 * (math.pi * lam * o.focal_spread) ** 2 * kr**4)
        expect = es * et if lam * kr <= o.aperture else 0.0
        assert abs(tf[i]) == pytest.approx(expect, abs=1e-6)
    # focal spread from Cc dE/E (relativistic factor (1 + 2 eps) / (1 + eps) with eps = eU / 2m0c^2)
    eps = 200e3 / (2 * opt.REST_ENERGY_EV)
    assert opt.focal_spread(1.4e-3, 0.4, 200.0) == pytest.approx(1.4e-3 * 0.4 / 200e3 * (1 + 2 * eps) / (1 + eps))


# ----------------------------------------------------------------------------- geometry


def test_chords_of_paraboloid_sphere_and_limacon():
    rng = np.random.default_rng(1)
    R = 15e-9
    body = TipBody(2.0, R, z_join=50e-9)
    x, z = rng.uniform(-30e-9, 30e-9, 4000), rng.uniform(-2e-9, 45e-9, 4000)
    expect = 2 * np.sqrt(np.maximum(2 * R * z - x**2, 0.0))
    assert np.allclose(body.outer_chord(x, z), expect, rtol=1e-12, atol=1e-20)
    # sphere (particle far from the tip): 2 sqrt(a^2 - rho^2); volume of an ellipsoid by quadrature
    a = 2e-9
    sph = Particle((100e-9, 0.0, 30e-9), (a, a, a), 0.0, "aC", "shank", 1)
    ell = Particle((100e-9, 0.0, 30e-9), (2e-9, 1e-9, 1.5e-9), 0.6, "aC", "shank", 1)
    g = np.linspace(-2.5e-9, 2.5e-9, 801)
    X, Z = np.meshgrid(100e-9 + g, 30e-9 + g)
    vol = projected_thickness(body, [ell], X, Z)["aC"].sum() * (g[1] - g[0]) ** 2
    assert vol == pytest.approx(4 / 3 * math.pi * 2e-9 * 1e-9 * 1.5e-9, rel=2e-3)
    xr = 100e-9 + np.linspace(-1.9e-9, 1.9e-9, 50)
    th = projected_thickness(body, [sph], xr, np.full(50, 30e-9))["aC"]
    assert np.allclose(th, 2 * np.sqrt(a**2 - (xr - 100e-9) ** 2), rtol=1e-9)
    # limacon section rho = r (1 + e cos phi): brute-force chord along y, and the section area
    r, e = 10e-9, 0.05
    xs = np.linspace(-1.2 * r, 1.2 * r, 61)
    y = np.linspace(-1.2 * r, 1.2 * r, 200001)
    for xi in xs:
        s = np.hypot(xi, y)
        inside = s < r * (1 + e * np.divide(xi, s, out=np.ones_like(s), where=s > 0))
        assert limacon_chord(xi, r, e) == pytest.approx(inside.sum() * (y[1] - y[0]), abs=3 * (y[1] - y[0]))
    xf = np.linspace(-1.2 * r, 1.2 * r, 200001)
    assert limacon_chord(xf, r, e).sum() * (xf[1] - xf[0]) == pytest.approx(math.pi * r**2 * (1 + e**2 / 2), rel=1e-6)


def test_particle_sunk_into_the_tip_counts_only_outside():
    """A sphere centred on the surface: its chord minus the part inside the tip (brute force along y)."""
    body = TipBody(2.0, 20e-9, z_join=50e-9)
    z0 = 10e-9
    r0 = float(body.radius(z0))
    p = Particle((r0, 0.0, z0), (3e-9, 3e-9, 3e-9), 0.0, "aC", "apex", 1)
    xq = r0 + np.linspace(-2.5e-9, 2.5e-9, 21)
    zq = np.full(21, z0 + 0.7e-9)
    got = projected_thickness(body, [p], xq, zq)["aC"]
    y = np.linspace(-30e-9, 30e-9, 600001)
    for xi, zi, g in zip(xq, zq, got):
        in_sph = (xi - r0) ** 2 + y**2 + (zi - z0) ** 2 < 9e-18
        in_tip = xi**2 + y**2 < 2 * 20e-9 * zi
        assert g == pytest.approx(np.sum(in_sph & ~in_tip) * (y[1] - y[0]), abs=3e-13)


def test_core_is_the_inner_parallel_surface():
    """Erosion of a paraboloid (R = 20 nm) by t = 5 nm < R: the inner offset curve
    (r - t f'/sqrt(1+f'^2), f + t/sqrt(1+f'^2)) lies on the core radius table."""
    R, t = 20e-9, 5e-9
    body = TipBody(2.0, R, z_join=200e-9, layer_thickness=t, z_max=300e-9)
    r = np.linspace(0, 40e-9, 200)
    f, fp = r**2 / (2 * R), r / R
    ro = r - t * fp / np.sqrt(1 + fp**2)
    zo = f + t / np.sqrt(1 + fp**2)
    assert np.allclose(body.core_radius(zo[1:]), ro[1:], atol=2e-12)
    assert body.core_radius(t - 0.05e-9) < 0 < body.core_radius(t + 0.05e-9)


# ----------------------------------------------------------------------------- detector


def test_poisson_statistics_and_detector_noise():
    rng = np.random.default_rng(3)
    flat = np.full((256, 256), 400.0)
    det = opt.Detector(psf_sigma=0.0, tail_weight=0.0, gain=1.0, bits=0)
    img = opt.detect(flat, det, rng).astype(float)
    assert img.mean() == pytest.approx(400, rel=5e-3)
    assert img.var() == pytest.approx(400, rel=0.03)  # Poisson: variance = mean (SE of the variance 0.6 %)
    det = opt.Detector(psf_sigma=0.6, tail_weight=0.1, tail_length=3.0, gain=2.5, read_noise=4.0, offset=100, bits=0)
    img = opt.detect(flat, det, rng).astype(float)
    nu = opt.noise_variance_factor(flat.shape, det)
    assert 0.1 < nu < 0.5  # a Gaussian PSF alone: 1 / (4 pi sigma^2) = 0.22
    assert img.mean() == pytest.approx(400 * 2.5 + 100, rel=5e-3)
    assert img.var() == pytest.approx(2.5**2 * 400 * nu + 16, rel=0.05)


def test_snr_setting_gives_that_snr_in_the_saved_image():
    p = draw_params(
        11,
        layer="none",
        particles=(),
        bits=16,
        background_level=0.5,
        illumination_gradient=0.0,
        vignetting=0.0,
        shape=(320, 320),
        pixel_size=0.3e-9,
        snr=12.0,
    )
    img, truth = simulate(p)
    r_a, c_a = truth["apex_px"]
    vac = img[max(0, int(r_a) + 20) :, :].astype(float)
    vac = vac[:, : min(100, vac.shape[1])]
    assert vac.std() == pytest.approx(truth["noise_sigma"], rel=0.1)
    assert truth["vacuum_level"] == pytest.approx(vac.mean(), rel=0.02)


def test_quantisation_clipping_and_dtypes():
    kw = dict(
        layer="none", particles=(), shape=(256, 256), pixel_size=0.3e-9, illumination_gradient=0.0, vignetting=0.0
    )
    img8, t8 = simulate(draw_params(2, bits=8, background_level=1.2, **kw))
    assert img8.dtype == np.uint8 and img8.max() == 255
    r_a = int(t8["apex_px"][0])
    below = img8[r_a + 15 :] if t8["orientation"] == "down" else img8[: r_a - 15]
    assert np.mean(below == 255) > 0.5 and t8["saturated_fraction"] > 0.2  # saturated vacuum
    img16, t16 = simulate(draw_params(2, bits=16, background_level=0.4, **kw))
    assert img16.dtype == np.uint16 and img16.max() < 65535 and t16["saturated_fraction"] == 0
    imgf, _ = simulate(draw_params(2, bits=0, **kw))
    assert imgf.dtype == np.float32 and np.any(imgf != np.rint(imgf))


def test_deterministic_by_seed():
    kw = dict(shape=(256, 256), pixel_size=0.3e-9)
    a, ta = simulate(draw_params(7, **kw))
    b, tb = simulate(draw_params(7, **kw))
    c, _ = simulate(draw_params(8, **kw))
    assert np.array_equal(a, b) and not np.array_equal(a, c[: a.shape[0], : a.shape[1]] if c.shape == a.shape else c)
    assert json.dumps(ta["params"], default=str) == json.dumps(tb["params"], default=str)


# ----------------------------------------------------------------------------- truth


def test_truth_silhouette_is_the_outer_surface():
    p = draw_params(
        5,
        asymmetry=0.04,
        layer="DLC",
        layer_thickness=8e-9,
        shape=(256, 256),
        pixel_size=0.3e-9,
        particles=(ParticleSpec(6e-9, 0.0, (2e-9, 1.5e-9, 2e-9)),),
    )
    img, truth = simulate(p)
    body = tip_body(p)
    xs, zs = truth["silhouette_tip"].T
    # back from image coordinates to the tip frame
    xb, zb = tip_frame(truth["silhouette_px"], truth)
    assert np.allclose(xb, xs, atol=1e-15) and np.allclose(zb, zs, atol=1e-15)
    m = (zs > 0.2e-9) & (zs < 60e-9)
    inward = np.where(xs[m] > 0, -1.0, 1.0) * 0.01e-9
    assert np.all(body.outer_chord(xs[m] + inward, zs[m]) > 0)
    assert np.all(body.outer_chord(xs[m] - inward, zs[m]) == 0)
    rl, rr = truth["flank_r_left"], truth["flank_r_right"]
    ok = truth["flank_z"] > 1e-9
    assert np.allclose(rr[ok] / rl[ok], 1.04 / 0.96)
    assert truth["particle_flank"] == "right" and truth["particles"][0]["height"] == 6e-9
    # pull-off truth: the power law's area pi (n h Q)^(2/n) (1 + e^2/2) below the join
    h = np.array([1e-9, 6e-9])
    assert np.allclose(true_section_area(truth, h), np.pi * (p.n * h * p.Q) ** (2 / p.n) * (1 + 0.04**2 / 2), rtol=1e-3)
    assert truth["Q"] == pytest.approx(p.S ** (p.n - 2) * p.R ** (p.n - 1))


def test_padding_leaves_the_apex_alone():
    """Doubling the FFT padding (2 um defocus, the shank cut at the padding's edge) changes
    the image near the apex by < 1e-3."""
    p = _clean(defocus=2e-6, cs=1e-3, aperture=15e-3, shape=(128, 128), apex_px=(96.4, 64.1), pixel_size=0.2e-9)
    a, (m, dx, pad) = simulate_intensity(p)
    b, _ = simulate_intensity(p, pad=2 * pad)
    sel = np.s_[60:128, 20:108]
    assert np.max(np.abs(a[sel] - b[sel])) < 1e-3
    # and too little padding would have shown (the check can fail)
    c, _ = simulate_intensity(p, pad=8)
    assert np.max(np.abs(c[sel] - b[sel])) > 5e-3


# ----------------------------------------------------------------------------- grader and files


def test_grader_on_the_true_silhouette():
    """A profile that IS the true silhouette grades to edge RMS ~ 0 and n as the ideal fit."""
    from types import SimpleNamespace

    from pipeline.fits.profile_fit import fit_power_law

    p = draw_params(4, asymmetry=0.0, shape=(256, 256), pixel_size=0.3e-9)
    _, truth = simulate(p)
    xs, zs = truth["silhouette_tip"].T
    keep = zs <= 20e-9
    prof = SimpleNamespace(
        edge_px=truth["silhouette_px"][keep],
        apex_px=np.array(truth["apex_px"]),
        angle=math.radians(truth["rotation_deg"]),
        z=zs[keep],
        x=xs[keep],
        edge_model={"coating_thickness": 0.0},
    )
    e = edge_errors(prof.edge_px, truth, prof.z <= 6e-9)
    assert e["rms"] < 1e-13 and e["n_points"] > 100
    fit = fit_power_law(np.abs(xs[keep]), zs[keep], 6e-9, groups=np.where(xs[keep] < 0, -1, 1))
    g = grade(prof, fit, truth)
    assert abs(g["dn"]) < 0.01 and abs(g["dn_ideal"]) < 0.01 and g["pulloff_error"] < 0.01
    assert g["apex_error"] < 1e-15 and not g["lost"]
    # a flank offset by 0.3 nm along x reads back as 0.3 nm (times the normal's x component)
    shifted = truth["silhouette_px"][keep] + np.array([0.0, 0.3e-9 / truth["pixel_size"]])
    e2 = edge_errors(shifted, truth, zs[keep] <= 6e-9)
    assert 0.05e-9 < e2["rms"] < 0.3e-9
    assert ideal_fit(truth).n == pytest.approx(p.n, abs=0.01)


@pytest.mark.parametrize("sn", [0.3, 0.8])
def test_sampled_pulloff_coverage_is_calibrated(sn):
    """Fits whose (n, ln Q) error truly follows their covariance (drawn about the exact silhouette's fit)
    are covered at 2 sigma by ``pulloff_covered_by_samples`` in ~95 % of draws, also at sigma_n 0.8
    where the area factor is far from linear in n (measured 0.96 at both)."""
    from types import SimpleNamespace

    from pipeline.synth.tem_wave_truth import pulloff_covered_by_samples

    p = draw_params(4, asymmetry=0.0, shape=(256, 256), pixel_size=0.3e-9)
    _, truth = simulate(p)
    fit = ideal_fit(truth)
    cov = np.array([[sn**2, 0.72 * sn**2], [0.72 * sn**2, 0.81 * sn**2]])  # correlation 0.8
    rng = np.random.default_rng(1)
    hits = 0
    for k in range(200):
        n, ln_q = rng.multivariate_normal([fit.n, fit.ln_Q], cov)
        hits += pulloff_covered_by_samples(SimpleNamespace(n=n, ln_Q=ln_q, S=fit.S, cov_n_lnQ=cov), truth, seed=k)
    assert 0.90 <= hits / 200 <= 0.99, hits


def test_common_offset_sd_of_the_edge_covariance():
    """The grader's reported SD of the edge's mean offset: a common offset of SD s in the covariance
    reads back as s (B-spline rows sum to 1); independent knots average down; no covariance, NaN."""
    from types import SimpleNamespace

    from pipeline.synth.tem_wave_truth import common_offset_sd

    rng = np.random.default_rng(0)
    basis = rng.random((50, 8))
    basis /= basis.sum(axis=1, keepdims=True)
    sel = np.arange(50) < 30
    common = SimpleNamespace(offset_basis=basis, offset_cov=0.2e-9**2 * np.ones((8, 8)))
    assert common_offset_sd(common, sel) == pytest.approx(0.2e-9, rel=1e-12)
    indep = SimpleNamespace(offset_basis=basis, offset_cov=0.2e-9**2 * np.eye(8))
    a = basis[sel].mean(axis=0)
    assert common_offset_sd(indep, sel) == pytest.approx(0.2e-9 * np.sqrt(a @ a), rel=1e-12)
    assert math.isnan(common_offset_sd(SimpleNamespace(), sel))


def test_cli_writes_calibrated_images(tmp_path):
    from pipeline.tem.reading import read_tem_image

    main(["--out", str(tmp_path), "--n", "1", "--seed", "40"])
    tif = tmp_path / "tem_wave_0040.tif"
    truth = json.loads((tmp_path / "tem_wave_0040_truth.json").read_text())
    im = read_tem_image(tif)
    assert im.pixel_size == pytest.approx(truth["pixel_size"], rel=1e-6)
    assert im.data.shape == tuple(truth["shape"])
    assert (tmp_path / "tem_wave_0040_truth.png").is_file()
    img = np.arange(256, dtype=np.uint16).reshape(16, 16)
    write_image(tmp_path / "a.png", img, 0.2e-9)
    assert read_tem_image(tmp_path / "a.png", 0.2e-9).source == "tip YAML"
