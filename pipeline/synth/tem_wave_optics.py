"""Electron optics and detector of the independent TEM simulator (``pipeline.synth.tem_wave``).

Electron (relativistic; CODATA 2018 constants):
  wavelength        lambda = h / sqrt(2 m0 e U (1 + e U / (2 m0 c^2)))    (2.508 pm at 200 kV)
  interaction const sigma  = 2 pi gamma m0 e lambda / h^2                  (7.288e-3 rad/(V nm) at 200 kV)
(Kirkland, "Advanced Computing in Electron Microscopy", 2nd ed., Eqs. 2.5, 5.6; the EMsoft
program EMqg prints 0.2508e-2 nm and 0.7288e-2 (V nm)^-1 at 200 kV).

Objective lens (Kirkland's sign convention: defocus df > 0 is underfocus):
  chi(k) = pi lambda k^2 (Cs lambda^2 k^2 / 2 - df)
  wave in the image plane: psi_i = F^-1[ psi_exit(k) A(k) exp(-i chi(k)) E_s(k) E_t(k) ]
  A(k): objective aperture, |lambda k| <= alpha_ap (sharp), and never beyond the grid's band
        limit 1 / (4 dx) (then |psi_i|^2 has no aliased frequencies);
  E_s(k) = exp[-(pi alpha_s / lambda)^2 (Cs lambda^3 k^3 - df lambda k)^2]   (spatial
        coherence, Gaussian illumination of semi-angle alpha_s; Frank 1973),
  E_t(k) = exp[-(pi lambda Delta)^2 k^4 / 2]  (temporal coherence, focal spread Delta;
        Wade & Frank 1977), Delta = Cc sqrt((dE/E)^2 + (dU/U)^2 + (2 dI/I)^2) with the
        relativistic factor (1 + e U / m0c^2) / (1 + e U / 2 m0c^2) on dE/E and dU/U
        (Reimer & Kohl, "Transmission Electron Microscopy", 5th ed., Sec. 6.4).
The envelopes act on the wave (quasi-coherent approximation): exact for the interference
with the unscattered wave that forms the vacuum, the fringes and thin edges; an
approximation deep inside the thick core, where the image carries no edge information.

Detector: the image (electrons per pixel, Poisson) is spread by the scintillator's point
spread function, MTF_s(f) = (1 - w) exp(-2 pi^2 s^2 f^2) + w / (1 + (2 pi L f)^2)^(3/2)
(a Gaussian core of s px and an exponential tail of weight w and length L px; the pixel's
own box comes from integrating the fine simulation grid over each pixel), converted with a
gain (DN per electron), offset, Gaussian read noise, rounded and clipped to the bit depth.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from scipy import fft as sfft

__all__ = [
    "PLANCK",
    "E_CHARGE",
    "M_ELECTRON",
    "C_LIGHT",
    "REST_ENERGY_EV",
    "electron_gamma",
    "electron_beta2",
    "electron_wavelength",
    "interaction_constant",
    "focal_spread",
    "Optics",
    "transfer_function",
    "transfer_block",
    "delocalisation",
    "image_intensity",
    "Detector",
    "detector_mtf",
    "detect",
]

PLANCK = 6.62607015e-34  # J s
E_CHARGE = 1.602176634e-19  # C
M_ELECTRON = 9.1093837015e-31  # kg
C_LIGHT = 299792458.0  # m/s
REST_ENERGY_EV = M_ELECTRON * C_LIGHT**2 / E_CHARGE  # 510998.95 eV


def electron_gamma(kv):
    """Lorentz factor of an electron accelerated through ``kv`` kilovolts."""
    return 1.0 + kv * 1e3 / REST_ENERGY_EV


def electron_beta2(kv):
    """(v/c)^2 of the electron."""
    return 1.0 - 1.0 / electron_gamma(kv) ** 2


def electron_wavelength(kv):
    """Relativistic electron wavelength (m) at ``kv`` kilovolts."""
    eU = E_CHARGE * kv * 1e3
    return PLANCK / math.sqrt(2.0 * M_ELECTRON * eU * (1.0 + eU / (2.0 * M_ELECTRON * C_LIGHT**2)))


def interaction_constant(kv):
    """sigma = 2 pi gamma m0 e lambda / h^2 (rad per volt per metre of projected thickness)."""
    return 2.0 * math.pi * electron_gamma(kv) * M_ELECTRON * E_CHARGE * electron_wavelength(kv) / PLANCK**2


def focal_spread(cc, energy_spread_ev, kv, hv_instability=0.0, current_instability=0.0):
    """Focal spread Delta (m, rms) from Cc (m), the rms energy spread (eV) and the rms relative
    instabilities of the high tension and the lens current (Reimer & Kohl Sec. 6.4)."""
    rel = (1.0 + kv * 1e3 / REST_ENERGY_EV) / (1.0 + kv * 1e3 / (2.0 * REST_ENERGY_EV))
    de = energy_spread_ev / (kv * 1e3) * rel
    return cc * math.sqrt(de**2 + (hv_instability * rel) ** 2 + (2.0 * current_instability) ** 2)


@dataclass(frozen=True)
class Optics:
    """Imaging conditions: kv (kV), defocus (m, > 0 underfocus), cs (m), aperture (objective
    semi-angle, rad; inf = none), illumination_angle (semi-angle alpha_s, rad), focal_spread (m)."""

    kv: float = 200.0
    defocus: float = 0.0
    cs: float = 1.0e-3
    aperture: float = 10e-3
    illumination_angle: float = 0.05e-3
    focal_spread: float = 3e-9

    @property
    def wavelength(self):
        return electron_wavelength(self.kv)


def _chi_gradient_length(k, optics):
    """|d chi / dk| / (2 pi) = |Cs lambda^3 k^3 - df lambda k| (m): how far a spatial frequency k
    is displaced in the image (delocalisation)."""
    lam = optics.wavelength
    return np.abs(optics.cs * lam**3 * k**3 - optics.defocus * lam * k)


def _envelopes(k, optics):
    lam = optics.wavelength
    es = np.exp(-((math.pi * optics.illumination_angle / lam) ** 2) * _chi_gradient_length(k, optics) ** 2)
    et = np.exp(-0.5 * (math.pi * lam * optics.focal_spread) ** 2 * k**4)
    return es * et


def band_limit(dx, optics):
    """Spatial frequency (1/m) up to which the wave is transferred: the aperture or the grid's
    1 / (4 dx), whichever is lower."""
    return min(optics.aperture / optics.wavelength, 0.25 / dx)


def delocalisation(optics, dx, threshold=1e-3):
    """Largest image displacement (m) of any frequency transferred with an envelope above
    ``threshold``: the padding the FFT needs so that nothing wraps around."""
    k = np.linspace(0.0, band_limit(dx, optics), 2001)
    keep = _envelopes(k, optics) > threshold
    return float(_chi_gradient_length(k[keep], optics).max()) if keep.any() else 0.0


def _band_indices(n, dx, kmax):
    """FFT-layout indices along one axis of the frequencies |k| <= kmax."""
    q = min(n // 2, int(math.floor(kmax * n * dx)) + 1)
    return np.unique(np.r_[0 : q + 1, n - q : n] % n)


def transfer_block(shape, dx, optics, coherent=False):
    """The transfer function A exp(-i chi) E_s E_t on the block of FFT indices (iy, ix) that
    holds the transferred band |k| <= ``band_limit`` (zero outside that disc); complex64."""
    ny, nx = shape
    lam = optics.wavelength
    kmax = band_limit(dx, optics)
    iy, ix = _band_indices(ny, dx, kmax), _band_indices(nx, dx, kmax)
    ky = sfft.fftfreq(ny, dx)[iy][:, None]
    kx = sfft.fftfreq(nx, dx)[ix][None, :]
    k2 = ky**2 + kx**2
    chi = math.pi * lam * k2 * (0.5 * optics.cs * lam**2 * k2 - optics.defocus)
    amp = (k2 <= kmax**2).astype(np.float64)
    if not coherent:
        amp *= _envelopes(np.sqrt(k2), optics)
    tf = (amp * np.cos(chi)).astype(np.float32) - 1j * (amp * np.sin(chi)).astype(np.float32)
    return iy, ix, tf.astype(np.complex64)


def transfer_function(shape, dx, optics, coherent=False):
    """Objective-lens transfer function A exp(-i chi) E_s E_t on the full FFT grid (complex64).
    ``coherent``: drop the envelopes (tests)."""
    iy, ix, blk = transfer_block(shape, dx, optics, coherent)
    tf = np.zeros(shape, np.complex64)
    tf[np.ix_(iy, ix)] = blk
    return tf


def image_intensity(exit_wave, dx, optics, coherent=False):
    """|psi_image|^2 on the same grid (periodic: the caller pads), relative to the incident beam."""
    spec = sfft.fft2(exit_wave.astype(np.complex64, copy=False), workers=1)
    iy, ix, blk = transfer_block(exit_wave.shape, dx, optics, coherent)
    sub = spec[np.ix_(iy, ix)] * blk
    spec[...] = 0
    spec[np.ix_(iy, ix)] = sub
    img = sfft.ifft2(spec, workers=1, overwrite_x=True)
    return img.real.astype(np.float64) ** 2 + img.imag.astype(np.float64) ** 2


@dataclass(frozen=True)
class Detector:
    """Camera: scintillator PSF (Gaussian core ``psf_sigma`` px, exponential tail of weight
    ``tail_weight`` and length ``tail_length`` px), ``gain`` (DN per electron), ``offset``
    (DN), ``read_noise`` (DN rms), ``bits`` (8, 16; 0 = float32, no rounding or clipping)."""

    psf_sigma: float = 0.5
    tail_weight: float = 0.05
    tail_length: float = 3.0
    gain: float = 1.0
    offset: float = 0.0
    read_noise: float = 0.0
    bits: int = 16


def _scintillator_mtf(f2, det):
    """MTF_s at squared spatial frequencies ``f2`` (cycles per pixel, squared)."""
    core = np.exp(-2.0 * math.pi**2 * det.psf_sigma**2 * f2)
    tail = (1.0 + (2.0 * math.pi * det.tail_length) ** 2 * f2) ** -1.5
    return (1.0 - det.tail_weight) * core + det.tail_weight * tail


def detector_mtf(shape, det):
    """Scintillator MTF on the detector's FFT grid (f in cycles per pixel)."""
    fy = sfft.fftfreq(shape[0])[:, None]
    fx = sfft.fftfreq(shape[1])[None, :]
    return _scintillator_mtf(fy**2 + fx**2, det)


