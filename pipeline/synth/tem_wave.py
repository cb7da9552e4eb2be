"""Independent bright-field TEM image simulator of a worn AFM tip, with known truth.

The TEM stage (``pipeline.tem``) fits a Beer-Lambert projection model with a Gaussian blur
to the image; its tests draw images from that same model (``pipeline.synth.tem_image``).
This simulator forms the image wave-optically instead and shares no code with either: it
is the test bed for the edge extraction on physics the fit does not model (issue 16).

Physics, in order (SI units inside; the references are listed at the end)

1. Tip (``tem_wave_geometry``): a worn apex z = r^n / (n Q) (paper Eq. 1 with
   Q = S^(n-2) R^(n-1), Eq. 2) up to z_join, eased into a cone of half angle 10-25 deg;
   sections rho = r(z) (1 + e cos phi) (flanks r (1 + e) and r (1 - e): up to 10 % apart for
   |e| <= 0.05); a crystalline Si core; an outer layer of normal thickness t (native oxide
   SiO2 1-2 nm or DLC 2-20 nm) whose OUTER surface is the power law (what touches the
   sample); amorphous-carbon contamination particles (ellipsoids 1-5 nm) partly sunk into
   ONE flank 3-20 nm above the apex, and larger ones (6-24 nm) far up the shank.  Projected
   thickness of each material along the beam: closed-form chords per point of a grid
   finer than the pixel (``grid_step``, default <= 0.1 nm), averaged over 4 x 4
   sub-points where a material boundary crosses a grid cell.
2. Exit wave: psi = exp(sum_m [i sigma(U) V_m - 1 / (2 lambda_m)] t_m) with V_m the mean
   inner potential and lambda_m the absorption length of material m (the intensity of a
   slab falls as exp(-t / lambda): scattering outside the objective aperture).
3. Objective lens (``tem_wave_optics``): Fresnel propagation by the defocus, spherical
   aberration, a sharp objective aperture, Frank / Wade-Frank envelopes of partial
   spatial and temporal coherence.  The field is padded by more than the largest
   delocalisation |d chi/dk| / 2 pi of any transferred frequency plus a taper in which the
   exit wave is blended to vacuum, so nothing from the padding's edge (where the shank is
   cut) reaches the image.  Intensity integrated over each detector pixel (its box MTF).
4. Illumination (linear gradient and radial vignetting) x dose -> Poisson electrons ->
   scintillator PSF -> gain, offset, read noise -> 8/16-bit rounding with clipping (a
   saturated vacuum where the background level is set above full scale) or float32.

Dose from ``snr``: SNR = (I_vacuum - I_ref) / sigma_vacuum in the saved image, I_ref the
absorption-only intensity on the axis 3 nm above the CORE's apex (through the core and the
layer), sigma_vacuum the noise in vacuum after the PSF (Poisson, read noise, rounding).
A faint layer's own SNR is lower by its contrast.

Parameter ranges drawn by ``draw_params`` (every one can be fixed by a keyword)

| parameter | range | note |
|---|---|---|
| n, R, S | 2-6, 8-35 nm, 1-2 | R lowered until the tip 26 nm up fits in 55 % of the field |
| power law up to z_join | 8-30 nm | then eased (10-40 nm) into a 10-25 deg cone |
| asymmetry e | 0 (half of the draws) or 0.01-0.05, either sign | flanks differ by 2e |
| layer | none 30 %, oxide 35 % (1-2 nm), DLC 35 % (2-20 nm) | |
| layer / core attenuation kappa | oxide 0.2-0.5, DLC 0.05-0.30 | lambda_layer = lambda_core / kappa |
| core absorption length at 200 kV | 25-80 nm | crystalline Si: mass thickness + Bragg scattering |
| particles near the apex | half: 1-3 on one flank (20 deg of the image plane), 3-20 nm up, 1-5 nm | a-C |
| shank contamination | half of the draws: 1-3 blobs 6-24 nm, 30 nm up or more | a-C |
| accelerating voltage | 100-300 kV | lambda ~ beta^2 (elastic cross-sections ~ 1/beta^2) |
| defocus | 20 % within 0.1 um of focus, 30 % within 0.5 um, 50 % -2..+2 um | Fresnel fringes ~ sqrt(lambda df) wide |
| Cs, objective aperture | 0.5-2 mm, 5-20 mrad | |
| illumination semi-angle, Cc, energy spread | 0.02-0.3 mrad, 1.2-2.5 mm, 0.3-0.6 eV rms | |
| pixel size, image side | 0.1-0.5 nm, 256-1024 px (field 60-220 nm) | |
| rotation, orientation | -15..15 deg, apex down 80 % / up 20 % | |
| SNR | 5-30 | |
| bit depth | 8 (35 %), 16 (50 %), float32 (15 %) | 15 % of 8/16-bit: vacuum at 1.02-1.2 x full scale |
| PSF | Gaussian 0.3-0.8 px + tail 0-15 % over 2-5 px | |
| read noise, offset | 16 bit: 1-8 DN, 0-300 DN; 8 bit: 0.2-1 DN, 0-8 DN | |
| illumination | gradient 0-8 % across the field, vignetting 0-10 % | |

Materials (mean inner potential V0; absorption length lambda as the image shows it)

| material | V0 (V) | lambda | source / assumption |
|---|---|---|---|
| Si (crystalline core) | 12.1 | 25-80 nm at 200 kV | 11.5-12.6 V (holography, DFT; Kruse et al. 2003) |
| SiO2 (native oxide) | 10.1 | lambda_core / (0.2-0.5) | amorphous SiO2 ~10 V (holography, 9.5-11 V) |
| DLC (a-C:H coating) | 9.5 | lambda_core / (0.05-0.30) | a-C 9.09 V at 1.75 g/cm^3 (Wanner et al. 2006) |
| a-C contamination | 8.0 | lambda_core / (0.1-0.3) | hydrocarbon contamination, less dense than a-C: 7-9 V |

Absorption lengths (assumption, order of magnitude): elastic scattering outside a 10 mrad
aperture at 200 kV (screened-Rutherford cross-sections, Egerton 2011 Sec. 3.1; the fraction
1 / (1 + alpha^2 / theta_0^2) beyond the aperture, Lenz screening angle theta_0 =
lambda / (2 pi a), a = 0.885 a_0 Z^(-1/3)) gives mass-thickness lengths of order 150-300 nm
for a-C (2 g/cm^3) and 80-160 nm for amorphous Si: a ratio ~0.5.  The crystalline core
loses more to Bragg beams outside the aperture (extinction distances of Si 60-80 nm at
200 kV), hence 25-80 nm; a-C:H is less dense than a-C.  Together they give the 5-30 %
layer/core contrast the issue describes; kappa (= lambda_core / lambda_layer) is drawn
directly.  All lengths scale with beta^2 (v/c squared) between voltages.

References: E. J. Kirkland, Advanced Computing in Electron Microscopy, 2nd ed. (Springer
2010), Ch. 2-3, 5 (wavelength, interaction constant, transfer function, envelopes);
L. Reimer, H. Kohl, Transmission Electron Microscopy, 5th ed. (Springer 2008), Ch. 3, 6
(Fresnel fringes, partial coherence, contrast); J. Frank, Optik 38 (1973) 519 (spatial
coherence envelope); R. H. Wade, J. Frank, Optik 49 (1977) 81 (temporal envelope);
M. Wanner et al., Ultramicroscopy 106 (2006) 341 (a-C mean inner potential 9.09 V);
P. Kruse et al., Ultramicroscopy 96 (2003) 11 (Si mean inner potential); R. F. Egerton,
Electron Energy-Loss Spectroscopy in the Electron Microscope, 3rd ed. (Springer 2011).

Use: ``image, truth = simulate(draw_params(seed))``; ``python -m pipeline.synth.tem_wave
--out DIR --n 12`` writes sample images (TIFF with the calibration, an 8-bit PNG preview,
an overlay of the true silhouette and truth JSON).  The grader is
``pipeline.synth.tem_wave_truth``.
"""

