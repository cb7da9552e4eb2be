"""An AFM force-curve instrument simulated independently of the pipeline's assumptions.

This generator shares no code and few assumptions with ``pipeline.synth.force_curves`` (a
Lorentzian force law on an ideal hard contact, white noise) nor with the forces stage, so
that the stage can be judged on physics and instrument habits it does not model:

Tip-sample force ``F(D)`` (N, negative = attractive) at the separation ``D`` between the
undeformed apex and the sample plane:

* attraction (D >= 0), scaled so that the largest attraction is ``F_p`` (the pull-off force,
  the truth the stage must recover):
  - ``dugdale``: a rigid power-law tip z = r^n/(nQ) under a Dugdale law of range ``ell``: the
    tip area within the range, F = -F_p (1 - D/ell)^(2/n) for D < ell, 0 beyond (so a lever
    stiffer than F_p (2/n)/ell detaches smoothly, without a jump);
  - ``exponential``: the same tip under a smooth traction law sigma ~ (s/ell) exp(1 - s/ell)
    (zero at contact, peak at ``ell``), integrated over the tip's area (largest attraction
    at D > 0 for blunt tips);
  - ``vdw``: sphere-plane van der Waals with a cut-off, F = -F_p (a0/(a0 + D))^2, a0 = ``ell``.
* contact (D < 0, indentation delta = -D): F = F(0) + F_rep(delta), the Sneddon (1965)
  solution of a power-law punch on the elastic half-space E* (DMT-like: the attraction
  outside the contact stays as at D = 0): delta = B k_n a^n, F_rep = 2 E* n/(n+1) B k_n
  a^(n+1), B = 1/(nQ), k_n = sqrt(pi) Gamma(n/2+1)/Gamma(n/2+1/2) (n = 2: Hertz).  Its
  stiffness 2 E* a is finite (hundreds of N/m on a nanometre contact), so the contact slope
  of a stiff lever is not 1/InvOLS.

Lever and ramp: quasi-static equilibrium k d = F(D0 - z + d) along the stable branches
(F'(D) < k) with the instabilities (snap-in on approach, jump-off on retract) found from
the branch folds; after each jump the lever rings (damped oscillator f0, Q); the approach
stops at a relative trigger deflection, optionally dwells, and retracts at the same speed.
Thermal Brownian motion of the free lever (SHO spectrum, <d^2> = k_B T/k; in contact pinned
to k_B T/(k + k_contact)), detector white noise, slow drift (random walk + linear).  The
signal passes the ADC's anti-alias filter (2nd-order Butterworth at ``lowpass``) and is
sampled at ``fs``.

Detector and piezo: V = (d + alpha d^2)/InvOLS + offset + virtual deflection (tilt in z) +
laser interference (a sinusoid in z of period ``interference_period``), clipped and quantised
by the ADC; the recorded height is the true piezo travel scaled by ``z_scale`` (a calibration
error of the piezo, common to all curves of an instrument) plus sensor noise.

Everything is deterministic by seed.  ``simulate_curve`` returns the recorded arrays and the
truth; ``write_instrument_csv`` writes them in an instrument-like CSV layout.
"""

from __future__ import annotations

import csv
from dataclasses import asdict, dataclass, field
from pathlib import Path

import numpy as np
from scipy import signal
from scipy.fft import next_fast_len
from scipy.special import gamma

K_B = 1.380649e-23  # J/K


@dataclass
class Interaction:
    """Tip-sample force law: ``law`` (dugdale | exponential | vdw), largest attraction F_p (N),
    range ell (m), tip shape n, Q (m^(n-1)), reduced modulus E* (Pa) of the contact."""

    F_p: float
    law: str = "dugdale"
    ell: float = 4.5e-9
    n: float = 2.0
    Q: float = 20e-9
    E_star: float = 100e9


@dataclass
class Lever:
    k: float = 1.0  # N/m
    invols: float = 60e-9  # m/V, the true one at this mounting
    f0: float = 70e3  # Hz
    Q: float = 100.0
    temperature: float = 295.0  # K
    alpha: float = 0.0  # 1/m, detector nonlinearity V ~ d + alpha d^2


