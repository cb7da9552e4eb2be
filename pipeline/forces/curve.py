"""The :class:`ForceCurve` container and splitting a ramp into approach/retract."""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from pipeline.forces.errors import ForceCurveError


@dataclass
class ForceCurve:
    """One force-distance curve.

    ``z_*``: piezo extension towards the sample (m), ``defl_*``: deflection in
    ``defl_units`` ("V" or "m"), positive = repulsive.  ``spring_constant`` (N/m)
    and ``invols`` (m/V) are the values stored in the file, or None.
    """

    path: str
    z_approach: np.ndarray
    defl_approach: np.ndarray
    z_retract: np.ndarray
    defl_retract: np.ndarray
    defl_units: str = "V"
    spring_constant: float | None = None
    invols: float | None = None
    source_format: str = "csv"
    metadata: dict = field(default_factory=dict)

    def deflection_volts(self, segment: str = "retract") -> np.ndarray:
        """Deflection of ``segment`` in V (converted with the file InvOLS if stored in m)."""
        d = self.defl_retract if segment == "retract" else self.defl_approach
        if self.defl_units == "V":
            return d
        if self.invols is None:
            raise ForceCurveError(
                self.path, "deflection is stored in metres and the file gives no InvOLS to convert it to volts"
            )
        return d / self.invols


def split_at_turnaround(path, z: np.ndarray, defl: np.ndarray):
    """Split one ramp at the maximum piezo extension (the direction sign change).

    Returns (z_app, d_app, z_ret, d_ret); the turning point belongs to both.
    """
    if z.size < 4:
        raise ForceCurveError(path, f"only {z.size} data points")
    i = int(np.argmax(z))
    if i == z.size - 1:
        raise ForceCurveError(
            path, "no retract segment: the piezo never reverses direction (extension is maximal at the last point)"
        )
    if i == 0:
        raise ForceCurveError(path, "no approach segment: the piezo only retracts")
    return z[: i + 1], defl[: i + 1], z[i:], defl[i:]


def check_segments(curve: ForceCurve, min_points: int = 10) -> ForceCurve:
    """Check both segments are present, finite and move the piezo the right way."""
    for name, z, d in (
        ("approach", curve.z_approach, curve.defl_approach),
        ("retract", curve.z_retract, curve.defl_retract),
    ):
        if z.size < min_points:
            raise ForceCurveError(curve.path, f"no {name} segment (only {z.size} points)")
        n_bad = int(np.count_nonzero(~np.isfinite(z)) + np.count_nonzero(~np.isfinite(d)))
        if n_bad:
            raise ForceCurveError(curve.path, f"{n_bad} NaN/inf values in the {name} segment")
    if curve.z_approach[-1] <= curve.z_approach[0]:
        raise ForceCurveError(
            curve.path,
            "the piezo moves away from the sample during the 'approach' segment (check force_curves.height_axis)",
        )
    if curve.z_retract[-1] >= curve.z_retract[0]:
        raise ForceCurveError(
            curve.path,
            "the piezo moves towards the sample during the 'retract' segment (check force_curves.height_axis)",
        )
    return curve
