"""Dispatch a force-curve file to the CSV or the afmformats reader."""
from __future__ import annotations

from pathlib import Path

from pipeline.forces.curve import ForceCurve
from pipeline.forces.errors import ForceCurveError
from pipeline.forces.read_afmformats import read_afmformats_curves
from pipeline.forces.read_csv import read_csv_curve
from pipeline.forces.settings import READER_DEFAULTS, with_defaults

CSV_SUFFIXES = {".csv", ".tsv", ".txt", ".dat"}


def read_curves(path, reader: dict | None = None) -> list[ForceCurve]:
    """Curves in one file (a list: instrument maps hold several).

    ``reader['format']``: ``auto`` (by extension: .csv/.tsv/.txt/.dat -> CSV, else
    afmformats), ``csv`` or ``afmformats``.  Raises :class:`ForceCurveError`.
    """
    reader = with_defaults(reader, READER_DEFAULTS)
    path = Path(path)
    if not path.is_file():
        raise ForceCurveError(path, "file not found")
    fmt = reader["format"]
    if fmt == "auto":
        fmt = "csv" if path.suffix.lower() in CSV_SUFFIXES else "afmformats"
    if fmt == "csv":
        return [read_csv_curve(path, reader)]
    if fmt == "afmformats":
        return read_afmformats_curves(path, reader)
    raise ForceCurveError(path, f"unknown force_curves.format {fmt!r}")