@dataclass
class Instrument:
    fs: float = 5e3  # Hz, sampling rate
    velocity: float = 0.5e-6  # m/s, ramp speed
    lowpass: float = 2e3  # Hz, anti-alias filter corner (0: none)
    trigger: float = 20e-9  # m of deflection above the baseline that ends the approach
    free_travel: float = 150e-9  # m of free approach before contact
    retract_extra: float = 80e-9  # m of free retract after the pull-off position
    dwell: float = 0.0  # s at the turnaround
    detector_noise: float = 0.03e-9  # m rms (white, at fs)
    drift_walk: float = 0.0  # m/sqrt(s), random-walk drift of the deflection
    drift_rate: float = 0.0  # m/s, linear drift of the deflection
    offset_V: float = 0.0
    tilt: float = 0.0  # V per m of piezo travel (virtual deflection)
    interference: float = 0.0  # m (deflection-equivalent amplitude)
    interference_period: float = 330e-9  # m of piezo travel
    z_scale: float = 1.0  # recorded height / true travel
    z_noise: float = 0.0  # m rms, height sensor noise
    adc_range: float = 10.0  # V (+-)
    adc_bits: int = 16


@dataclass
class InstrumentCurve:
    height: np.ndarray  # m, recorded, grows away from the sample
    deflection_V: np.ndarray
    segment: np.ndarray
    truth: dict = field(default_factory=dict)


# ----------------------------------------------------------------------------- forces
def sneddon_constant(n: float) -> float:
    """k_n = sqrt(pi) Gamma(n/2 + 1) / Gamma(n/2 + 1/2) (power-law punch, Sneddon 1965)."""
    return float(np.sqrt(np.pi) * gamma(n / 2 + 1) / gamma(n / 2 + 0.5))


def repulsion(delta, n, Q, E_star):
    """(F_rep, contact stiffness) of a power-law punch z = r^n/(nQ) pressed ``delta`` (m) into E*."""
    delta = np.maximum(np.asarray(delta, float), 0.0)
    B, kn = 1.0 / (n * Q), sneddon_constant(n)
    a = (delta / (B * kn)) ** (1.0 / n)
    return 2.0 * E_star * n / (n + 1.0) * B * kn * a ** (n + 1.0), 2.0 * E_star * a


def _exponential_shape(D, ell, n, m=4000):
    """Attraction of a power-law tip under sigma(s) = (s/ell) exp(1 - s/ell), up to a constant:
    integral over the plan area A(z) ~ z^(2/n); with u = z^(2/n), dA ~ du: int sigma(D + u^(n/2)) du."""
    u = np.linspace(0.0, (40.0 * ell) ** (2.0 / n), m)
    s = np.asarray(D, float)[..., None] + u ** (n / 2.0)
    return np.trapezoid((s / ell) * np.exp(1.0 - s / ell), u, axis=-1)


_TABLES: dict = {}


def _exponential_table(ell, n):
    """(D grid, attraction shape normalised to a peak of 1) of the exponential law, cached."""
    key = (float(ell), float(n))
    if key not in _TABLES:
        grid = np.concatenate([np.linspace(0.0, 6.0 * ell, 3001), np.linspace(6.0 * ell, 40.0 * ell, 400)[1:]])
        shape = np.concatenate([_exponential_shape(g, ell, n) for g in np.array_split(grid, 34)])
        _TABLES[key] = (grid, shape / shape.max())
    return _TABLES[key]


def attraction(D, it: Interaction):
    """F(D) (N, <= 0) for D >= 0, scaled so that its largest magnitude is F_p."""
    D = np.maximum(np.asarray(D, float), 0.0)
    if it.law == "dugdale":
        return -it.F_p * np.clip(1.0 - D / it.ell, 0.0, None) ** (2.0 / it.n)
    if it.law == "vdw":
        return -it.F_p * (it.ell / (it.ell + D)) ** 2
    if it.law == "exponential":
        grid, shape = _exponential_table(it.ell, it.n)
        return -it.F_p * np.interp(D, grid, shape, right=0.0)
    raise ValueError(f"unknown force law {it.law!r} (dugdale | exponential | vdw)")


def tip_force(D, it: Interaction):
    """(F, dF/dD) of the whole tip-sample interaction (N, N/m), attraction + Sneddon contact."""
    D = np.asarray(D, float)
    F0 = float(attraction(0.0, it))
    Frep, kc = repulsion(-D, it.n, it.Q, it.E_star)
    F = np.where(D < 0, F0 + Frep, attraction(D, it))
    # numerical derivative on the attractive side (piecewise laws), exact stiffness in contact
    h = 1e-13
    dF = np.where(
        D < 0, -kc, (attraction(D + h, it) - attraction(np.maximum(D - h, 0.0), it)) / (D + h - np.maximum(D - h, 0.0))
    )
    return F, dF


