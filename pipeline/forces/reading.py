"""Dispatch a force-curve file to the CSV or the afmformats reader."""

from __future__ import annotations

from pathlib import Path

from pipeline.forces.curve import ForceCurve
from pipeline.forces.errors import ForceCurveError
from pipeline.forces.read_afmformats import read_afmformats_curves
from pipeline.forces.read_csv import read_csv_curve
from pipeline.forces.settings import READER_DEFAULTS, with_defaults

CSV_SUFFIXES = {".csv", ".tsv", ".txt", ".dat"}


def _afmformats_suffixes() -> set[str]:
    from pipeline.forces.read_afmformats import supported_suffixes

    return {x.lower() for x in supported_suffixes()}


def read_curves(path, reader: dict | None = None) -> list[ForceCurve]:
    """Curves in one file (a list: instrument maps hold several).

    ``reader['format']``: ``auto`` (by extension: .csv/.tsv/.txt/.dat -> CSV, else afmformats;
    a text file the CSV layout does not fit but afmformats reads, such as an AFM Workshop
    export, goes to afmformats), ``csv`` or ``afmformats``.  Raises :class:`ForceCurveError`.
    """
    reader = with_defaults(reader, READER_DEFAULTS)
    path = Path(path)
    if not path.is_file():
        raise ForceCurveError(path, "file not found")
    fmt = reader["format"]
    auto = fmt == "auto"
    if auto:
        fmt = "csv" if path.suffix.lower() in CSV_SUFFIXES else "afmformats"
    if fmt == "csv":
        try:
            return [read_csv_curve(path, reader)]
        except ForceCurveError as exc:
            # an instrument's own text export (AFM Workshop .csv, NT-MDT .txt): afmformats knows it
            if auto and path.suffix.lower() in _afmformats_suffixes():
                try:
                    return read_afmformats_curves(path, reader)
                except ForceCurveError as exc2:
                    if "not an afmformats format" not in exc2.reason and "cannot read it" not in exc2.reason:
                        raise
            raise exc
    if fmt == "afmformats":
        return read_afmformats_curves(path, reader)
    raise ForceCurveError(path, f"unknown force_curves.format {fmt!r}")
