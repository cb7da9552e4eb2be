"""Cantilever calibration at tip level: spring constant k (N/m) and the InvOLS (m/V) of the
calibration session.

k belongs to the lever and is one per tip: ``given`` (cantilever.spring_constant) >
``reference_lever`` > ``thermal`` > ``file``.  The InvOLS that converts an interval's
deflection is one per interval by default (``pipeline.forces.invols``); the tip-level InvOLS
here, ``given`` (cantilever.deflection_sensitivity) > ``hard_sample`` (contact slope of the
curves in cantilever.hard_sample_curves) > ``file`` (metadata of the force curves), is the one
of the calibration session (the reference-lever and thermal k need it), the value used for
every interval when the method says so (a setup never remounted), and a fallback.

Every input carries a 1-sigma uncertainty (0 when unknown: stated in the source
string); k, InvOLS and their product k*InvOLS (N/V, the factor turning Delta in
volts into F_p) are propagated to first order with numerical derivatives, keeping
correlations (InvOLS_hard enters both k of the reference-lever method and InvOLS;
the thermal k scales as 1/InvOLS^2).
"""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from pipeline.forces.contact_slope import invols_from_curves
from pipeline.forces.curve import ForceCurve
from pipeline.forces.errors import CalibrationError, ForceCurveError
from pipeline.forces.invols import PER_INTERVAL_METHODS
from pipeline.forces.reference_lever import reference_lever_k
from pipeline.forces.settings import (
    CANTILEVER_DEFAULTS,
    READER_DEFAULTS,
    REFERENCE_DEFAULTS,
    THERMAL_DEFAULTS,
    resolve_paths,
    with_defaults,
)
from pipeline.forces.thermal import SHAPE_FACTOR, fit_sho, read_thermal_file, thermal_k


@dataclass
class Calibration:
    k: float
    u_k: float
    invols: float  # NaN when the curves are in metres without a file InvOLS
    u_invols: float
    k_method: str
    invols_method: str
    k_source: str
    invols_source: str
    factor: float  # k * invols (N/V)
    u_factor: float
    corr_k_invols: float
    details: dict = field(default_factory=dict)  # group -> {name: (value, units, description)}

    @property
    def u_factor_rel(self) -> float:
        return self.u_factor / self.factor if self.factor else np.nan

    @property
    def u_k_rel(self) -> float:
        return self.u_k / self.k


def _propagate(funcs, x: dict, u: dict):
    """Values, standard uncertainties and covariance of funcs(x) for independent inputs x +- u."""
    names = [n for n in x if u.get(n, 0) > 0]
    y0 = np.array([f(x) for f in funcs])
    J = np.zeros((len(funcs), len(names)))
    for j, n in enumerate(names):
        h = u[n] * 1e-3
        xp, xm = dict(x), dict(x)
        xp[n], xm[n] = x[n] + h, x[n] - h
        J[:, j] = (np.array([f(xp) for f in funcs]) - np.array([f(xm) for f in funcs])) / (2 * h)
    cov = J @ np.diag([u[n] ** 2 for n in names]) @ J.T if names else np.zeros((len(funcs), len(funcs)))
    return y0, np.sqrt(np.diag(cov)), cov


def _file_value(curves, attr, label):
    vals = np.array([getattr(c, attr) for c in curves if getattr(c, attr) is not None], float)
    if vals.size == 0:
        return None
    if np.ptp(vals) > 1e-6 * abs(vals.mean()):
        raise CalibrationError(
            f"the curve files store different {label} values ({vals.min():.6g} .. {vals.max():.6g}); give "
            f"cantilever.{'spring_constant' if attr == 'spring_constant' else 'deflection_sensitivity'} in the tip YAML"
        )
    return float(vals[0])


