"""Seeded generator of a complete synthetic wear test (the bundled ``data_samples/``).

For each tip: a series of intervals whose apex goes from a paraboloid (n = 2) to a
flattened power law (Eq. 2, z = r^n / (n S^(n-2) R^(n-1))), one side-view TEM image
per interval, and 5-10 approach/retract force curves per interval whose pull-off
forces follow the full M-D-n model (Zheng & Yu; paper Eqs. 4-11) for a chosen
W_A and h.  The deflection sensitivity changes at every remount (``invols_drift``, 5 %
by default), as it does in a TEM wear test; k does not.  The ground truth is written beside the
data (``truth.yaml``), and a tip YAML for ``config/tips/`` that points at it.

Everything is deterministic for a given seed.
"""

from __future__ import annotations

import copy
from dataclasses import asdict, dataclass, field
from pathlib import Path

import numpy as np
import yaml

from pipeline.config import reduced_modulus


@dataclass
class TipTruth:
    """Ground truth of one synthetic tip (SI units)."""

    name: str
    description: str
    R: float  # m, Eq. 2
    S: float  # Eq. 2
    n: list  # power index per interval
    scans: list  # wear scans before each interval
    W_A: float  # J/m^2
    h: float  # m, Dugdale adhesion range
    E_tip: float
    nu_tip: float
    E_sample: float
    nu_sample: float
    u_E_star: float  # Pa, 1 sigma stated in the config
    k: float  # N/m, true spring constant
    u_k: float  # N/m stated calibration uncertainty
    invols: float  # m/V, deflection sensitivity at the calibration session (hard sample, reference lever)
    u_invols: float
    pixel_size: float  # m
    coating: float  # m, lighter outer layer thickness (DLC / native oxide)
    curves_per_interval: int = 8
    fp_scatter: float = 0.03  # relative curve-to-curve scatter of F_p
    calibration: str = "given"  # "given" (k, InvOLS in the YAML) or "curves" (hard sample + reference lever)
    k_ref: float = 0.0  # N/m, reference lever for calibration == "curves"
    u_k_ref: float = 0.0
    # relative SD of the InvOLS change at every remount (the chip leaves the AFM for the TEM after
    # each interval; the laser spot moves): each interval's InvOLS = invols (1 + invols_drift N(0,1))
    invols_drift: float = 0.05
    rotation_deg: float = 3.0
    blur_sigma_px: float = 1.2
    edge_snr: float = 15.0
    seed: int = 0
    extra: dict = field(default_factory=dict)

    @property
    def E_star(self) -> float:
        return reduced_modulus(self.E_tip, self.nu_tip, self.E_sample, self.nu_sample)

    def Q(self, n: float) -> float:
        """Q = S^(n-2) R^(n-1)  [m^(n-1)] (Eq. 2)."""
        return self.S ** (n - 2) * self.R ** (n - 1)

    def interval_names(self) -> list[str]:
        return [f"scan{s:03d}" for s in self.scans]


def sample_tips() -> list[TipTruth]:
    """The two tips of ``data_samples/`` (modelled on the paper's tips A and B)."""
    return [
        TipTruth(
            name="tipA_DLC",
            description="DLC-coated Si tip worn on a DLC flat (like the paper's tip A)",
            R=30e-9,
            S=1.0,
            n=[2.0, 2.9, 3.8, 4.6, 5.4],
            scans=[0, 10, 30, 60, 100],
            W_A=46.7e-3,
            h=4.6e-9,
            E_tip=150e9,
            nu_tip=0.3,
            E_sample=150e9,
            nu_sample=0.3,
            u_E_star=5e9,
            k=1.2,
            u_k=0.06,
            invols=45e-9,
            u_invols=0.9e-9,
            pixel_size=0.25e-9,
            coating=15e-9,
            rotation_deg=4.0,
            seed=11,
            calibration="curves",
            k_ref=0.55,
            u_k_ref=0.0165,
        ),
        TipTruth(
            name="tipB_Si",
            description="Si tip with native oxide worn on a DLC flat (like the paper's tip B)",
            R=10e-9,
            S=2.0,
            n=[2.0, 3.1, 4.0, 4.9, 5.8],
            scans=[0, 10, 30, 60, 100],
            W_A=79.8e-3,
            h=4.5e-9,
            E_tip=165e9,
            nu_tip=0.22,
            E_sample=150e9,
            nu_sample=0.3,
            u_E_star=5e9,
            k=0.9,
            u_k=0.045,
            invols=60e-9,
            u_invols=1.2e-9,
            pixel_size=0.2e-9,
            coating=1.5e-9,
            rotation_deg=-6.0,
            seed=22,
        ),
    ]