from __future__ import annotations

import argparse
import json
import math
from dataclasses import asdict, dataclass, replace
from pathlib import Path

import numpy as np
from scipy import fft as sfft

from pipeline.synth.tem_wave_geometry import TipBody, place_particle, projected_thickness
from pipeline.synth.tem_wave_optics import (
    Detector,
    Optics,
    band_limit,
    delocalisation,
    detect,
    electron_beta2,
    focal_spread,
    image_intensity,
    interaction_constant,
    noise_variance_factor,
)

__all__ = [
    "MEAN_INNER_POTENTIAL",
    "ParticleSpec",
    "TemWaveParams",
    "draw_params",
    "simulate",
    "simulate_intensity",
    "tip_body",
    "write_image",
    "truth_to_json",
    "main",
]

# Mean inner potentials (V); see the module doc for sources.
MEAN_INNER_POTENTIAL = {"Si": 12.1, "SiO2": 10.1, "DLC": 9.5, "aC": 8.0}
LAYER_MATERIAL = {"none": None, "oxide": "SiO2", "DLC": "DLC"}
_SUPERSAMPLE = 4  # sub-points per grid cell edge where a material boundary crosses it
_TAPER = 4e-9  # m over which the exit wave is blended to vacuum at the padding's edge


@dataclass(frozen=True)
class ParticleSpec:
    """A contamination particle: ``height`` above the apex (m) where it touches the surface,
    ``azimuth_deg`` (0 = right flank in the image plane, 180 = left, 90 = towards the
    viewer), ``semi_axes`` (a, b, c) m (a, b in the x-z plane, c along the beam), ``sink``
    (centre at sink x a from the surface, < 1 = partly sunk in), ``tilt_deg`` (in-plane),
    ``kind`` ("apex" or "shank")."""

    height: float
    azimuth_deg: float
    semi_axes: tuple
    sink: float = 0.6
    tilt_deg: float = 0.0
    kind: str = "apex"