# ----------------------------------------------------------------------------- the lever
@dataclass
class _Branches:
    D: np.ndarray
    z: np.ndarray
    d: np.ndarray
    segments: list  # (i0, i1) index ranges of stable runs, ascending in D


def _branches(it: Interaction, lever: Lever, D0: float, delta_max: float) -> _Branches:
    """Equilibria on a fine grid of D: d = F/k, z = D0 - D + d; stable where F'(D) < k."""
    # contact: geometric in the indentation (a blunt tip's force rises as delta^(1 + 1/n), steeply
    # at the first picometres); attraction: 2 pm steps over its range; then geometric to the far end
    contact = -np.geomspace(delta_max, 1e-18, 6000)
    fine = np.arange(0.0, 12.0 * it.ell + 2e-9, 2e-12)
    far = np.geomspace(12.0 * it.ell + 2e-9, D0 + 10e-6, 3000)[1:]
    D = np.concatenate([contact, fine, far])
    F, dF = tip_force(D, it)
    d = F / lever.k
    z = D0 - D + d
    stable = dF < lever.k
    edges = np.flatnonzero(np.diff(stable.astype(int)))
    starts = np.concatenate([[0], edges + 1])
    ends = np.concatenate([edges + 1, [D.size]])
    segs = [(int(a), int(b)) for a, b in zip(starts, ends) if stable[a] and b - a >= 2]
    return _Branches(D, z, d, segs)


def _state_on_ramp(br: _Branches, z, approach: bool):
    """Deflection (m) and contact flag along a monotone piezo path ``z`` (m).

    Approach (z rising) starts on the farthest branch and, at its fold (largest z), jumps to
    the next branch of smaller D holding that z; retract (z falling) starts on the deepest
    branch and jumps to branches of larger D at each fold (smallest z)."""
    segs = br.segments if not approach else br.segments[::-1]
    d = np.full(z.shape, np.nan)
    which = np.full(z.shape, -1)
    cur, z_from = 0, -np.inf if approach else np.inf
    for _ in range(len(segs)):
        i0, i1 = segs[cur]
        zs, ds = br.z[i0:i1], br.d[i0:i1]  # z falls with D along a stable run
        zmax, zmin = zs[0], zs[-1]
        if approach:
            m = (z > z_from) & (z <= zmax) if cur < len(segs) - 1 else z > z_from
            d[m] = np.interp(z[m], zs[::-1], ds[::-1])
            z_from = zmax
        else:
            m = (z < z_from) & (z >= zmin) if cur < len(segs) - 1 else z < z_from
            d[m] = np.interp(z[m], zs[::-1], ds[::-1])
            z_from = zmin
        which[m] = cur
        # next branch: the first further one that holds the fold's z
        # (a fold that barely exists leaves the branches touching: the adjacent one, within 10 pm)
        nxt = None
        for j in range(cur + 1, len(segs)):
            a, b = segs[j]
            if min(br.z[a], br.z[b - 1]) - 1e-11 <= z_from <= max(br.z[a], br.z[b - 1]) + 1e-11:
                nxt = j
                break
        if nxt is None:
            break
        cur = nxt
    contact_seg = len(segs) - 1 if approach else 0
    return d, which == contact_seg


def _ring(t, jumps, f0, Q):
    """Damped ringing after each jump (t_jump, step size): the step response of the lever."""
    out = np.zeros_like(t)
    w0 = 2 * np.pi * f0
    zeta = 1.0 / (2.0 * Q)
    wd = w0 * np.sqrt(max(1.0 - zeta**2, 1e-12))
    for tj, step in jumps:
        m = t >= tj
        tau = t[m] - tj
        env = np.exp(-zeta * w0 * tau)
        out[m] += -step * env * (np.cos(wd * tau) + zeta / np.sqrt(max(1 - zeta**2, 1e-12)) * np.sin(wd * tau))
    return out


def _thermal(n, dt, lever: Lever, rng):
    """Brownian deflection (m) of the free lever: SHO spectrum with variance k_B T / k."""
    m = next_fast_len(n, real=True)  # an FFT of a length with a large prime factor takes seconds
    f = np.fft.rfftfreq(m, dt)
    f0, Q = lever.f0, lever.Q
    H = f0**2 / (f0**2 - f**2 + 1j * f * f0 / Q)
    X = (rng.standard_normal(f.size) + 1j * rng.standard_normal(f.size)) * np.abs(H)
    X[0] = 0.0
    x = np.fft.irfft(X, m)[:n]
    sd = np.std(x)
    return x * (np.sqrt(K_B * lever.temperature / lever.k) / sd if sd > 0 else 0.0)