def interval_invols(t: TipTruth) -> np.ndarray:
    """True InvOLS of every interval (m/V): the calibration value with a remount drift, from a
    random stream of its own (the images and curves of a seed do not change with it)."""
    drift = np.random.default_rng([t.seed, 0x1A5E]).standard_normal(len(t.n))
    return t.invols * (1.0 + t.invols_drift * drift)


def true_pulloff_forces(t: TipTruth) -> np.ndarray:
    """F_p per interval from the full M-D-n model (exact solver)  [N]."""
    from pipeline.mechanics import pulloff_force

    n = np.asarray(t.n, dtype=float)
    Q = np.array([t.Q(x) for x in n])
    return np.asarray(pulloff_force(n, Q, t.E_star, t.W_A, t.h, model="mdn", exact=True), dtype=float)


def generate_tip(t: TipTruth, out_dir: Path) -> dict:
    """Write TEM images, force curves and truth.yaml of one tip into ``out_dir``.

    Returns the truth as a plain dict (also written to ``truth.yaml``)."""
    out_dir = Path(out_dir)
    rng = np.random.default_rng(t.seed)
    F_true = true_pulloff_forces(t)
    invols = interval_invols(t)
    truth = _tip_truth_record(t)
    for i, (name, n, scans, F) in enumerate(zip(t.interval_names(), t.n, t.scans, F_true)):
        truth["intervals"].append(_write_interval(t, i, name, n, scans, F, float(invols[i]), out_dir, rng))
    if t.calibration == "curves":
        _write_calibration_curves(t, out_dir / "calibration", rng)
        truth["reference_lever_k_N_per_m"] = t.k_ref
    with open(out_dir / "truth.yaml", "w") as fh:
        yaml.safe_dump(truth, fh, sort_keys=False)
    return truth


def _tip_truth_record(t: TipTruth) -> dict:
    """The tip's part of truth.yaml (its intervals are appended by ``generate_tip``)."""
    return {
        "description": t.description,
        "generator": "pipeline.synth.wear_test (python -m pipeline make-samples)",
        "seed": t.seed,
        "W_A_J_per_m2": t.W_A,
        "h_m": t.h,
        "E_star_Pa": t.E_star,
        "R_m": t.R,
        "S": t.S,
        "spring_constant_N_per_m": t.k,
        "deflection_sensitivity_m_per_V": t.invols,  # calibration session (hard sample, reference lever)
        "invols_drift": t.invols_drift,
        "pixel_size_m": t.pixel_size,
        "coating_thickness_m": t.coating,
        "intervals": [],
    }


def _write_interval(t: TipTruth, i, name, n, scans, F, invols_i, out_dir: Path, rng) -> dict:
    """Write interval ``i``'s TEM image and force curves (true pull-off force ``F``, InvOLS
    ``invols_i``); returns its truth record."""
    from pipeline.synth.force_curves import make_force_curve, write_curve_csv
    from pipeline.synth.tem_image import render_tem_image, write_tem_tiff

    Q = t.Q(n)
    img, img_truth = render_tem_image(
        n=n,
        Q=Q,
        pixel_size=t.pixel_size,
        shape=(512, 512),
        blur_sigma_px=t.blur_sigma_px,
        edge_snr=t.edge_snr,
        rotation_deg=t.rotation_deg + rng.normal(0, 0.5),
        coating_thickness=t.coating,
        orientation="down",
        seed=int(rng.integers(2**31)),
        S=t.S,
        contamination=(i == len(t.n) - 1),
    )
    (out_dir / "tem").mkdir(parents=True, exist_ok=True)
    write_tem_tiff(out_dir / "tem" / f"{name}.tif", img, t.pixel_size)
    curve_dir = out_dir / "curves" / name
    F_curves = F * (1.0 + t.fp_scatter * rng.standard_normal(t.curves_per_interval))
    for j, Fj in enumerate(F_curves):
        curve = make_force_curve(
            F_p=float(Fj),
            k=t.k,
            invols=invols_i,
            seed=int(rng.integers(2**31)),
            offset_V=float(rng.normal(0.0, 0.05)),
            tilt=float(rng.normal(0.0, 2e5)),
            noise=0.1e-9,
        )
        write_curve_csv(curve_dir / f"curve_{j + 1:02d}.csv", curve)
    return {
        "name": name,
        "scans": scans,
        "n": n,
        "Q_SI": Q,
        "F_p_true_N": float(F),
        "F_p_curves_N": [float(x) for x in F_curves],
        "deflection_sensitivity_m_per_V": invols_i,
        "image": {
            k: (float(v) if isinstance(v, (int, float, np.floating)) else v)
            for k, v in img_truth.items()
            if isinstance(v, (int, float, str, np.floating))
        },
    }


