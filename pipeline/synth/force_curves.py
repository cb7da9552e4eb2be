"""Synthetic AFM force-distance curves and thermal-noise records (deterministic by seed).

Physics: a lever of stiffness k at piezo extension z (towards the sample) and a
tip-sample force F(g) at gap g = z_c - z + d, equilibrium k d = F(g), with

    F(g) = -F_p / (1 + (g / lam)^2)        g >= 0  (adhesion; max |F| = F_p at g = 0)
    F(g) = -F_p - k_c g                    g <  0  (elastic contact, stiffness k_c)

The lever is unstable where dF/dg = k: on approach it snaps in at the far root
(a few nm, with some long-range attraction before it), on retract it jumps off at
the near root, within (k lam / 2 F_p)^2 of the maximum adhesive force for a soft
lever -- the pull-off force is the maximum adhesive force.  In contact the
deflection-vs-z slope is k_c / (k_c + k) (1 for a hard sample).  White deflection
noise (m rms) is added, and the signal is written in volts with InvOLS, a
baseline offset (V) and a tilt (V per m of extension).
"""

from __future__ import annotations

import csv
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
from scipy.optimize import brentq

K_B = 1.380649e-23  # J/K


@dataclass
class SyntheticCurve:
    """Arrays over the whole ramp (approach then retract) and the true values used."""

    height: np.ndarray  # piezo height (m), grows away from the sample
    deflection_V: np.ndarray
    segment: np.ndarray  # "approach" / "retract"
    truth: dict = field(default_factory=dict)


def _force(g, F_p, lam, k_c):
    g = np.asarray(g, float)
    out = -F_p / (1.0 + (np.maximum(g, 0.0) / lam) ** 2)
    neg = g < 0
    if np.any(neg):
        out = np.where(neg, -F_p - k_c * np.where(neg, g, -1.0), out)
    return out


def _instability_gaps(F_p, k, lam):
    """Gaps (m) where dF/dg = k: (jump-off, snap-in)."""
    a = 2.0 * F_p / (lam * k)
    h = lambda u: a * u / (1.0 + u * u) ** 2 - 1.0  # noqa: E731
    u_peak = 1.0 / np.sqrt(3.0)
    if h(u_peak) <= 0:
        raise ValueError(
            f"no jump-off: lever k={k:g} N/m is too stiff for "
            f"F_p={F_p:g} N over range {lam:g} m (need F_p > 1.54 k lam)"
        )
    u_off = brentq(h, 0.0, u_peak, xtol=1e-15, rtol=1e-14)
    u_snap = brentq(h, u_peak, 2.0 * a ** (1 / 3) + 2.0, xtol=1e-14)
    return u_off * lam, u_snap * lam


def _branch_tables(F_p, k, lam, kc, g_off, g_snap, z0, z_c, s, R):
    """Deflection against extension on the two branches, ((z, d) in contact, (z, d) free): the
    contact branch a straight line (g <= 0) and the adhesive gap 0..g_off, the free branch g >= g_snap."""
    delta_max = F_p / k
    g_gap = np.linspace(0.0, g_off, 64)
    d_gap = _force(g_gap, F_p, lam, kc) / k
    z_gap = z_c + d_gap - g_gap
    z_deep = R + 1e-9
    zc_b = np.concatenate([z_gap[::-1], [z_deep]])
    dc_b = np.concatenate([d_gap[::-1], [-delta_max + s * (z_deep - z0)]])
    g_free = np.geomspace(g_snap, z_c + 10e-9, 4000)
    d_free = _force(g_free, F_p, lam, kc) / k
    return (zc_b, dc_b), ((z_c + d_free - g_free)[::-1], d_free[::-1])


