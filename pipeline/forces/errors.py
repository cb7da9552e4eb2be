"""Errors of the forces stage; every message names the file it is about."""
from __future__ import annotations


class ForceCurveError(ValueError):
    """A force curve that cannot be read or analysed (``path``: file, ``reason``: why)."""

    def __init__(self, path, reason: str):
        self.path = str(path)
        self.reason = reason
        super().__init__(f"{self.path}: {reason}")


class CalibrationError(ValueError):
    """Missing or inconsistent cantilever calibration (k, InvOLS)."""


class ForcesStageError(RuntimeError):
    """The stage cannot produce an output (e.g. every curve of the interval was rejected)."""
