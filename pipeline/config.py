"""Load and validate the workflow config and the per-tip YAMLs.

Both files are checked against JSON schemas (``pipeline/schemas/*.schema.yaml``,
JSON Schema 2020-12) before any work starts.  Schema properties that carry the
custom keyword ``x-unit`` are quantity strings ("150 GPa"); they are converted
to SI floats here, with pint checking the dimension.  Every error names the
file and the key, and what was expected.
"""

from __future__ import annotations

import copy
import glob
import math
from pathlib import Path

import jsonschema
import numpy as np
import yaml

from pipeline.units import QuantityError, example_unit, parse_quantity

SCHEMA_DIR = Path(__file__).with_name("schemas")
TIP_SCHEMA = SCHEMA_DIR / "tip.schema.yaml"
WORKFLOW_SCHEMA = SCHEMA_DIR / "config.schema.yaml"

# Files accepted as force curves when an interval's `curves` names a folder.
CURVE_SUFFIXES = (
    ".csv",
    ".tsv",
    ".txt",
    ".dat",
    ".tab",
    ".jpk-force",
    ".jpk-force-map",
    ".jpk-qi-data",
    ".jpk-qi-series",
    ".ibw",
    ".h5",
    ".zip",
)


class ConfigError(ValueError):
    """A configuration file that is unreadable, invalid, or points at missing data."""


def read_schema(path: Path) -> dict:
    with open(path) as fh:
        return yaml.safe_load(fh)


def load_yaml(path) -> dict:
    path = Path(path)
    if not path.is_file():
        raise ConfigError(f"{path}: file not found" + (" (it is a folder)" if path.is_dir() else ""))
    try:
        with open(path, encoding="utf-8") as fh:
            data = yaml.safe_load(fh)
    except UnicodeDecodeError as exc:
        raw = path.read_bytes()
        line = raw[: exc.start].count(b"\n") + 1
        raise ConfigError(
            f"{path}: line {line}: byte 0x{raw[exc.start]:02x} is not UTF-8 (a Latin-1 'µ' or '°'?): save the "
            "file as UTF-8, or write the unit in ASCII ('um', 'deg')"
        ) from None
    except yaml.YAMLError as exc:
        raise ConfigError(f"{path}: not valid YAML ({exc})") from None
    if not isinstance(data, dict):
        raise ConfigError(f"{path}: expected a mapping of keys at the top level, got {type(data).__name__}")
    return data


def _resolve(node: dict, root: dict) -> dict:
    """Follow local ``$ref`` pointers, merging sibling keywords (x-unit, default)."""
    while "$ref" in node:
        ref = node["$ref"]
        if not ref.startswith("#/"):
            raise ValueError(f"only local $ref supported, got {ref}")
        target = root
        for part in ref[2:].split("/"):
            target = target[part]
        merged = dict(target)
        merged.update({k: v for k, v in node.items() if k != "$ref"})
        node = merged
    return node


def _key_path(parts) -> str:
    out = ""
    for p in parts:
        out += f"[{p}]" if isinstance(p, int) else (f".{p}" if out else str(p))
    return out or "<top level>"


def _schema_at(root: dict, path) -> dict:
    """The (resolved) schema node that describes the instance at ``path``."""
    node = _resolve(root, root)
    for part in path:
        if isinstance(part, int):
            node = _resolve(node.get("items", {}), root)
        else:
            props = dict(node.get("properties", {}))
            for branch in node.get("oneOf", []) + node.get("anyOf", []):
                props.update(_resolve(branch, root).get("properties", {}))
            node = _resolve(props.get(part, {}), root)
    return node


def _error_message(err: jsonschema.ValidationError, root: dict) -> str:
    where = _key_path(err.absolute_path)
    schema = _schema_at(root, err.absolute_path)
    if err.validator == "type" and "x-unit" in schema:
        kind = schema["x-unit"].replace("_", " ")
        return (
            f"{where}: {err.instance!r} has no unit; write a {kind} with its "
            f"unit, e.g. '{err.instance} {example_unit(schema['x-unit'])}'"
        )
    if err.validator == "pattern" and "x-unit" in schema:
        return f"{where}: {err.instance!r} is not '<number> <unit>' (a {schema['x-unit'].replace('_', ' ')})"
    if err.validator == "additionalProperties":
        allowed = sorted(schema.get("properties", {}))
        return f"{where}: {err.message}; allowed keys: {', '.join(allowed)}"
    if err.validator == "oneOf" and where.endswith("materials"):
        return f"{where}: give either E_star, or both tip and sample (each with E and nu), not both"
    if err.validator == "enum":
        return f"{where}: {err.instance!r} is not one of {err.validator_value}"
    if err.validator == "anyOf":
        alts = [_describe(_resolve(b, root)) for b in err.validator_value]
        return f"{where}: {err.instance!r} is not valid; expected {' or '.join(alts)}"
    return f"{where}: {err.message}"