@dataclass(frozen=True)
class TemWaveParams:
    """Everything that defines one simulated image (SI units; angles in degrees or rad as named)."""

    # tip shape (Eq. 1, 2)
    n: float = 4.0
    R: float = 20e-9
    S: float = 1.0
    z_join: float = 15e-9
    shank_half_angle_deg: float = 15.0
    blend_length: float = 20e-9
    asymmetry: float = 0.0
    # materials
    layer: str = "none"  # "none", "oxide", "DLC"
    layer_thickness: float = 0.0
    core_absorption_length_200kv: float = 50e-9
    layer_contrast: float = 0.2  # kappa = lambda_core / lambda_layer
    contamination_contrast: float = 0.2
    mean_inner_potential: tuple = ()  # ((material, V), ...) overrides of MEAN_INNER_POTENTIAL
    particles: tuple = ()  # ParticleSpec, ...
    # image geometry
    pixel_size: float = 0.25e-9
    shape: tuple = (512, 512)
    apex_px: tuple = (358.3, 255.7)  # (row, col), pixel centres at integers
    rotation_deg: float = 0.0
    orientation: str = "down"
    # optics
    kv: float = 200.0
    defocus: float = 0.5e-6  # > 0 underfocus
    cs: float = 1.0e-3
    aperture: float = 10e-3
    illumination_angle: float = 0.05e-3
    cc: float = 1.4e-3
    energy_spread_ev: float = 0.4  # rms
    # illumination and detector
    snr: float = 15.0
    bits: int = 16  # 8, 16, 0 = float32
    background_level: float = 0.6  # vacuum at the field centre, fraction of full scale (> 1 saturates)
    float_gain: float = 1.0  # DN per electron of a float32 image
    offset: float = 0.0  # DN
    read_noise: float = 2.0  # DN rms
    psf_sigma: float = 0.5  # px
    psf_tail_weight: float = 0.05
    psf_tail_length: float = 3.0  # px
    illumination_gradient: float = 0.03  # relative change across the field
    gradient_angle_deg: float = 30.0
    vignetting: float = 0.0  # relative drop at the field corners
    # simulation
    grid_step: float = 0.1e-9  # target step of the wave grid (m); the pixel is split into m x m
    noise: bool = True
    seed: int = 0

    @property
    def Q(self):
        """Q of Eq. 1 from Eq. 2: S^(n-2) R^(n-1) (m^(n-1))."""
        return self.S ** (self.n - 2.0) * self.R ** (self.n - 1.0)

    def optics(self):
        return Optics(
            kv=self.kv,
            defocus=self.defocus,
            cs=self.cs,
            aperture=self.aperture,
            illumination_angle=self.illumination_angle,
            focal_spread=focal_spread(self.cc, self.energy_spread_ev, self.kv),
        )

    def potentials(self):
        return {**MEAN_INNER_POTENTIAL, **dict(self.mean_inner_potential)}

    def absorption_lengths(self):
        """Absorption length (m) of each material at this voltage (lambda ~ beta^2)."""
        core = self.core_absorption_length_200kv * electron_beta2(self.kv) / electron_beta2(200.0)
        out = {"Si": core, "aC": core / self.contamination_contrast}
        mat = LAYER_MATERIAL[self.layer]
        if mat:
            out[mat] = core / self.layer_contrast
        return out


def tip_body(p: TemWaveParams, z_max=600e-9) -> TipBody:
    """The tip geometry of ``p`` (outer layer included)."""
    return TipBody(
        p.n,
        p.Q,
        z_join=p.z_join,
        shank_slope=math.tan(math.radians(p.shank_half_angle_deg)),
        blend_length=p.blend_length,
        asymmetry=p.asymmetry,
        layer_thickness=p.layer_thickness if p.layer != "none" else 0.0,
        z_max=z_max,
    )


# ----------------------------------------------------------------------------- frames


def _tip_coords(rows, cols, p):
    """Image (row, col) -> tip frame (x, z) in m (apex at 0, z up the tip; rotation
    counter-clockwise as displayed with the apex down; "up" = the "down" image flipped)."""
    th = math.radians(p.rotation_deg)
    sgn = 1.0 if p.orientation == "down" else -1.0
    dx = (cols - p.apex_px[1]) * p.pixel_size
    dy = sgn * (p.apex_px[0] - rows) * p.pixel_size
    return dx * math.cos(th) + dy * math.sin(th), -dx * math.sin(th) + dy * math.cos(th)


def _image_coords(x, z, p):
    """Tip frame (x, z) in m -> image (row, col)."""
    th = math.radians(p.rotation_deg)
    sgn = 1.0 if p.orientation == "down" else -1.0
    dx = x * math.cos(th) - z * math.sin(th)
    dy = x * math.sin(th) + z * math.cos(th)
    return p.apex_px[0] - sgn * dy / p.pixel_size, p.apex_px[1] + dx / p.pixel_size


# ----------------------------------------------------------------------------- exit wave