def _lowpass(volts, inst: Instrument, fi):
    """The instrument's anti-alias filter (sampling rate ``fi``), if any."""
    if inst.lowpass > 0:
        sos = signal.butter(2, inst.lowpass, fs=fi, output="sos")
        volts = signal.sosfilt(sos, volts - volts[0]) + volts[0]
    return volts


def _digitised(volts, inst: Instrument):
    """``volts`` rounded to the ADC's levels and clipped to its range."""
    lsb = 2 * inst.adc_range / 2**inst.adc_bits
    return np.clip(np.round(volts / lsb) * lsb, -inst.adc_range, inst.adc_range - lsb)


def simulate_curve(it: Interaction, lever: Lever, inst: Instrument, *, seed=0, height_start=2e-6) -> InstrumentCurve:
    """One approach-retract ramp as the instrument records it (module doc)."""
    rng = np.random.default_rng(seed)
    k = lever.k
    D0 = inst.free_travel
    br = _branches(it, lever, D0, _trigger_depth(it, k, inst))
    # trigger: first z on the contact branch where d = trigger
    i0, i1 = br.segments[0]
    dz = br.d[i0:i1][::-1]
    zz = br.z[i0:i1][::-1]
    z_trig = float(np.interp(inst.trigger, dz, zz))
    # internal time grid (oversampled for the lever's ringing and the anti-alias filter)
    T_ramp = z_trig / inst.velocity
    over = int(np.clip(np.ceil(8.0 * lever.f0 / inst.fs), 8, 256))
    fi = inst.fs * over
    dt = 1.0 / fi
    n_app = int(np.ceil(T_ramp * fi))
    n_dw = int(round(inst.dwell * fi))
    z_ret_end = _retract_end(br, i0, i1, it, inst)
    n_ret = int(np.ceil((z_trig - z_ret_end) / inst.velocity * fi))
    z_app = np.linspace(0.0, z_trig, n_app, endpoint=False)
    z_dw = np.full(n_dw, z_trig)
    z_ret = np.linspace(z_trig, z_ret_end, n_ret)
    d_app, c_app = _state_on_ramp(br, z_app, approach=True)
    d_ret, c_ret = _state_on_ramp(br, z_ret, approach=False)
    d_dw = np.full(n_dw, inst.trigger)
    d = np.concatenate([d_app, d_dw, d_ret])
    contact = np.concatenate([c_app, np.ones(n_dw, bool), c_ret])
    z = np.concatenate([z_app, z_dw, z_ret])
    t = np.arange(d.size) * dt
    ramp_step = inst.velocity * dt  # the largest change of d between samples on a stable branch is ~ this
    jumps = [(t[j + 1], d[j + 1] - d[j]) for j in np.flatnonzero(np.abs(np.diff(d)) > max(20.0 * ramp_step, 0.02e-9))]
    d_mech = d + _ring(t, jumps, lever.f0, lever.Q)
    # thermal motion: free lever k_B T/k; pinned in contact k_B T/(k + k_contact)
    kc = np.zeros(d.size)
    pressed = contact & (D0 - z + d < 0)  # the Sneddon stiffness 2 E* a where the tip indents
    kc[pressed] = repulsion(-(D0 - z[pressed] + d[pressed]), it.n, it.Q, it.E_star)[1]
    th = _thermal(d.size, dt, lever, rng) * np.sqrt(k / (k + kc))
    drift = inst.drift_rate * t + (
        np.cumsum(rng.standard_normal(d.size)) * inst.drift_walk * np.sqrt(dt) if inst.drift_walk else 0.0
    )
    sig = d_mech + th + drift
    volts = (sig + lever.alpha * sig**2) / lever.invols
    volts = (
        volts
        + inst.tilt * z
        + (inst.interference / lever.invols)
        * np.sin(2 * np.pi * z / inst.interference_period + rng.uniform(0, 2 * np.pi))
    )
    volts = _lowpass(volts, inst, fi)
    idx = np.arange(0, volts.size, over)
    volts, zs, ts = volts[idx], z[idx], t[idx]
    volts = volts + inst.offset_V + rng.standard_normal(volts.size) * inst.detector_noise / lever.invols
    volts = _digitised(volts, inst)
    height = height_start - (zs * inst.z_scale + rng.standard_normal(zs.size) * inst.z_noise)
    n_a = int(np.ceil((n_app + n_dw) / over))
    seg = np.array(["extend"] * n_a + ["retract"] * (volts.size - n_a), dtype=object)
    truth = _truth(it, lever, inst, br, i0, i1, len(jumps), seed, float(ts[-1]))
    return InstrumentCurve(height, volts, seg, truth)