def _describe(schema: dict) -> str:
    """What a schema branch accepts, in words (for anyOf errors)."""
    if "enum" in schema:
        return " / ".join(repr(v) for v in schema["enum"])
    if "x-unit" in schema:
        kind = schema["x-unit"].replace("_", " ")
        return f"a {kind} with its unit (e.g. '1.5 {example_unit(schema['x-unit'])}')"
    if schema.get("type") == "integer":
        lo, hi = schema.get("minimum"), schema.get("maximum")
        return f"an integer{f' {lo}..{hi}' if lo is not None and hi is not None else ''}"
    return schema.get("type", "a value")


def validate(instance: dict, schema: dict, source) -> None:
    """Validate ``instance`` against ``schema``; raise ConfigError listing every problem."""
    validator = jsonschema.Draft202012Validator(schema)
    errors = sorted(validator.iter_errors(instance), key=lambda e: (list(map(str, e.absolute_path)), e.message))
    if errors:
        lines = [_error_message(e, schema) for e in errors]
        raise ConfigError(f"{source}: invalid configuration:\n  - " + "\n  - ".join(lines))


def _apply_defaults(instance, schema: dict, root: dict):
    schema = _resolve(schema, root)
    if isinstance(instance, dict):
        for key, sub in schema.get("properties", {}).items():
            sub_r = _resolve(sub, root)
            if key not in instance and "default" in sub_r:
                instance[key] = copy.deepcopy(sub_r["default"])
            if key in instance:
                instance[key] = _apply_defaults(instance[key], sub_r, root)
    elif isinstance(instance, list) and "items" in schema:
        instance = [_apply_defaults(v, schema["items"], root) for v in instance]
    return instance


def _convert_quantities(instance, schema: dict, root: dict, source, path=()):
    """Replace every quantity string (schema keyword ``x-unit``) by its SI float."""
    schema = _resolve(schema, root)
    if "x-unit" in schema and isinstance(instance, str):
        try:
            return parse_quantity(instance, schema["x-unit"], where=f"{source}: {_key_path(path)}")
        except QuantityError as exc:
            raise ConfigError(str(exc)) from None
    if isinstance(instance, dict):
        props = dict(schema.get("properties", {}))
        for branch in schema.get("oneOf", []) + schema.get("anyOf", []):
            if isinstance(branch, dict):
                props.update(_resolve(branch, root).get("properties", {}))
        return {
            k: (_convert_quantities(v, props[k], root, source, path + (k,)) if k in props else v)
            for k, v in instance.items()
        }
    if isinstance(instance, list) and "items" in schema:
        return [_convert_quantities(v, schema["items"], root, source, path + (i,)) for i, v in enumerate(instance)]
    return instance


def validated(raw: dict, schema_path: Path, source) -> dict:
    """Schema-validate ``raw``, fill defaults and convert quantities to SI."""
    schema = read_schema(schema_path)
    raw = copy.deepcopy(raw)
    validate(raw, schema, source)
    raw = _apply_defaults(raw, schema, schema)
    return _convert_quantities(raw, schema, schema, source)


# --------------------------------------------------------------------------- workflow


def load_workflow_config(config) -> dict:
    """Validate the workflow config (a path or an already-loaded dict) -> SI dict."""
    source = config if not isinstance(config, dict) else "config/config.yaml"
    raw = load_yaml(config) if not isinstance(config, dict) else config
    cfg = validated(raw, WORKFLOW_SCHEMA, source)
    g = cfg["h_grid"]
    if not 0 < g["min"] < g["max"]:
        raise ConfigError(f"{source}: h_grid: need 0 < min < max, got min={g['min']:g} m, max={g['max']:g} m")
    rd = Path(str(cfg.get("results_dir", "results")))
    if rd.exists() and not rd.is_dir():
        raise ConfigError(
            f"{source}: results_dir: {str(rd)!r} is an existing file, not a folder; name a folder (or remove the file)"
        )
    return cfg


def h_grid(cfg: dict) -> np.ndarray:
    """The adhesion-range grid in metres from a validated workflow config."""
    g = cfg["h_grid"]
    if g["spacing"] == "log":
        return np.geomspace(g["min"], g["max"], g["points"])
    return np.linspace(g["min"], g["max"], g["points"])