def _write_calibration_curves(t: TipTruth, out_dir: Path, rng, count: int = 4) -> None:
    """Curves on a hard sample (contact slope 1/InvOLS) and pressed on a reference
    lever of stiffness k_ref (apparent InvOLS_ref = InvOLS (1 + k/k_ref))."""
    from pipeline.synth.force_curves import make_force_curve, write_curve_csv

    for sub, kc in (("hard_sample", np.inf), ("reference_lever", t.k_ref)):
        for j in range(count):
            curve = make_force_curve(
                F_p=2e-9,
                k=t.k,
                invols=t.invols,
                contact_stiffness=kc,
                seed=int(rng.integers(2**31)),
                offset_V=float(rng.normal(0.0, 0.05)),
                noise=0.1e-9,
                setpoint_deflection=40e-9,
                z_range=150e-9 if np.isinf(kc) else 150e-9 * (kc + t.k) / kc,
            )
            write_curve_csv(out_dir / sub / f"curve_{j + 1:02d}.csv", curve)


def tip_config(t: TipTruth, data_dir: str) -> dict:
    """The tip YAML (as a dict of quantity strings) for a generated tip."""
    names = t.interval_names()
    return {
        "description": t.description,
        "data_dir": data_dir,
        "materials": {
            "tip": {"E": f"{t.E_tip / 1e9:g} GPa", "nu": t.nu_tip},
            "sample": {"E": f"{t.E_sample / 1e9:g} GPa", "nu": t.nu_sample},
            "E_star_uncertainty": f"{t.u_E_star / 1e9:g} GPa",
        },
        "cantilever": _cantilever_config(t),
        "tem": {"orientation": "auto", "fit_height": "6 nm", "S": t.S},
        "intervals": [
            {"name": nm, "scans": s, "image": f"tem/{nm}.tif", "curves": f"curves/{nm}"}
            for nm, s in zip(names, t.scans)
        ],
        "reference_intervals": [names[0]],
    }


def _cantilever_config(t: TipTruth) -> dict:
    """k per tip; InvOLS per interval from its own curves' contact slopes (the default, ``auto``):
    the tip YAML gives only the calibration session (hard-sample curves for the reference lever)."""
    if t.calibration == "curves":
        return {
            "hard_sample_curves": "calibration/hard_sample",
            "spring_constant_method": "reference_lever",
            "reference_lever": {
                "spring_constant": f"{t.k_ref:g} N/m",
                "spring_constant_uncertainty": f"{t.u_k_ref:g} N/m",
                "curves": "calibration/reference_lever",
            },
        }
    return {
        "spring_constant": f"{t.k:g} N/m",
        "spring_constant_uncertainty": f"{t.u_k:g} N/m",
    }


def write_sample_bundle(out="data_samples", config_dir="config/tips", tips=None) -> None:
    """Generate every sample tip under ``out`` and its YAML under ``config_dir``."""
    out, config_dir = Path(out), Path(config_dir)
    config_dir.mkdir(parents=True, exist_ok=True)
    for t in tips or sample_tips():
        generate_tip(t, out / t.name)
        cfg = tip_config(t, data_dir=str(out / t.name))
        header = (
            f"# {t.description}.\n"
            "# Generated by `python -m pipeline make-samples` "
            f"(seeded); ground truth in {out / t.name / 'truth.yaml'}.\n"
            "# Every dimensional value carries its unit; see README 'Configuration'.\n"
            "# k is one per tip; InvOLS is measured for every interval from the contact slope of its own\n"
            "# curves (the default: the chip is remounted for every TEM session).\n"
        )
        (config_dir / f"{t.name}.yaml").write_text(header + yaml.safe_dump(cfg, sort_keys=False))


def truth_as_dict(t: TipTruth) -> dict:
    d = asdict(t)
    d["E_star"] = t.E_star
    return copy.deepcopy(d)