def make_force_curve(
    F_p,
    k,
    invols,
    *,
    seed=0,
    offset_V=0.0,
    tilt=0.0,
    noise=0.1e-9,
    contact_stiffness=np.inf,
    adhesion_range=0.5e-9,
    setpoint_deflection=20e-9,
    z_range=None,
    n_points=2000,
    height_start=1.0e-6,
    height_jitter=0.0,
    jitter="sensor",
) -> SyntheticCurve:
    """One approach + retract ramp.

    F_p (N) pull-off force, k (N/m), invols (m/V), offset_V (V), tilt (V/m of
    extension), noise (m rms deflection), contact_stiffness k_c (N/m, inf = hard),
    adhesion_range lam (m), setpoint_deflection (m, at the turnaround), z_range (m;
    default max(100 nm, 3 (F_p/k + setpoint))), n_points (total, split evenly).
    ``height_jitter`` (m rms, white): ``jitter="sensor"``: the recorded height is the smooth
    ramp plus sensor noise (the deflection follows the smooth ramp); ``"piezo"``: the piezo
    itself jitters, the deflection follows the jittered position and the height sensor records
    it (the lever stays in contact until the first sample beyond the instability).  Either way
    contact and free points interleave in height at the jump-off.
    ``truth``: F_p, k, invols, delta_m (deflection at the jump-off), delta_V,
    contact_slope, z_pulloff/z_snap (m of extension), noise, offset_V, tilt.
    """
    if not (F_p > 0 and k > 0 and invols > 0):
        raise ValueError("F_p, k and invols must be positive")
    lam, kc = float(adhesion_range), float(contact_stiffness)
    delta_max = F_p / k
    R = float(z_range) if z_range is not None else max(100e-9, 3.0 * (delta_max + setpoint_deflection))
    s = 1.0 if np.isinf(kc) else kc / (kc + k)
    g_off, g_snap = _instability_gaps(F_p, k, lam)
    z0 = R - (setpoint_deflection + delta_max) / s  # contact point at g = 0 (d = -F_p/k)
    z_c = z0 + delta_max
    z_po = z_c + float(_force(g_off, F_p, lam, kc)) / k - g_off
    if z_po < 0.3 * R:
        raise ValueError(f"z_range {R:g} m leaves too little free retract after the pull-off (at {z_po:g} m)")
    (zc_b, dc_b), (zf_b, df_b) = _branch_tables(F_p, k, lam, kc, g_off, g_snap, z0, z_c, s, R)
    z_snap = float(zf_b[-1])
    n_app = n_points // 2
    z_app = np.linspace(0.0, R, n_app)
    z_ret = np.linspace(R, 0.0, n_points - n_app)
    rng = np.random.default_rng(seed)
    d_noise = rng.normal(0.0, noise, n_points)
    jit = rng.normal(0.0, height_jitter, n_points) if height_jitter > 0 else np.zeros(n_points)
    if jitter not in ("sensor", "piezo"):
        raise ValueError(f"jitter must be 'sensor' or 'piezo', got {jitter!r}")
    za, zr = (z_app + jit[:n_app], z_ret + jit[n_app:]) if jitter == "piezo" else (z_app, z_ret)
    snapped = np.maximum.accumulate(za >= z_snap)  # hysteresis: each state held until its instability
    released = np.maximum.accumulate(zr < z_po)
    d_app = np.where(snapped, np.interp(za, zc_b, dc_b), np.interp(za, zf_b, df_b))
    d_ret = np.where(released, np.interp(zr, zf_b, df_b), np.interp(zr, zc_b, dc_b))
    z = np.concatenate([z_app, z_ret]) + jit
    d = np.concatenate([d_app, d_ret]) + d_noise
    volts = d / invols + offset_V + tilt * z
    seg = np.array(["approach"] * n_app + ["retract"] * (n_points - n_app), dtype=object)
    delta = -float(_force(g_off, F_p, lam, kc)) / k
    truth = dict(
        F_p=F_p,
        k=k,
        invols=invols,
        delta_m=delta,
        delta_V=delta / invols,
        contact_slope=s,
        z_pulloff=z_po,
        z_snap=z_snap,
        noise=noise,
        offset_V=offset_V,
        tilt=tilt,
        seed=seed,
        z_range=R,
        height_jitter=height_jitter,
        jitter=jitter,
    )
    return SyntheticCurve(height_start - z, volts, seg, truth)


def write_curve_csv(path, curve: SyntheticCurve) -> Path:
    """Write ``height_nm, deflection_V, segment`` (the default CSV layout) with a ``#`` truth line."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    t = curve.truth
    with open(path, "w", newline="") as fh:
        fh.write(
            f"# synthetic force curve: F_p={t['F_p']:.6e} N k={t['k']:.6e} "
            f"N/m invols={t['invols']:.6e} m/V seed={t['seed']}\n"
        )
        w = csv.writer(fh)
        w.writerow(["height_nm", "deflection_V", "segment"])
        w.writerows(
            zip((f"{h:.6f}" for h in curve.height * 1e9), (f"{v:.7e}" for v in curve.deflection_V), curve.segment)
        )
    return path


def sho_psd(f, f0, Q, msq):
    """One-sided SHO PSD (units^2/Hz) whose integral over 0..inf is ``msq``."""
    f = np.asarray(f, float)
    A = 2.0 * msq / (np.pi * f0 * Q)
    return A * f0**4 / ((f * f - f0 * f0) ** 2 + (f * f0 / Q) ** 2)


def thermal_noise_series(
    k, f0, Q, *, temperature=295.0, invols=50e-9, fs=None, n=2**20, shape_factor=0.817, white=0.0, seed=0
):
    """Thermal deflection record (t in s, volts) of a lever with stiffness k (N/m).

    The first-mode apparent deflection has <z^2> = shape_factor k_B T / k (so that
    k = shape_factor k_B T / <z^2>); ``white`` adds a white floor (m^2/Hz).
    Gaussian, generated in the frequency domain; fs defaults to 5 f0.
    """
    fs = float(fs or 5.0 * f0)
    rng = np.random.default_rng(seed)
    f = np.fft.rfftfreq(n, 1.0 / fs)
    S = sho_psd(f, f0, Q, shape_factor * K_B * temperature / k) + white
    X = np.sqrt(S * n * fs / 4.0) * (rng.normal(size=f.size) + 1j * rng.normal(size=f.size))
    X[0] = 0.0
    X[-1] = X[-1].real * np.sqrt(2.0)
    z = np.fft.irfft(X, n=n)
    return np.arange(n) / fs, z / invols


def write_thermal_csv(path, t, volts) -> Path:
    """Write a thermal record as ``time_s, deflection_V``."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    np.savetxt(path, np.column_stack([t, volts]), delimiter=",", header="time_s,deflection_V", comments="", fmt="%.9e")
    return path