def _hard_sample_invols(cant, reader, details, key="hard_sample_curves", group="hard_sample"):
    files = resolve_paths(cant, cant[key])
    if not files:
        raise CalibrationError(
            f"cantilever.{key}: no files match {cant[key]!r} (base_dir {cant.get('base_dir', '.')!r})"
        )
    from pipeline.forces.reading import read_curves

    curves, rejected = [], []
    for p in files:  # an unreadable file is left out with its reason, not the whole calibration
        try:
            curves.extend(read_curves(p, reader))
        except ForceCurveError as exc:
            rejected.append((str(p), exc.reason))
    try:
        if not curves:
            raise ForceCurveError(files[0], "no readable hard-sample curve")
        mean, u, vals, us, bad = invols_from_curves(
            curves, fit_range=tuple(cant["contact_fit_range"]), segment=cant["contact_segment"]
        )
    except ForceCurveError as exc:
        why = "; ".join(f"{p}: {r}" for p, r in rejected[:3])
        raise CalibrationError(f"cantilever.{key}: {exc}" + (f"; unreadable: {why}" if why else "")) from None
    rejected += bad
    details[group] = {
        "file": ([c.path for c in curves], "1", "hard-sample curves read"),
        "invols": (vals, "m/V", "InvOLS from the contact slope of each curve used"),
        "u_invols_fit": (us, "m/V", "fit standard error of each curve's InvOLS"),
        "rejected": ([f"{p}: {r}" for p, r in rejected], "1", "curves left out, with the reason"),
        "contact_fit_range": (np.asarray(cant["contact_fit_range"], float), "1", "fraction of max deflection fitted"),
    }
    n = vals.size
    src = (
        f"contact slope of {n} curve(s) in {cant[key]} ({cant['contact_segment']}), u = SEM"
        if n > 1
        else f"contact slope of 1 curve in {cant[key]}, u = fit error"
    )
    if rejected:
        src += f"; {len(rejected)} curve(s) left out: " + "; ".join(f"{Path(p).name}: {r}" for p, r in rejected[:3])
    return mean, u, src


def calibrate(cantilever: dict | None, curves: list[ForceCurve], reader: dict | None = None) -> Calibration:
    """Resolve k and InvOLS for an interval's curves from the ``cantilever:`` config (SI)."""
    cant = with_defaults(cantilever, CANTILEVER_DEFAULTS)
    reader = with_defaults(reader, READER_DEFAULTS)
    if "base_dir" in cant:
        reader.setdefault("base_dir", cant["base_dir"])
    details: dict = {}
    x, u = {}, {}  # the calibration's inputs and their uncertainties, filled by the two steps
    im, i_src = _tip_invols(cant, reader, curves, details, x, u)
    km, k_fun, k_src = _spring_constant(cant, reader, curves, details, x, u)
    if np.isnan(x["invols"]):
        (k,), (uk,), _ = _propagate([k_fun], x, u)
        return Calibration(k, uk, np.nan, np.nan, km, im, k_src, i_src, np.nan, np.nan, np.nan, details)
    funcs = [k_fun, lambda p: p["invols"], lambda p: k_fun(p) * p["invols"]]
    (k, inv, fac), (uk, ui, uf), cov = _propagate(funcs, x, u)
    if km in ("reference_lever", "thermal") and "spring_constant_uncertainty" in cant:
        uk = cant["spring_constant_uncertainty"]
        uf = fac * np.hypot(uk / k, ui / inv)
        cov[0, 1] = 0.0
    corr = cov[0, 1] / (uk * ui) if uk > 0 and ui > 0 else 0.0
    if not (k > 0 and inv > 0):
        raise CalibrationError(f"non-positive calibration: k = {k:g} N/m, InvOLS = {inv:g} m/V")
    return Calibration(
        float(k), float(uk), float(inv), float(ui), km, im, k_src, i_src, float(fac), float(uf), float(corr), details
    )


def _tip_invols(cant, reader, curves, details, x, u):
    """InvOLS at tip level (the calibration session; per-interval values: invols.py) into x, u;
    returns (method, source in words)."""
    im = cant["deflection_sensitivity_method"]
    per_interval = im in PER_INTERVAL_METHODS
    if per_interval:
        im = "given" if "deflection_sensitivity" in cant else "hard_sample" if "hard_sample_curves" in cant else "file"
    if im == "given":
        if "deflection_sensitivity" not in cant:
            raise CalibrationError("deflection_sensitivity_method 'given' needs cantilever.deflection_sensitivity")
        x["invols"], u["invols"] = cant["deflection_sensitivity"], cant.get("deflection_sensitivity_uncertainty", 0.0)
        i_src = "tip YAML cantilever.deflection_sensitivity" + ("" if u["invols"] else " (no uncertainty given: 0)")
    elif im == "hard_sample":
        if "hard_sample_curves" not in cant:
            raise CalibrationError("deflection_sensitivity_method 'hard_sample' needs cantilever.hard_sample_curves")
        x["invols"], u["invols"], i_src = _hard_sample_invols(cant, reader, details)
        if "deflection_sensitivity_uncertainty" in cant:
            u["invols"] = cant["deflection_sensitivity_uncertainty"]
            i_src += "; u from tip YAML"
    elif im == "file":
        i_src = _invols_from_files(cant, curves, per_interval, x, u)
    else:
        raise CalibrationError(f"unknown deflection_sensitivity_method {im!r}")
    return im, i_src


