"""Errors of the forces stage; every message names the file it is about."""

from __future__ import annotations

from pipeline.errors import FileError


class ForceCurveError(FileError):
    """A force curve that cannot be read or analysed (``path``: file, ``reason``: why)."""


class CalibrationError(ValueError):
    """Missing or inconsistent cantilever calibration (k, InvOLS)."""


class ForcesStageError(RuntimeError):
    """The stage cannot produce an output (e.g. every curve of the interval was rejected)."""