# The workflow settings stage 4 (the inversion) reads; Snakemake reruns it when they change.
INVERSION_KEYS = ("h_grid", "traction_laws", "solver_mode", "monte_carlo")


def inversion_settings(cfg: dict) -> dict:
    """``run_inversion``'s keyword arguments from a validated workflow config: the h grid (m), the
    traction laws, the solver mode, the Monte Carlo size and its seed."""
    return {
        "h_grid": h_grid(cfg),
        "laws": list(cfg["traction_laws"]),
        "solver_mode": cfg["solver_mode"],
        "mc_samples": cfg["monte_carlo"]["samples"],
        "seed": cfg["monte_carlo"]["seed"],
    }


# --------------------------------------------------------------------------- tips


def reduced_modulus(E1: float, nu1: float, E2: float, nu2: float) -> float:
    """E* from Eq. 7: 1/E* = (1 - nu1^2)/E1 + (1 - nu2^2)/E2   [Pa]."""
    return 1.0 / ((1.0 - nu1**2) / E1 + (1.0 - nu2**2) / E2)


def list_curve_files(spec: str, data_dir: Path) -> list[Path]:
    """Force-curve files named by an interval's ``curves`` entry (a folder or a glob)."""
    target = data_dir / spec
    if target.is_dir():
        files = sorted(p for p in target.iterdir() if p.is_file() and p.name.lower().endswith(CURVE_SUFFIXES))
    else:
        files = sorted(Path(p) for p in glob.glob(str(target)) if Path(p).is_file())
    return files


def load_tip_config(path, check_files: bool = True) -> dict:
    """Validate one tip YAML and return an SI dict with resolved paths.

    Adds: ``name`` (file stem), ``source`` (the YAML path), ``data_dir`` (Path),
    ``E_star`` and ``u_E_star`` [Pa] in ``materials``, per interval ``image_path``
    (Path), ``curve_paths`` (list of Path) and ``reference`` (bool), and
    ``base_dir`` in the ``cantilever`` and ``force_curves`` sections.
    """
    path = Path(path)
    raw = load_yaml(path)
    raw.setdefault("tem", {})  # an absent section still gets its (unit-converted) defaults
    tip = validated(raw, TIP_SCHEMA, path)
    _check_physical(tip, path)
    tip["name"] = path.stem
    tip["source"] = str(path)
    data_dir = Path(tip["data_dir"])
    tip["data_dir"] = data_dir
    if check_files and not data_dir.is_dir():
        raise ConfigError(f"{path}: data_dir: folder {str(data_dir)!r} does not exist")

    _resolve_materials(tip["materials"], path)
    _check_intervals(tip, path)
    for i, iv in enumerate(tip["intervals"]):
        _resolve_interval(iv, i, tip, data_dir, path, check_files)

    tip.setdefault("cantilever", {})["base_dir"] = str(data_dir)
    tip.setdefault("force_curves", {})["base_dir"] = str(data_dir)
    return tip


def _resolve_materials(mat: dict, path) -> None:
    """E* (Eq. 7 from the two materials unless given) and its uncertainty, checked."""
    if "E_star" not in mat:
        mat["E_star"] = reduced_modulus(mat["tip"]["E"], mat["tip"]["nu"], mat["sample"]["E"], mat["sample"]["nu"])
    mat.setdefault("E_star_uncertainty", 0.0)
    mat["u_E_star"] = mat["E_star_uncertainty"]
    if not (math.isfinite(mat["E_star"]) and mat["E_star"] > 0):
        raise ConfigError(f"{path}: materials: E* must be positive, got {mat['E_star']:g} Pa")
    if mat["u_E_star"] >= mat["E_star"]:
        raise ConfigError(
            f"{path}: materials.E_star_uncertainty ({mat['u_E_star'] * 1e-9:.3g} GPa) is not smaller than "
            f"E* ({mat['E_star'] * 1e-9:.3g} GPa)"
        )


def _check_intervals(tip: dict, path) -> None:
    """Interval names unique; reference intervals among them, and at least one worn interval."""
    names = [iv["name"] for iv in tip["intervals"]]
    dupes = sorted({n for n in names if names.count(n) > 1})
    if dupes:
        raise ConfigError(f"{path}: intervals: duplicate interval name(s) {dupes}")
    for i, ref in enumerate(tip["reference_intervals"]):
        if ref not in names:
            raise ConfigError(f"{path}: reference_intervals[{i}]: {ref!r} is not an interval name (have {names})")
    if len(set(tip["reference_intervals"])) == len(names):
        raise ConfigError(
            f"{path}: reference_intervals: every interval is a "
            "reference; at least one worn interval is needed to find h"
        )