def _invols_from_files(cant, curves, per_interval, x, u) -> str:
    """The InvOLS the curve files carry (NaN where none is needed or it is the interval's own)."""
    v = _file_value(curves, "invols", "InvOLS")
    if v is not None:
        x["invols"], u["invols"] = v, cant.get("deflection_sensitivity_uncertainty", 0.0)
        return "force-curve file metadata" + ("" if u["invols"] else " (uncertainty unknown: 0)")
    if all(c.defl_units == "m" for c in curves):
        x["invols"], u["invols"] = np.nan, 0.0
        return "not used: deflection recorded in metres by the instrument"
    if per_interval:
        x["invols"], u["invols"] = np.nan, 0.0
        return "none at tip level (InvOLS per interval)"
    raise CalibrationError(
        "no deflection sensitivity (InvOLS): the curve files carry none; give "
        "cantilever.deflection_sensitivity or cantilever.hard_sample_curves"
    )


def _spring_constant(cant, reader, curves, details, x, u):
    """The spring constant's inputs into x, u; returns (method, k as a function of the inputs,
    source in words)."""
    km = cant["spring_constant_method"]
    if km == "auto":
        km = (
            "given"
            if "spring_constant" in cant
            else "reference_lever"
            if "reference_lever" in cant
            else "thermal"
            if "thermal" in cant
            else "file"
        )
    if km == "given":
        if "spring_constant" not in cant:
            raise CalibrationError("spring_constant_method 'given' needs cantilever.spring_constant")
        x["k"], u["k"] = cant["spring_constant"], cant.get("spring_constant_uncertainty", 0.0)
        k_fun = lambda p: p["k"]  # noqa: E731
        k_src = "tip YAML cantilever.spring_constant" + ("" if u["k"] else " (no uncertainty given: 0)")
    elif km == "file":
        v = _file_value(curves, "spring_constant", "spring constant")
        if v is None:
            raise CalibrationError(
                "no spring constant: the curve files carry none; give "
                "cantilever.spring_constant, reference_lever or thermal"
            )
        x["k"], u["k"] = v, cant.get("spring_constant_uncertainty", 0.0)
        k_fun = lambda p: p["k"]  # noqa: E731
        k_src = "force-curve file metadata" + ("" if u["k"] else " (uncertainty unknown: 0)")
    elif km == "reference_lever":
        k_fun, k_src = _reference_setup(cant, reader, x, u, details)
    elif km == "thermal":
        k_fun, k_src = _thermal_setup(cant, x, u, details)
    else:
        raise CalibrationError(f"unknown spring_constant_method {km!r}")
    if km in ("reference_lever", "thermal") and "spring_constant_uncertainty" in cant:
        k_src += "; u(k) from tip YAML"
    return km, k_fun, k_src


def _reference_invols(ref, cant, reader, x, u, details):
    """The InvOLS of the test lever pressed on the reference lever (given or from its curves)
    into ``x``/``u``; returns where it came from."""
    if "deflection_sensitivity" in ref:
        x["invols_ref"], u["invols_ref"] = (
            ref["deflection_sensitivity"],
            ref.get("deflection_sensitivity_uncertainty", 0.0),
        )
        r_src = "InvOLS on the reference lever from tip YAML"
    elif "curves" in ref:
        x["invols_ref"], u["invols_ref"], r_src = _hard_sample_invols(
            {**cant, "ref_curves": ref["curves"]}, reader, details, "ref_curves", "reference_curves"
        )
        r_src = "InvOLS on the reference lever: " + r_src
    else:
        raise CalibrationError(
            "cantilever.reference_lever needs deflection_sensitivity or curves (InvOLS measured on the reference lever)"
        )
    return r_src


def _reference_details(x, u, length, tc) -> dict:
    """The reference-lever inputs as the forces file's calibration details list them."""
    return {
        "k_ref": (x["k_ref"], "N/m", "reference lever spring constant"),
        "u_k_ref": (u["k_ref"], "N/m", "its uncertainty"),
        "invols_ref": (x["invols_ref"], "m/V", "InvOLS of the test lever pressed on the reference lever"),
        "u_invols_ref": (u["invols_ref"], "m/V", "its uncertainty"),
        "length": (length if length is not None else np.nan, "m", "reference lever length L"),
        "offset": (x["dL"], "m", "loading point distance dL from the reference lever end"),
        "tilt": (x["theta"], "rad", "tilt angle"),
        "tilt_correction": (tc, "1", "k multiplied by cos^p(tilt): cos p=1, cos2 p=2, none p=0"),
    }


