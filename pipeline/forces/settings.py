"""Defaults of the tip-YAML sections ``force_curves:`` and ``cantilever:`` (SI values).

These mirror the ``default:`` entries of ``pipeline/schemas/tip.schema.yaml`` so the
stage also works on dicts that did not pass through the config loader.
"""

from __future__ import annotations

import glob
from pathlib import Path

READER_DEFAULTS = {
    "format": "auto",  # auto | csv | afmformats
    "columns": {"height": "height_nm", "deflection": "deflection_V", "segment": "segment"},
    "height_unit": "nm",
    "deflection_unit": "V",
    "height_axis": "height",  # height: grows away from the sample; extension: grows towards it
    "afmformats_height": "measured",  # measured (sensor) | piezo
    "baseline_gap": 0.2,  # fraction of the free retract range next to the jump left out of the baseline fit
    "min_baseline_points": 50,
    "pulloff_method": "fit",  # fit: line through the last contact points; min: raw minimum
    "pulloff_fit_points": 20,
    "min_pulloff_snr": 5.0,  # Delta must exceed this many baseline-noise rms
    "outlier_rule": "esd",  # esd: generalized ESD (Rosner 1983) | modified_z (Iglewicz & Hoaglin)
    "outlier_alpha": 0.01,  # significance of the ESD test (a curve is dropped only on strong evidence)
    "outlier_z": 3.5,  # modified z-score threshold (rule modified_z)
    "min_curves": 2,  # fewest accepted curves an interval needs (1: no scatter can be estimated)
}

CANTILEVER_DEFAULTS = {
    "spring_constant_method": "auto",  # auto | given | file | reference_lever | thermal
    # deflection_sensitivity_method: auto | contact | interval_curves | interval_given | given | hard_sample | file
    "deflection_sensitivity_method": "auto",
    "contact_fallback": "fail",  # fail | tip: an interval whose own curves give no contact slope
    "invols_check_sigma": 3.0,  # report a contact slope that disagrees with the InvOLS in use beyond this
    "contact_invols_floor": 0.005,  # relative systematic uncertainty of a contact-slope InvOLS
    "contact_fit_range": [0.2, 0.8],
    "contact_segment": "approach",
}

REFERENCE_DEFAULTS = {
    "offset": 0.0,
    "offset_uncertainty": 0.0,
    "length_uncertainty": 0.0,
    "tilt": 0.0,
    "tilt_correction": "cos",
}

THERMAL_DEFAULTS = {"temperature": 295.0, "temperature_uncertainty": 1.0, "lever_shape": "rectangular"}


def with_defaults(cfg: dict | None, defaults: dict) -> dict:
    """Shallow merge (``columns`` merged one level deeper)."""
    out = dict(defaults)
    for key, value in (cfg or {}).items():
        if value is None:
            continue
        if isinstance(value, dict) and isinstance(defaults.get(key), dict):
            out[key] = {**defaults[key], **value}
        else:
            out[key] = value
    return out


def resolve_paths(cfg: dict, pattern: str) -> list[Path]:
    """Files for a folder or glob ``pattern`` relative to ``cfg['base_dir']`` (sorted; hidden files skipped)."""
    base = Path(cfg.get("base_dir", "."))
    p = Path(pattern)
    p = p if p.is_absolute() else base / p
    if p.is_dir():
        files = [q for q in p.iterdir() if q.is_file() and not q.name.startswith(".")]
    elif p.is_file():
        files = [p]
    else:
        files = [Path(q) for q in glob.glob(str(p)) if Path(q).is_file()]
    return sorted(files)