def _resolve_interval(iv: dict, i: int, tip: dict, data_dir: Path, path, check_files: bool) -> None:
    """An interval's reference flag and its files (image, curves, calibration curves), checked."""
    iv["reference"] = iv["name"] in tip["reference_intervals"]
    iv["image_path"] = data_dir / iv["image"]
    iv["curve_paths"] = list_curve_files(iv["curves"], data_dir) if data_dir.is_dir() else []
    if check_files:
        if not iv["image_path"].is_file():
            raise ConfigError(f"{path}: intervals[{i}].image: {str(iv['image_path'])!r} does not exist")
        if not iv["curve_paths"]:
            raise ConfigError(
                f"{path}: intervals[{i}].curves: no force-curve files found at {str(data_dir / iv['curves'])!r} "
                f"(expected a folder or glob of {', '.join(CURVE_SUFFIXES)})"
            )
    if "calibration_curves" in iv:
        iv["calibration_paths"] = list_curve_files(iv["calibration_curves"], data_dir) if data_dir.is_dir() else []
        if check_files and not iv["calibration_paths"]:
            raise ConfigError(
                f"{path}: intervals[{i}].calibration_curves: no force-curve files found at "
                f"{str(data_dir / iv['calibration_curves'])!r}"
            )
    if iv.get("deflection_sensitivity_uncertainty") is not None and "deflection_sensitivity" not in iv:
        raise ConfigError(
            f"{path}: intervals[{i}].deflection_sensitivity_uncertainty is given without deflection_sensitivity"
        )


# quantities that must be positive (by key, wherever they stand in a tip YAML); every
# ``*_uncertainty`` must be >= 0
POSITIVE_KEYS = {
    "E",
    "E_star",
    "spring_constant",
    "deflection_sensitivity",
    "pixel_size",
    "fit_height",
    "profile_height",
    "length",
    "temperature",
    "frequency_min",
    "frequency_max",
    "coating_thickness",
}


def _walk(node, path=()):
    if isinstance(node, dict):
        for k, v in node.items():
            yield from _walk(v, path + (k,))
    elif isinstance(node, list):
        for i, v in enumerate(node):
            yield from _walk(v, path + (i,))
    else:
        yield path, node


def _check_physical(tip: dict, source) -> None:
    """Values the schema's types allow but physics does not (one error per problem, file and key named)."""
    problems = []
    for path, v in _walk(tip):
        if not path or isinstance(path[-1], int) or isinstance(v, bool) or not isinstance(v, (int, float)):
            continue
        key = str(path[-1])
        if key in POSITIVE_KEYS and not (math.isfinite(v) and v > 0):
            problems.append(f"{_key_path(path)}: must be positive, got {v:g} (SI)")
        elif key.endswith("_uncertainty") and not (math.isfinite(v) and v >= 0):
            problems.append(f"{_key_path(path)}: an uncertainty must be >= 0, got {v:g} (SI)")
        elif key == "nu" and not (-1.0 < v <= 0.5):
            problems.append(f"{_key_path(path)}: Poisson's ratio must lie in (-1, 0.5], got {v:g}")
    tem = tip.get("tem", {})
    if tem.get("profile_height", np.inf) < tem.get("fit_height", 0):
        problems.append(
            f"tem.profile_height ({tem['profile_height'] * 1e9:.3g} nm) is below tem.fit_height "
            f"({tem['fit_height'] * 1e9:.3g} nm): the fit window needs a profile at least that high"
        )
    if problems:
        raise ConfigError(f"{source}: invalid configuration:\n  - " + "\n  - ".join(problems))


def discover_tips(cfg: dict) -> dict[str, Path]:
    """Map tip name -> YAML path for the tips selected by the workflow config."""
    tips_dir = Path(cfg["tips_dir"])
    if not tips_dir.is_dir():
        raise ConfigError(f"tips_dir: folder {str(tips_dir)!r} does not exist")
    found = {p.stem: p for p in sorted(tips_dir.glob("*.yaml"))}
    wanted = cfg.get("tips") or list(found)
    missing = [t for t in wanted if t not in found]
    if missing:
        raise ConfigError(f"tips: no YAML for {missing} in {str(tips_dir)!r} (have {sorted(found)})")
    if not wanted:
        raise ConfigError(f"tips_dir: no tip YAML files in {str(tips_dir)!r}")
    return {t: found[t] for t in wanted}