def _reference_setup(cant, reader, x, u, details):
    if "reference_lever" not in cant:
        raise CalibrationError("spring_constant_method 'reference_lever' needs cantilever.reference_lever")
    if not np.isfinite(x["invols"]):
        raise CalibrationError(
            "the reference-lever spring constant needs the InvOLS of the calibration session (the "
            "test lever on a hard sample): give cantilever.hard_sample_curves or deflection_sensitivity"
        )
    ref = with_defaults(cant["reference_lever"], REFERENCE_DEFAULTS)
    ref.setdefault("base_dir", cant.get("base_dir", "."))
    if "spring_constant" not in ref:
        raise CalibrationError("cantilever.reference_lever.spring_constant (k_ref) is required")
    x["k_ref"], u["k_ref"] = ref["spring_constant"], ref.get("spring_constant_uncertainty", 0.0)
    r_src = _reference_invols(ref, cant, reader, x, u, details)
    length = ref.get("length")
    if ref["offset"] and length is None:
        raise CalibrationError("cantilever.reference_lever.offset needs the reference lever length")
    if length is not None:
        x["L"], u["L"] = length, ref["length_uncertainty"]
    x["dL"], u["dL"] = ref["offset"], ref["offset_uncertainty"]
    x["theta"], u["theta"] = ref["tilt"], ref.get("tilt_uncertainty", 0.0)
    tc = ref["tilt_correction"]

    def k_fun(p):
        return reference_lever_k(
            p["k_ref"],
            p["invols"],
            p["invols_ref"],
            length=p.get("L"),
            offset=p["dL"],
            tilt=p["theta"],
            tilt_correction=tc,
        )

    try:
        k_fun(x)
    except ValueError as exc:
        raise CalibrationError(f"reference lever: {exc}") from None
    details["reference_lever"] = _reference_details(x, u, length, tc)
    src = (
        "reference lever (Tortonese & Kirk 1997): k = k_ref (L/(L-dL))^3 "
        f"(InvOLS_ref/InvOLS_hard - 1) cos^p(tilt), tilt_correction={tc}; {r_src}"
    )
    return k_fun, src


def _thermal_setup(cant, x, u, details):
    th = with_defaults(cant["thermal"], THERMAL_DEFAULTS)
    if "file" not in th:
        raise CalibrationError("cantilever.thermal.file (thermal noise record or PSD) is required")
    files = resolve_paths(cant, th["file"])
    if len(files) != 1:
        raise CalibrationError(f"cantilever.thermal.file {th['file']!r} matches {len(files)} files (need 1)")
    if th["lever_shape"] not in SHAPE_FACTOR:
        raise CalibrationError(f"cantilever.thermal.lever_shape must be one of {sorted(SHAPE_FACTOR)}")
    try:
        f, P, n_avg, unit = read_thermal_file(files[0])
        fit = fit_sho(f, P, fmin=th.get("frequency_min"), fmax=th.get("frequency_max"), n_avg=n_avg)
    except (ValueError, RuntimeError, OSError) as exc:
        raise CalibrationError(f"thermal calibration from {files[0]}: {exc}") from None
    if unit == "m":
        x["msq_m"], u["msq_m"] = fit.msq, fit.u_msq
        k_fun = lambda p: thermal_k(p["msq_m"], p["T"], th["lever_shape"])  # noqa: E731
    else:
        if np.isnan(x["invols"]):
            raise CalibrationError("thermal record in volts needs an InvOLS")
        x["msq_V"], u["msq_V"] = fit.msq, fit.u_msq
        k_fun = lambda p: thermal_k(p["msq_V"] * p["invols"] ** 2, p["T"], th["lever_shape"])  # noqa: E731
    x["T"], u["T"] = th["temperature"], th["temperature_uncertainty"]
    details["thermal"] = {
        "file": (str(files[0]), "1", "thermal noise record / PSD"),
        "f0": (fit.f0, "Hz", "resonance frequency of the SHO fit"),
        "Q": (fit.Q, "1", "quality factor"),
        "msq": (fit.msq, f"{unit}^2", "area of the first resonance <z^2> (before InvOLS)"),
        "u_msq": (fit.u_msq, f"{unit}^2", "its fit uncertainty"),
        "white": (fit.white, f"{unit}^2/Hz", "white floor"),
        "n_averages": (fit.n_avg, "1", "periodograms averaged (0: PSD given)"),
        "temperature": (x["T"], "K", "temperature"),
        "shape_factor": (SHAPE_FACTOR[th["lever_shape"]], "1", f"{th['lever_shape']} lever correction"),
    }
    src = (
        f"thermal noise ({th['lever_shape']}, C = {SHAPE_FACTOR[th['lever_shape']]}): k = "
        f"C k_B T/<z^2>, SHO fit f0 = {fit.f0:.5g} Hz, Q = {fit.Q:.3g}, file {files[0].name}"
    )
    return k_fun, src
