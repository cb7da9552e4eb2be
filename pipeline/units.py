"""Physical quantities at the edges: parse "150 GPa" / "0.3 nm" / "0.2 N/m" to SI.

Pint does the parsing and dimension checking; inside the package every value is a
plain float in SI base units (m, kg, s, N, Pa, J/m^2, V, K, rad).
"""

from __future__ import annotations

import functools
import re


class QuantityError(ValueError):
    """A quantity string that cannot be read or has the wrong dimension."""


@functools.lru_cache(maxsize=1)
def registry():
    """pint's UnitRegistry, imported on first use: pint (with dask, which it probes) costs ~0.3 s
    of a job's start-up, and most jobs read every quantity from an already validated config."""
    import sys

    blocked = "dask" not in sys.modules
    if blocked:  # pint probes for dask (~0.2 s to import) only to support dask arrays, which we never give it
        sys.modules["dask"] = None
    try:
        import pint
    finally:
        if blocked and sys.modules.get("dask", 0) is None:
            del sys.modules["dask"]

    # Angstrom written as "A"/"Å" is mapped in parse_quantity (pint's "A" is ampere).
    # cache_folder=':auto:' keeps pint's parsed definitions on disk (start-up 0.3 s -> ~0.05 s)
    return pint.UnitRegistry(cache_folder=":auto:")


def _dimensionality(kind: str):
    ureg = registry()
    examples = {
        "length": "m",
        "pressure": "Pa",
        "stiffness": "N/m",
        "energy_per_area": "J/m^2",
        "force": "N",
        "sensitivity": "m/V",  # deflection sensitivity (InvOLS)
        "voltage": "V",
        "temperature": "K",
        "angle": "rad",
        "time": "s",
        "frequency": "Hz",
        "length_per_length": "m/m",
    }
    if kind not in examples:
        raise KeyError(f"unknown quantity kind {kind!r}")
    return ureg.Quantity(1.0, examples[kind]).dimensionality


_NUMBER_UNIT = re.compile(r"^\s*([-+]?(\d+\.?\d*|\.\d+)([eE][-+]?\d+)?)\s*(.*?)\s*$")


def parse_quantity(text, kind: str, where: str = "") -> float:
    """Parse a quantity string such as "150 GPa" and return its SI value (float).

    ``kind`` names the expected dimension ("length", "pressure", "stiffness",
    "energy_per_area", "force", "sensitivity", "voltage", "temperature",
    "angle", "time", "frequency").  A bare number for a dimensional kind is an
    error: units are mandatory.  ``where`` names the file/key for messages.
    """
    loc = f"{where}: " if where else ""
    if isinstance(text, bool) or not isinstance(text, (str, int, float)):
        raise QuantityError(f"{loc}expected a quantity with a unit (e.g. '1.5 nm'), got {text!r}")
    if isinstance(text, (int, float)):
        if kind == "angle":
            raise QuantityError(f"{loc}angle needs a unit ('deg' or 'rad'), got bare number {text!r}")
        unit = example_unit(kind)
        raise QuantityError(
            f"{loc}bare number {text!r} has no unit; write it with a "
            f"unit of {kind.replace('_', ' ')}, e.g. '{text} {unit}'"
        )
    m = _NUMBER_UNIT.match(text)
    if not m or not m.group(4):
        raise QuantityError(f"{loc}{text!r} is not '<number> <unit>' (e.g. '{_example(kind)}')")
    value, unit = float(m.group(1)), m.group(4)
    unit = unit.replace("µ", "u").replace("μ", "u")
    if unit in ("A", "Å"):
        unit = "angstrom"
    ureg = registry()
    try:
        q = ureg.Quantity(value, unit)
    except Exception as exc:  # pint raises several error types
        raise QuantityError(f"{loc}unknown unit {unit!r} in {text!r} ({exc})") from None
    want = _dimensionality(kind)
    if q.dimensionality != want:
        raise QuantityError(f"{loc}{text!r} is not a {kind.replace('_', ' ')} (expected units like '{_example(kind)}')")
    return float(q.to_base_units().magnitude)


def _example(kind: str) -> str:
    return {
        "length": "0.3 nm",
        "pressure": "150 GPa",
        "stiffness": "0.2 N/m",
        "energy_per_area": "0.05 J/m^2",
        "force": "10 nN",
        "sensitivity": "50 nm/V",
        "voltage": "1 V",
        "temperature": "295 K",
        "angle": "11 deg",
        "time": "1 s",
        "frequency": "70 kHz",
    }.get(kind, "1 unit")


def example_unit(kind: str) -> str:
    """A typical unit for a quantity kind, for messages ("nm" for "length")."""
    return _example(kind).split(" ", 1)[1]


def to_unit(value_si: float, unit: str) -> float:
    """Convert an SI value to ``unit`` (for reports and plots)."""
    ureg = registry()
    q = ureg.Quantity(1.0, unit).to_base_units()
    return value_si / q.magnitude