def _trigger_depth(it: Interaction, k, inst: Instrument):
    """Contact depth that reaches the trigger (|F(0)| + k trigger of repulsion), with margin."""
    F_need = abs(float(attraction(0.0, it))) + k * inst.trigger
    B, kn = 1.0 / (it.n * it.Q), sneddon_constant(it.n)
    a_need = (F_need / (2 * it.E_star * it.n / (it.n + 1) * B * kn)) ** (1.0 / (it.n + 1))
    return 1.5 * B * kn * a_need**it.n + 0.05e-9


def _retract_end(br, i0, i1, it: Interaction, inst: Instrument):
    """Where the retract ends: once the lever has been free for ``retract_extra`` (the pull-off is
    at the contact branch's fold; without an instability the lever detaches smoothly: "free" where
    the attraction is < 1 % of F_p)."""
    Dseg = br.D[i0:i1]
    free = np.flatnonzero((Dseg > 0) & (np.abs(attraction(Dseg, it)) < 0.01 * it.F_p))
    z_detach = float(br.z[i0:i1][free[0]]) if free.size else float(br.z[i0:i1][-1])
    return min(0.0, z_detach) - inst.retract_extra


def _truth(it: Interaction, lever: Lever, inst: Instrument, br, i0, i1, jumps: int, seed, duration) -> dict:
    """The truth of a curve: the largest attraction (the pull-off force), what the contact slope
    really is, and every parameter of the lever and the instrument."""
    k = lever.k
    Dg = np.linspace(0.0, 6.0 * it.ell, 4001)
    F_max = float(-attraction(Dg, it).min())
    _, kc_trig = repulsion(-br.D[i0:i1][np.argmin(np.abs(br.d[i0:i1] - 0.5 * inst.trigger))], it.n, it.Q, it.E_star)
    return dict(
        F_p=F_max,
        k=k,
        invols=lever.invols,
        delta_m=F_max / k,
        law=it.law,
        ell=it.ell,
        n=it.n,
        Q=it.Q,
        E_star=it.E_star,
        contact_stiffness_mid=float(kc_trig),
        contact_slope_factor=float(kc_trig / (kc_trig + k)),
        jumps=jumps,
        seed=seed,
        fs=inst.fs,
        duration=duration,
        **{f"lever_{a}": v for a, v in asdict(lever).items()},
        **{f"inst_{a}": v for a, v in asdict(inst).items()},
    )


HEADER = ("Height (nm)", "Vertical Deflection (V)", "Segment")
READER = {"columns": {"height": HEADER[0], "deflection": HEADER[1], "segment": HEADER[2]}}


def write_instrument_csv(path, curve: InstrumentCurve) -> Path:
    """Write the curve as an instrument export (the column names of ``HEADER``, tab-separated,
    a comment block of metadata); read it with ``force_curves.columns`` = ``READER``."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    t = curve.truth
    with open(path, "w", newline="") as fh:
        fh.write(f"# simulated instrument export: k={t['k']:.5g} N/m, fs={t['fs']:.5g} Hz (truth kept by the study)\n")
        w = csv.writer(fh, delimiter="\t")
        w.writerow(HEADER)
        w.writerows(
            zip((f"{h * 1e9:.5f}" for h in curve.height), (f"{v:.6e}" for v in curve.deflection_V), curve.segment)
        )
    return path


def write_interval(folder, it: Interaction, lever: Lever, inst: Instrument, *, n_curves=8, scatter=0.03, seed=0):
    """``n_curves`` curves of one interval (pull-off scattered by ``scatter`` relative SD from
    curve to curve, as contact sites differ) written as instrument CSVs in ``folder``.
    Returns (paths, per-curve truth dicts)."""
    rng = np.random.default_rng([seed, 0xAF1])
    paths, truths = [], []
    for j in range(n_curves):
        itj = Interaction(**{**asdict(it), "F_p": it.F_p * (1.0 + scatter * rng.standard_normal())})
        c = simulate_curve(itj, lever, inst, seed=int(rng.integers(2**31)))
        paths.append(write_instrument_csv(Path(folder) / f"curve_{j:02d}.tsv", c))
        truths.append(c.truth)
    return paths, truths