def apply_psf(img, det):
    """Spread ``img`` by the scintillator PSF (FFT on a reflect-padded copy, no wrap-around)."""
    if det.psf_sigma <= 0 and det.tail_weight <= 0:
        return img
    pad = int(math.ceil(4 * det.psf_sigma + (8 * det.tail_length if det.tail_weight > 0 else 0))) + 2
    big = np.pad(img, pad, mode="reflect")
    spec = sfft.rfft2(big, workers=1)
    fy = sfft.fftfreq(big.shape[0])[:, None]
    fx = sfft.rfftfreq(big.shape[1])[None, :]
    out = sfft.irfft2(spec * _scintillator_mtf(fy**2 + fx**2, det), s=big.shape, workers=1)
    return out[pad:-pad, pad:-pad]


def noise_variance_factor(shape, det):
    """Var(PSF * white noise) / Var(white noise) = mean |MTF|^2 over the grid (Parseval)."""
    if det.psf_sigma <= 0 and det.tail_weight <= 0:
        return 1.0
    return float(np.mean(detector_mtf(shape, det) ** 2))


def detect(expected_electrons, det, rng):
    """Poisson electrons -> scintillator PSF -> gain, offset, read noise -> rounded and clipped
    to ``det.bits`` (uint8 / uint16) or float32 (bits 0).  Returns the saved image."""
    counts = rng.poisson(np.maximum(expected_electrons, 0.0)).astype(np.float64)
    signal = apply_psf(counts, det) * det.gain + det.offset
    if det.read_noise > 0:
        signal = signal + rng.normal(0.0, det.read_noise, signal.shape)
    if det.bits == 0:
        return signal.astype(np.float32)
    dtype = {8: np.uint8, 16: np.uint16}[det.bits]
    return np.clip(np.rint(signal), 0, np.iinfo(dtype).max).astype(dtype)