def _sampling(p):
    """(m, dx, pad): grid cells per pixel edge, grid step (m), padding (grid cells)."""
    H, W = p.shape
    m = max(2, int(math.ceil(p.pixel_size / p.grid_step - 1e-9)))
    m = max(2, min(m, 4096 // max(H, W)))
    dx = p.pixel_size / m
    reach = delocalisation(p.optics(), dx)
    pad = int(math.ceil((reach + _TAPER + 2e-9) / dx))
    return m, dx, pad


def _exit_wave_rows(body, particles, p, m, pad, rows, ncols, pot, lam_abs, sigma):
    """Exit wave on grid rows ``rows`` (all ``ncols`` columns) and the material masks there."""
    gr = (rows[:, None] - pad + 0.5) / m - 0.5  # detector row coordinate of each grid point
    gc = (np.arange(ncols)[None, :] - pad + 0.5) / m - 0.5
    x, z = _tip_coords(gr, gc, p)
    x, z = np.broadcast_arrays(x, z)
    th = projected_thickness(body, particles, x, z)
    return _wave(th, pot, lam_abs, sigma, p), {k: v > 0 for k, v in th.items()}


def _material_of(key, p):
    return "Si" if key == "core" else (LAYER_MATERIAL[p.layer] if key == "layer" else key)


def _wave(th, pot, lam_abs, sigma, p):
    """psi = exp(sum_m [i sigma V_m - 1/(2 lambda_m)] t_m) from the projected thicknesses ``th``."""
    att = np.zeros(th["core"].shape)
    phase = np.zeros(th["core"].shape)
    for key, t in th.items():
        mat = _material_of(key, p)
        if mat is not None:
            att += t * (0.5 / lam_abs[mat])
            phase += t * (sigma * pot[mat])
    amp = np.exp(-att)
    return amp * np.cos(phase) + 1j * (amp * np.sin(phase))


def exit_wave(p: TemWaveParams, body=None, particles=None, pad=None):
    """Exit wave (complex64) on the padded simulation grid, and (m, dx, pad).

    Grid point (i, j) sits at detector coordinates ((i - pad + 0.5)/m - 0.5, (j - pad + 0.5)/m - 0.5).
    Cells crossed by a material boundary are averaged over 4 x 4 sub-points; the outer
    ``_TAPER`` of the padding is blended to vacuum (psi = 1).
    """
    H, W = p.shape
    m, dx, pad0 = _sampling(p)
    pad = pad0 if pad is None else pad
    n_r, n_c = sfft.next_fast_len(H * m + 2 * pad), sfft.next_fast_len(W * m + 2 * pad)
    body = body or tip_body(p, z_max=_z_extent(p, pad, m))
    particles = particles if particles is not None else _particles(body, p)
    pot, lam_abs, sigma = p.potentials(), p.absorption_lengths(), interaction_constant(p.kv)
    psi = np.empty((n_r, n_c), np.complex64)
    masks = {}
    for r0 in range(0, n_r, 256):
        rows = np.arange(r0, min(n_r, r0 + 256), dtype=float)
        w, mk = _exit_wave_rows(body, particles, p, m, pad, rows, n_c, pot, lam_abs, sigma)
        psi[r0 : r0 + len(rows)] = w
        for k, v in mk.items():
            masks.setdefault(k, np.zeros((n_r, n_c), bool))[r0 : r0 + len(rows)] = v
    # cells where any material boundary passes (a mask differs from a 4-neighbour's):
    # average the wave over sub-points
    band = np.zeros((n_r, n_c), bool)
    for v in masks.values():
        d0, d1 = v[1:] != v[:-1], v[:, 1:] != v[:, :-1]
        band[1:] |= d0
        band[:-1] |= d0
        band[:, 1:] |= d1
        band[:, :-1] |= d1
    ib, jb = np.nonzero(band)
    if ib.size:
        ss = _SUPERSAMPLE
        sub = (np.arange(ss) + 0.5) / ss - 0.5
        gr = ((ib[:, None, None] + sub[None, :, None]) - pad + 0.5) / m - 0.5
        gc = ((jb[:, None, None] + sub[None, None, :]) - pad + 0.5) / m - 0.5
        x, z = _tip_coords(gr, gc, p)
        x, z = np.broadcast_arrays(x, z)
        th = projected_thickness(body, particles, x, z)
        psi[ib, jb] = _wave(th, pot, lam_abs, sigma, p).mean(axis=(1, 2))
    # blend to vacuum over the outer taper of the padding (sin^2 ramp): psi = 1 + w (psi - 1)
    nt = max(2, int(round(_TAPER / dx)))
    psi -= 1
    for axis, n in ((0, n_r), (1, n_c)):
        d = np.minimum(np.arange(n), n - 1 - np.arange(n)).astype(float)
        w = (np.sin(0.5 * np.pi * np.clip(d / nt, 0.0, 1.0)) ** 2).astype(np.float32)
        psi *= w[:, None] if axis == 0 else w[None, :]
    psi += 1
    return psi, (m, dx, pad)


def _z_extent(p, pad, m):
    """Largest tip-frame height (m) on the padded grid (for the core table)."""
    H, W = p.shape
    e = pad / m + 2
    rr = np.array([-e, -e, H + e, H + e])
    cc = np.array([-e, W + e, -e, W + e])
    _, z = _tip_coords(rr, cc, p)
    return float(max(z.max(), 50e-9)) + 20e-9


def _particles(body, p):
    return [
        place_particle(
            body, s.height, math.radians(s.azimuth_deg), s.semi_axes, s.sink, math.radians(s.tilt_deg), "aC", s.kind
        )
        for s in p.particles
    ]


# ----------------------------------------------------------------------------- image


def simulate_intensity(p: TemWaveParams, pad=None, coherent=False, body=None):
    """Noise-free image intensity per detector pixel relative to the incident beam (vacuum = 1),
    before illumination and detector; and the simulation grid (m, dx, pad).  ``pad``
    overrides the padding (grid cells); ``coherent`` drops the coherence envelopes."""
    H, W = p.shape
    psi, (m, dx, pad) = exit_wave(p, body=body, pad=pad)
    inten = image_intensity(psi, dx, p.optics(), coherent=coherent)
    del psi
    crop = inten[pad : pad + H * m, pad : pad + W * m]
    return crop.reshape(H, m, W, m).mean(axis=(1, 3)), (m, dx, pad)


def _illumination(p):
    H, W = p.shape
    v = (np.arange(H) / max(H - 1, 1) - 0.5)[:, None]
    u = (np.arange(W) / max(W - 1, 1) - 0.5)[None, :]
    a = math.radians(p.gradient_angle_deg)
    grad = p.illumination_gradient * (u * math.cos(a) + v * math.sin(a))
    vig = p.vignetting * (u**2 + v**2) / 0.5
    return 1.0 + grad - vig


def reference_contrast(p, body=None):
    """Absorption-only contrast 1 - I/I_vacuum on the axis 3 nm above the core's apex."""
    body = body or tip_body(p)
    z = np.linspace(0.0, 60e-9, 60001)
    rc = body.core_radius(z)
    z_ref = float(z[np.argmax(rc > 0)]) + 3e-9
    t_out, t_core = 2 * float(body.radius(z_ref)), 2 * max(float(body.core_radius(z_ref)), 0.0)
    lam = p.absorption_lengths()
    att = t_core / lam["Si"]
    if LAYER_MATERIAL[p.layer]:
        att += (t_out - t_core) / lam[LAYER_MATERIAL[p.layer]]
    return 1.0 - math.exp(-att), z_ref


def _detector(p, contrast):
    """Detector settings and the vacuum dose (electrons per pixel) that give ``p.snr``."""
    full = {8: 255.0, 16: 65535.0}.get(p.bits)
    det0 = Detector(psf_sigma=p.psf_sigma, tail_weight=p.psf_tail_weight, tail_length=p.psf_tail_length, bits=p.bits)
    nu = noise_variance_factor(p.shape, det0)
    if full is None:  # float32: gain given, read noise in DN
        B = None
        sr2 = p.read_noise**2
        g = p.float_gain
        # SNR = g N C / sqrt(g^2 N nu + sr2)  ->  quadratic in N
        a_, b_ = (g * contrast) ** 2, -(p.snr**2) * g**2 * nu
        c_ = -(p.snr**2) * sr2
        dose = (-b_ + math.sqrt(b_**2 - 4 * a_ * c_)) / (2 * a_)
    else:
        B = p.background_level * full
        sr2 = p.read_noise**2 + 1.0 / 12.0  # rounding noise
        room = (B * contrast / p.snr) ** 2 - sr2
        if room <= 0.05 * (B * contrast / p.snr) ** 2:  # read noise alone would exceed the budget
            sr2 = 0.5 * (B * contrast / p.snr) ** 2
            room = (B * contrast / p.snr) ** 2 - sr2
        dose = B**2 * nu / room
        g = B / dose
    read = math.sqrt(max(sr2 - (1.0 / 12.0 if full else 0.0), 0.0))
    det = replace(det0, gain=g, offset=p.offset, read_noise=read)
    sigma_vac = math.sqrt(g**2 * dose * nu + sr2)
    return det, dose, sigma_vac


def simulate(p: TemWaveParams):
    """Render ``p``: returns (image as saved: uint8 / uint16 / float32, truth dict).

    Truth (SI units; image coordinates (row, col) with pixel centres at integers):
    pixel_size; shape; orientation ("down": apex at the bottom of the tip); rotation_deg
    (axis tilt, counter-clockwise as displayed apex-down); apex_px; axis_px (unit vector up
    the tip); n, Q, R, S (Eq. 1, 2), z_join, cone_slope, asymmetry e; silhouette_px and
    silhouette_tip ((M, 2): the true OUTER silhouette, coating included, particles not, in
    the image and as (x, z) in the tip frame, left flank top -> apex -> right flank top);
    flank_z, flank_r_left, flank_r_right (each flank's distance from the axis at height z,
    i.e. z(r) per flank); layer, layer_material, layer_thickness, layer_contrast; materials
    (mean inner potential, absorption length, phase per length); particles (kind "apex" /
    "shank", flank, height, centre_px, semi_axes, protrusion beyond the silhouette);
    particle_flank (the flank carrying the apex particles, or None); optics (kv, wavelength,
    interaction constant, defocus, cs, aperture, illumination angle, focal spread,
    fringe_width = sqrt(lambda |df|)); detector; dose (electrons per pixel in vacuum); snr,
    reference_contrast, noise_sigma (DN), vacuum_level (DN), saturated_fraction; sim (grid);
    params (every input); intensity (the noise-free image relative to vacuum, not saved to JSON).
    """
    if p.orientation not in ("down", "up"):
        raise ValueError(f"orientation must be 'down' or 'up', got {p.orientation!r}")
    if p.layer not in LAYER_MATERIAL:
        raise ValueError(f"layer must be one of {sorted(LAYER_MATERIAL)}, got {p.layer!r}")
    m, _, pad = _sampling(p)
    body = tip_body(p, z_max=_z_extent(p, pad, m))
    inten, grid = simulate_intensity(p, body=body)
    contrast, z_ref = reference_contrast(p, body)
    det, dose, sigma_vac = _detector(p, contrast)
    expected = inten * _illumination(p) * dose
    rng = np.random.default_rng([int(p.seed), 1])
    if p.noise:
        img = detect(expected, det, rng)
    else:
        img = expected * det.gain + det.offset
        if p.bits:
            img = np.clip(np.rint(img), 0, 255 if p.bits == 8 else 65535).astype(np.uint8 if p.bits == 8 else np.uint16)
        else:
            img = img.astype(np.float32)
    truth = make_truth(p, body, grid, contrast, z_ref, det, dose, sigma_vac, img)
    truth["intensity"] = inten
    return img, truth


def make_truth(p, body, grid, contrast, z_ref, det, dose, sigma_vac, img):
    """The truth record of a rendered image (see ``simulate``)."""
    H, W = p.shape
    m, dx, pad = grid
    silhouette = _silhouette_record(p, body, m)
    th = math.radians(p.rotation_deg)
    sgn = 1.0 if p.orientation == "down" else -1.0
    axis = np.array([-sgn * math.cos(th), -math.sin(th)])  # (drow, dcol) from the apex up the tip
    parts = _particle_records(p, body)
    apex_flanks = sorted({q["flank"] for q in parts if q["kind"] == "apex"})
    sigma = interaction_constant(p.kv)
    materials = _materials_record(p, sigma)
    full = {8: 255, 16: 65535}.get(p.bits)
    sat = float(np.mean(img >= full)) if full else 0.0
    o = p.optics()
    has_layer = p.layer != "none"
    flank = apex_flanks[0] if len(apex_flanks) == 1 else (None if not apex_flanks else "both")
    return dict(
        simulator="pipeline.synth.tem_wave",
        seed=int(p.seed),
        params=_params_dict(p),
        pixel_size=p.pixel_size,
        shape=[H, W],
        orientation=p.orientation,
        rotation_deg=p.rotation_deg,
        apex_px=[float(p.apex_px[0]), float(p.apex_px[1])],
        axis_px=axis.tolist(),
        n=p.n,
        Q=p.Q,
        R=p.R,
        S=p.S,
        z_join=p.z_join,
        cone_slope=body.cone_slope,
        asymmetry=p.asymmetry,
        layer=p.layer,
        layer_material=LAYER_MATERIAL[p.layer],
        layer_thickness=p.layer_thickness if has_layer else 0.0,
        layer_contrast=p.layer_contrast if has_layer else 0.0,
        materials=materials,
        particles=parts,
        particle_flank=flank,
        optics=_optics_record(p, o, sigma),
        detector=_detector_record(p, det),
        dose=dose,
        snr=p.snr,
        reference_contrast=contrast,
        reference_height=z_ref,
        noise_sigma=sigma_vac,
        vacuum_level=dose * det.gain + det.offset,
        saturated_fraction=sat,
        sim=dict(cells_per_pixel=m, grid_step=dx, padding=pad, band_limit=band_limit(dx, o), supersample=_SUPERSAMPLE),
        **silhouette,
    )


def _silhouette_record(p, body, m):
    """The truth's silhouette (image and tip coordinates) and flank radii, up to where the tip
    leaves the padded field (``m`` cells per pixel)."""
    z_top = min(_z_extent(p, 0, m), 400e-9)
    xs, zs = body.silhouette(z_top, spacing=min(0.02e-9, 0.1 * p.pixel_size))
    rows, cols = _image_coords(xs, zs, p)
    zf = np.unique(np.concatenate([np.linspace(0, 30e-9, 3001), np.linspace(30e-9, z_top, 500)]))
    rl, rr = body.flank_radii(zf)
    return dict(
        silhouette_px=np.column_stack([rows, cols]),
        silhouette_tip=np.column_stack([xs, zs]),
        flank_z=zf,
        flank_r_left=rl,
        flank_r_right=rr,
    )


def _particle_records(p, body):
    """One truth record per particle of ``p`` (shape, position on the tip and in the image)."""
    parts = []
    for s, pp in zip(p.particles, _particles(body, p)):
        r_, c_ = _image_coords(pp.centre[0], pp.centre[2], p)
        parts.append(
            dict(
                kind=s.kind,
                flank="right" if pp.flank > 0 else "left",
                height=float(s.height),
                azimuth_deg=float(s.azimuth_deg),
                semi_axes=[float(v) for v in s.semi_axes],
                sink=float(s.sink),
                centre_tip=[float(v) for v in pp.centre],
                centre_px=[float(r_), float(c_)],
                protrusion=_protrusion(body, pp),
                material="aC",
            )
        )
    return parts


def _materials_record(p, sigma):
    """Mean inner potential, absorption length and phase per length of each material."""
    lam_abs = p.absorption_lengths()
    pot = p.potentials()
    return {
        mat: dict(mean_inner_potential=pot[mat], absorption_length=lam_abs[mat], phase_per_length=sigma * pot[mat])
        for mat in lam_abs
    }


def _optics_record(p, o, sigma):
    """The truth's optics (``o = p.optics()``, ``sigma`` the interaction constant)."""
    return dict(
        kv=o.kv,
        wavelength=o.wavelength,
        interaction_constant=sigma,
        defocus=o.defocus,
        cs=o.cs,
        aperture=o.aperture,
        illumination_angle=o.illumination_angle,
        focal_spread=o.focal_spread,
        cc=p.cc,
        energy_spread_ev=p.energy_spread_ev,
        fringe_width=math.sqrt(o.wavelength * abs(o.defocus)),
    )


def _detector_record(p, det):
    """The truth's detector."""
    return dict(
        bits=p.bits,
        gain=det.gain,
        offset=det.offset,
        read_noise=det.read_noise,
        psf_sigma=det.psf_sigma,
        tail_weight=det.tail_weight,
        tail_length=det.tail_length,
    )


def _protrusion(body, part):
    """How far (m) the particle's projection sticks out of the tip's silhouette (<= 0: hidden
    in front of or behind the tip)."""
    xc, _, zc = part.centre
    R = part.bounding_radius()
    g = np.linspace(-R, R, 81)
    X, Z = np.meshgrid(xc + g, zc + g)
    lo, hi = part.chord_interval(X, Z)
    on = hi > lo
    rl, rr = body.flank_radii(Z[on])
    out = np.where(X[on] > 0, X[on] - rr, -X[on] - rl)
    return float(out.max()) if out.size else float("-inf")


def _params_dict(p):
    return asdict(p)


# ----------------------------------------------------------------------------- random draws


def _fits(d, field_w):
    """True if the tip of draw ``d`` is at most 55 % of the field wide 26 nm above its apex."""
    body = TipBody(
        d["n"],
        d["S"] ** (d["n"] - 2) * d["R"] ** (d["n"] - 1),
        z_join=d["z_join"],
        shank_slope=math.tan(math.radians(d["shank_half_angle_deg"])),
        blend_length=d["blend_length"],
    )
    return 2 * float(body.radius(26e-9)) * (1 + abs(d["asymmetry"])) <= 0.55 * field_w


def draw_params(seed, apex_particles=None, shank_contamination=None, **fixed) -> TemWaveParams:
    """Random parameters in the ranges of the module doc, deterministic by ``seed``.

    ``apex_particles`` / ``shank_contamination``: True / False force particles near the apex
    (on one flank) / blobs up the shank in or out (None: drawn, each in half of the seeds).

    Any field of ``TemWaveParams`` given as a keyword is used as given; the draws that
    depend on it follow it (layer -> thickness and contrast, bits -> levels and noise,
    pixel size -> image side, R -> lowered until the tip fits unless given, orientation ->
    apex row).  The same seed draws the same uniforms whatever is fixed.
    """
    rng = np.random.default_rng([int(seed), 0])
    U = rng.uniform(size=64)  # every draw below takes its own entry
    X = iter(U)

    def u(lo=0.0, hi=1.0):
        return lo + (hi - lo) * next(X)

    d = dict(
        n=u(2.0, 6.0),
        R=u(8e-9, 35e-9),
        S=u(1.0, 2.0),
        z_join=u(8e-9, 30e-9),
        shank_half_angle_deg=u(10.0, 25.0),
        blend_length=u(10e-9, 40e-9),
    )
    a0, a1, a2 = u(), u(), u()
    d["asymmetry"] = 0.0 if a0 < 0.5 else (1 if a1 < 0.5 else -1) * (0.01 + 0.04 * a2)
    k0, k1, k2 = u(), u(), u()
    d["layer"] = "none" if k0 < 0.3 else ("oxide" if k0 < 0.65 else "DLC")
    d["core_absorption_length_200kv"] = u(25e-9, 80e-9)
    d["contamination_contrast"] = u(0.1, 0.3)
    d["pixel_size"] = u(0.1e-9, 0.5e-9)
    field_nm = u(60.0, 220.0)
    d["rotation_deg"] = u(-15.0, 15.0)
    d["orientation"] = "down" if u() < 0.8 else "up"
    d["kv"] = u(100.0, 300.0)
    f0, f1 = u(), u()
    d["defocus"] = (f1 - 0.5) * (0.2e-6 if f0 < 0.2 else (1e-6 if f0 < 0.5 else 4e-6))
    d["cs"] = u(0.5e-3, 2e-3)
    d["aperture"] = u(5e-3, 20e-3)
    d["illumination_angle"] = math.exp(u(math.log(0.02e-3), math.log(0.3e-3)))
    d["cc"] = u(1.2e-3, 2.5e-3)
    d["energy_spread_ev"] = u(0.3, 0.6)
    d["snr"] = u(5.0, 30.0)
    b0, b1, b2, b3, b4 = u(), u(), u(), u(), u()
    d["bits"] = 8 if b0 < 0.35 else (16 if b0 < 0.85 else 0)
    d["float_gain"] = u(0.5, 20.0)
    d["psf_sigma"] = u(0.3, 0.8)
    d["psf_tail_weight"] = u(0.0, 0.15)
    d["psf_tail_length"] = u(2.0, 5.0)
    d["illumination_gradient"] = u(0.0, 0.08)
    d["gradient_angle_deg"] = u(0.0, 360.0)
    d["vignetting"] = u(0.0, 0.1)
    p0, p1, p2, p3, p4 = u(), u(), u(), u(), u()
    r0, r1, r2, r3 = u(), u(), u(), u()
    part_rng = np.random.default_rng([int(seed), 2])
    apex_draws, shank_draws = part_rng.uniform(size=(3, 7)), part_rng.uniform(size=(3, 6))
    d.update(fixed)
    # draws that depend on a (possibly fixed) choice
    _layer_draws(d, fixed, k1, k2)
    _detector_draws(d, fixed, b1, b2, b3, b4)
    _field_draws(d, fixed, field_nm, (r0, r1, r2, r3))
    if "particles" not in fixed:
        H, px = d["shape"][0], d["pixel_size"]
        want_apex = p0 < 0.5 if apex_particles is None else apex_particles
        want_shank = p1 < 0.5 if shank_contamination is None else shank_contamination
        d["particles"] = _draw_particles(want_apex, want_shank, p2, p3, p4, apex_draws, shank_draws, H, px)
    d["seed"] = int(seed)
    return TemWaveParams(**d)


def _layer_draws(d, fixed, k1, k2):
    """The outer layer's thickness and contrast from the layer kind (unless fixed)."""
    kind = d["layer"]
    if kind not in LAYER_MATERIAL:
        raise ValueError(f"layer must be one of {sorted(LAYER_MATERIAL)}, got {kind!r}")
    d.setdefault("layer_thickness", 0.0)
    if "layer_thickness" not in fixed:
        d["layer_thickness"] = {"none": 0.0, "oxide": 1e-9 + 1e-9 * k1, "DLC": 2e-9 + 18e-9 * k1}[kind]
    if "layer_contrast" not in fixed:
        d["layer_contrast"] = {"none": 0.2, "oxide": 0.2 + 0.3 * k2, "DLC": 0.05 + 0.25 * k2}[kind]


def _detector_draws(d, fixed, b1, b2, b3, b4):
    """Background level, offset and read noise from the bit depth (unless fixed)."""
    bits = d["bits"]
    if "background_level" not in fixed:
        d["background_level"] = (
            1.02 + 0.18 * b2 if (b1 < 0.15 and bits) else (0.55 + 0.35 * b2 if bits == 8 else 0.05 + 0.75 * b2)
        )
    if "offset" not in fixed:
        d["offset"] = {8: 8 * b3, 16: 300 * b3, 0: 0.0}[bits]
    if "read_noise" not in fixed:
        d["read_noise"] = {8: 0.2 + 0.8 * b4, 16: 1.0 + 7.0 * b4, 0: 1.0 + 7.0 * b4}[bits]


def _field_draws(d, fixed, field_nm, r):
    """Image side (a field that holds the tip), R lowered until the tip fits, apex pixel (unless fixed)."""
    px = d["pixel_size"]
    if "shape" not in fixed:
        side_px = int(np.clip(round(field_nm * 1e-9 / px / 32) * 32, 256, 1024))
        while not _fits(d, side_px * px) and side_px < 1024:
            side_px = min(1024, side_px + 64)
        d["shape"] = (side_px, side_px)
    H, W = d["shape"]
    if "R" not in fixed:
        while not _fits(d, W * px) and d["R"] > 3e-9:
            d["R"] *= 0.9
    if "apex_px" not in fixed:
        r0, r1, r2, r3 = r
        row = (0.6 + 0.2 * r0) * H + (r1 - 0.5)
        d["apex_px"] = (row if d["orientation"] == "down" else H - 1 - row, (0.4 + 0.2 * r2) * W + (r3 - 0.5))


def _draw_particles(want_apex, want_shank, p2, p3, p4, apex_draws, shank_draws, H, px):
    """Particles near the apex (on one flank) and blobs up the shank, as ParticleSpec."""
    parts = []
    side = 0.0 if p2 < 0.5 else 180.0
    if want_apex:  # 1-3 particles 1-5 nm on one flank, 3-20 nm above the apex
        for a_ in apex_draws[: 1 + int(3 * p3 * 0.999)]:
            semi = (0.5e-9 + 2e-9 * a_[1], 0.5e-9 + 2e-9 * a_[2])
            semi = semi + ((0.8 + 0.4 * a_[3]) * 0.5 * (semi[0] + semi[1]),)
            parts.append(
                ParticleSpec(
                    height=3e-9 + 17e-9 * a_[0],
                    azimuth_deg=side + (a_[4] - 0.5) * 40.0,
                    semi_axes=semi,
                    sink=0.3 + 0.6 * a_[5],
                    tilt_deg=180.0 * a_[6],
                    kind="apex",
                )
            )
    if want_shank:  # 1-3 blobs 6-24 nm far up the shank, either flank
        z_hi = max(40e-9, 0.8 * H * px)
        for a_ in shank_draws[: 1 + int(3 * p4 * 0.999)]:
            semi = (3e-9 + 9e-9 * a_[1], 3e-9 + 9e-9 * a_[2], 3e-9 + 9e-9 * a_[3])
            az = (0.0 if a_[4] < 0.5 else 180.0) + (a_[5] - 0.5) * 60.0
            parts.append(
                ParticleSpec(
                    height=30e-9 + (z_hi - 30e-9) * a_[0],
                    azimuth_deg=az,
                    semi_axes=semi,
                    sink=0.5,
                    tilt_deg=0.0,
                    kind="shank",
                )
            )
    return tuple(parts)


# ----------------------------------------------------------------------------- files


def write_image(path, image, pixel_size, calibrated=True):
    """Save as an instrument would: TIFF (ImageJ resolution tags in nm; float32 allowed) or
    PNG (8/16 bit, no calibration: the pixel size must come from the tip YAML)."""
    path = Path(path)
    if path.suffix.lower() == ".png":
        import cv2

        if image.dtype not in (np.uint8, np.uint16):
            raise ValueError("PNG holds 8- or 16-bit images only")
        if not cv2.imwrite(str(path), image):
            raise OSError(f"could not write {path}")
        return
    import tifffile

    if calibrated:
        ppu = 1.0 / (pixel_size * 1e9)
        tifffile.imwrite(path, image, imagej=True, resolution=(ppu, ppu), metadata={"unit": "nm"})
    else:
        tifffile.imwrite(path, image)


def truth_to_json(truth):
    """JSON-serialisable copy of a truth record (arrays as lists; the intensity map dropped)."""

    def conv(v):
        if isinstance(v, np.ndarray):
            return v.tolist()
        if isinstance(v, dict):
            return {k: conv(x) for k, x in v.items() if k != "intensity"}
        if isinstance(v, (list, tuple)):
            return [conv(x) for x in v]
        if isinstance(v, (np.floating, np.integer)):
            return v.item()
        return v

    return conv(truth)


def _preview(image, truth, path, overlay):
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    a = image.astype(np.float64)
    lo, hi = np.percentile(a, [0.5, 99.8])
    H, W = a.shape
    fig, ax = plt.subplots(figsize=(6, 6 * H / W))
    ax.imshow(a, cmap="gray", vmin=lo, vmax=hi, interpolation="nearest")
    if overlay:
        s = truth["silhouette_px"]
        ax.plot(s[:, 1], s[:, 0], "r-", lw=0.6, label="true outer silhouette")
        for q in truth["particles"]:
            ax.plot(q["centre_px"][1], q["centre_px"][0], "c+", ms=6)
        ax.plot(truth["apex_px"][1], truth["apex_px"][0], "y.", ms=4)
        ax.set_xlim(-0.5, W - 0.5)
        ax.set_ylim(H - 0.5, -0.5)
    p = truth["params"]
    ax.set_title(
        f"n {p['n']:.2f}, {p['layer']} {p['layer_thickness'] * 1e9:.1f} nm, {p['kv']:.0f} kV, "
        f"df {p['defocus'] * 1e6:+.2f} um, px {p['pixel_size'] * 1e9:.2f} nm, SNR {p['snr']:.0f}, "
        f"{p['bits'] or 'float'} bit",
        fontsize=7,
    )
    ax.axis("off")
    fig.tight_layout()
    fig.savefig(path, dpi=120)
    plt.close(fig)


def main(argv=None):
    """CLI: write ``--n`` sample images (and their truth) to ``--out``."""
    ap = argparse.ArgumentParser(description="Independent wave-optical TEM images of worn AFM tips, with truth.")
    ap.add_argument("--out", required=True, help="output folder")
    ap.add_argument("--n", type=int, default=12, help="number of images (default 12)")
    ap.add_argument("--seed", type=int, default=0, help="first seed (image k uses seed + k)")
    ap.add_argument("--noise-free", action="store_true", help="no noise (expected counts, rounded)")
    a = ap.parse_args(argv)
    out = Path(a.out)
    out.mkdir(parents=True, exist_ok=True)
    for k in range(a.n):
        p = draw_params(a.seed + k, noise=not a.noise_free)
        img, truth = simulate(p)
        stem = out / f"tem_wave_{a.seed + k:04d}"
        write_image(stem.with_suffix(".tif"), img, p.pixel_size)
        _preview(img, truth, f"{stem}_preview.png", overlay=False)
        _preview(img, truth, f"{stem}_truth.png", overlay=True)
        with open(f"{stem}_truth.json", "w") as fh:
            json.dump(truth_to_json(truth), fh, indent=1)
        print(
            f"{stem}.tif  {p.shape[0]}x{p.shape[1]}  n {p.n:.2f}  {p.layer} {p.layer_thickness * 1e9:.1f} nm  "
            f"{p.kv:.0f} kV  df {p.defocus * 1e6:+.2f} um  px {p.pixel_size * 1e9:.3f} nm  SNR {p.snr:.0f}  "
            f"bits {p.bits or 'float32'}  particles {len(p.particles)}",
            flush=True,
        )


if __name__ == "__main__":
    main()
