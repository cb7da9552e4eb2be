"""Spring constant from the thermal-noise spectrum (Hutter & Bechhoefer; Butt & Jaschke).

k = C k_B T / <z^2>, with <z^2> the area of the first resonance of the deflection
PSD (converted to m^2/Hz with InvOLS) and C = 0.817 (rectangular lever) or 0.764
(V-shaped), the optical-lever / first-mode correction.  The peak is fitted with a
simple harmonic oscillator plus white floor,

    P(f) = P_w + A f0^4 / ((f^2 - f0^2)^2 + (f f0 / Q)^2),   <z^2> = pi A f0 Q / 2,

by least squares weighted with the model itself (iterated), which suits the
chi-square scatter of an averaged periodogram.

Thermal file (CSV): either ``time_s, deflection_V`` (or ``deflection_m``), turned into
a Welch PSD, or ``frequency_Hz, psd_V2_per_Hz`` (or ``psd_m2_per_Hz``).
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np
import pandas as pd

K_B = 1.380649e-23  # J/K
SHAPE_FACTOR = {"rectangular": 0.817, "v-shaped": 0.764}


@dataclass
class SHOFit:
    f0: float  # Hz
    Q: float
    msq: float  # area of the peak, PSD units * Hz
    white: float  # PSD units
    u_msq: float
    n_avg: int  # periodograms averaged (0 = unknown)


def _model(f, ln_f0, ln_q, ln_msq, w, scale=1.0):
    f0, Q, msq = np.exp(ln_f0), np.exp(ln_q), np.exp(ln_msq)
    A = 2.0 * msq / (np.pi * f0 * Q)
    return w * scale + A * f0**4 / ((f * f - f0 * f0) ** 2 + (f * f0 / Q) ** 2)


def psd_from_series(t, x, nperseg=None):
    """One-sided Welch PSD (units^2/Hz) of a record sampled at times t (s): (f, P, n_avg)."""
    t, x = np.asarray(t, float), np.asarray(x, float)
    fs = 1.0 / float(np.median(np.diff(t)))
    n = x.size
    nperseg = int(nperseg or min(n, 2 ** max(8, int(np.log2(n / 32)))))
    from scipy.signal import welch  # lazy: scipy.signal costs ~1 s to import

    f, P = welch(x - x.mean(), fs=fs, window="hann", nperseg=nperseg)
    return f, P, max(1, 2 * n // nperseg - 1)


def fit_sho(f, P, *, fmin=None, fmax=None, n_avg=0) -> SHOFit:
    """Fit the SHO + white model to the highest peak of P in [fmin, fmax]."""
    f, P = np.asarray(f, float), np.asarray(P, float)
    band = (f > (fmin if fmin is not None else 3 * f[1] if f.size > 1 else 0)) & (
        f < (fmax if fmax is not None else np.inf)
    )
    fb, Pb = f[band], P[band]
    if fb.size < 10:
        raise ValueError("thermal spectrum: fewer than 10 points in the fit band")
    ksm = max(1, fb.size // 2000)
    Ps = np.convolve(Pb, np.ones(2 * ksm + 1) / (2 * ksm + 1), mode="same")
    i0 = int(np.argmax(Ps))
    f0, peak = fb[i0], Ps[i0]
    white = float(np.median(Pb))
    half = np.flatnonzero(Ps > white + 0.5 * (peak - white))
    fwhm = max(float(fb[half.max()] - fb[half.min()]) if half.size > 1 else 2 * (fb[1] - fb[0]), fb[1] - fb[0])
    Q0 = f0 / fwhm
    msq0 = (peak - white) * np.pi * fwhm / 2
    w = max(15 * fwhm, 30 * (fb[1] - fb[0]))
    win = (fb > f0 - w) & (fb < f0 + w)
    fw, Pw = fb[win], Pb[win]
    scale = float(peak)
    model = lambda f, a, b, c, d: _model(f, a, b, c, d, scale)  # noqa: E731
    p = np.array([np.log(f0), np.log(Q0), np.log(max(msq0, 1e-300)), white / scale])
    sigma = np.maximum(Pw, 1e-300)
    from scipy.optimize import curve_fit  # only a thermal calibration needs it: imported here, not at start-up

    for _ in range(4):
        p, cov = curve_fit(model, fw, Pw, p0=p, sigma=sigma, absolute_sigma=n_avg > 0, maxfev=20000)
        sigma = np.maximum(model(fw, *p), 1e-300) / np.sqrt(max(n_avg, 1))
    f0, Q, msq = np.exp(p[:3])
    u_msq = msq * np.sqrt(cov[2, 2]) if np.isfinite(cov[2, 2]) else np.nan
    return SHOFit(float(f0), float(Q), float(msq), float(p[3] * scale), float(u_msq), int(n_avg))


def read_thermal_file(path):
    """(f, P, n_avg, units) from a thermal CSV; units 'V' or 'm' of the deflection."""
    path = Path(path)
    df = pd.read_csv(path, comment="#", skipinitialspace=True)
    cols = [c.strip() for c in df.columns]
    df.columns = cols
    for dcol, unit in (("deflection_V", "V"), ("deflection_m", "m")):
        if "time_s" in cols and dcol in cols:
            f, P, n_avg = psd_from_series(df["time_s"].to_numpy(float), df[dcol].to_numpy(float))
            return f, P, n_avg, unit
    for pcol, unit in (("psd_V2_per_Hz", "V"), ("psd_m2_per_Hz", "m")):
        if "frequency_Hz" in cols and pcol in cols:
            return df["frequency_Hz"].to_numpy(float), df[pcol].to_numpy(float), 0, unit
    raise ValueError(
        f"{path}: thermal file needs columns time_s + deflection_V|deflection_m "
        f"or frequency_Hz + psd_V2_per_Hz|psd_m2_per_Hz; found {cols}"
    )


def thermal_k(msq_m2, temperature, lever_shape="rectangular"):
    """k (N/m) from the first-mode mean-square deflection (m^2)."""
    return SHAPE_FACTOR[lever_shape] * K_B * temperature / msq_m2
