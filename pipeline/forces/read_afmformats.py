"""Instrument files through ``afmformats`` (JPK .jpk-force/-map/-qi, Asylum .ibw, ...).

afmformats returns force (N) = deflection (m) * k and deflection (m) = volts *
InvOLS with the file's calibration; we undo both to get volts, so the pipeline's
own calibration can replace the file's.  Files without calibration metadata
(afmformats' MissingMetaDataError) are re-read with 1 for what they lack (k, InvOLS or
both), so that part of the "force" column is undone with 1; what the file lacks is None.  Files
that store the instrument's force without its calibration (AFM Workshop CSV exports in nN) are
converted back to volts with the values the tip YAML gives (``reader['instrument_spring_constant']``,
``reader['instrument_deflection_sensitivity']``), or refused naming those settings.

Asylum .ibw: afmformats labels the whole ramp "approach"; the real split is in
the wave note (``Indexes: 0,1008,2015`` and ``Direction: NaN,1,-1``).

afmformats errors derive from BaseException, so they are caught by name and
re-raised as :class:`ForceCurveError` naming the file.
"""

from __future__ import annotations

import contextlib
import logging
from pathlib import Path

import numpy as np

from pipeline.forces.curve import ForceCurve, check_segments, split_at_turnaround
from pipeline.forces.errors import ForceCurveError


@contextlib.contextmanager
def _quiet_afmformats():
    """afmformats logs a traceback for every failing file; we report our own error."""
    log = logging.getLogger("afmformats")
    old = log.level
    log.setLevel(logging.CRITICAL + 1)
    try:
        yield
    finally:
        log.setLevel(old)


def _load(path: Path, meta_override=None):
    import afmformats
    import afmformats.errors as afe

    try:
        with _quiet_afmformats():
            return afmformats.load_data(path, modality="force-distance", meta_override=meta_override)
    except afe.MissingMetaDataError:
        raise
    except afe.AFMFileFormatError as exc:
        raise ForceCurveError(path, f"afmformats cannot read it ({type(exc).__name__}: {exc})") from None
    except (KeyboardInterrupt, SystemExit, GeneratorExit):
        raise
    except BaseException as exc:  # noqa: BLE001 - broken files raise anything (KeyError, zipfile errors, ...)
        raise ForceCurveError(path, f"afmformats cannot read it ({type(exc).__name__}: {exc})") from None


def _meta(md, key):
    """A metadata value as float, or None where afmformats has none (it raises on access)."""
    try:
        return float(md[key])
    except (KeyboardInterrupt, SystemExit):
        raise
    except BaseException:  # noqa: BLE001 - afmformats.meta.MetaDataMissingError derives from BaseException
        return None


def supported_suffixes() -> set[str]:
    import afmformats.formats as aff

    return set(aff.formats_by_suffix)


def _ibw_segments(path: Path):
    """(approach slice, retract slice) from an Asylum wave note, or None."""
    from igor2 import binarywave

    note = binarywave.load(str(path))["wave"]["note"]
    if isinstance(note, bytes):
        note = note.decode("latin-1")
    fields = dict(line.split(":", 1) for line in note.replace("\n", "\r").split("\r") if ":" in line)
    try:
        idx = [int(v) for v in fields["Indexes"].strip().strip(",").split(",")]
        dirs = [float(v) for v in fields["Direction"].strip().strip(",").split(",")]
    except (KeyError, ValueError):
        return None
    segs = [(idx[j - 1], idx[j], dirs[j]) for j in range(1, min(len(idx), len(dirs)))]
    app = next((s for s in segs if s[2] > 0), None)
    ret = next((s for s in segs if s[2] < 0 and app is not None and s[0] >= app[1]), None)
    if app is None or ret is None:
        return None
    return slice(app[0], app[1] + 1), slice(ret[0], ret[1] + 1)


def read_afmformats_curves(path, reader: dict | None = None) -> list[ForceCurve]:
    """All force-distance curves in an instrument file (maps give several)."""
    import afmformats.errors as afe

    path = Path(path)
    reader = reader or {}
    if not path.is_file():
        raise ForceCurveError(path, "file not found")
    if path.suffix not in supported_suffixes():
        raise ForceCurveError(
            path, f"extension {path.suffix!r} is not an afmformats format ({', '.join(sorted(supported_suffixes()))})"
        )
    missing = set()
    try:
        data = _load(path)
    except afe.MissingMetaDataError as exc:
        # re-read with 1.0 for what the file lacks: that part of the "force" is then raw
        missing = set(getattr(exc, "meta_keys", None) or ("sensitivity", "spring constant"))
        try:
            data = _load(path, meta_override={k: 1.0 for k in missing})
        except afe.MissingMetaDataError as exc2:
            raise ForceCurveError(path, f"afmformats: missing metadata {exc2}") from None
    if not data:
        raise ForceCurveError(path, "afmformats found no force-distance curve in it")
    hcol = "height (piezo)" if reader.get("afmformats_height", "measured") == "piezo" else "height (measured)"
    curves = []
    for j in range(len(data)):
        try:
            curves.append(_curve(path, data, j, missing, reader, hcol))
        except ForceCurveError:
            raise
        except (KeyboardInterrupt, SystemExit, GeneratorExit):
            raise
        except BaseException as exc:  # noqa: BLE001 - afmformats loads lazily: a broken file fails here
            raise ForceCurveError(path, f"afmformats cannot read it ({type(exc).__name__}: {exc})") from None
    return curves


def _curve(path, data, j, missing, reader, hcol) -> ForceCurve:
    """Curve ``j`` of an afmformats data set, in volts (module doc)."""
    fd = data[j]
    md = fd.metadata
    k_file, s_file = (None if key in missing else _meta(md, key) for key in ("spring constant", "sensitivity"))
    col = hcol if hcol in fd.columns else "height (piezo)"
    z = -np.asarray(fd[col], dtype=float)
    force = np.asarray(fd["force"], dtype=float)
    if "spring constant" not in missing and k_file is None:
        # the file stores the instrument's force (N) and not the calibration it was made with
        # (AFM Workshop exports): undone with the values the tip YAML says the instrument used
        k_i, s_i = reader.get("instrument_spring_constant"), reader.get("instrument_deflection_sensitivity")
        if not (k_i and s_i):
            raise ForceCurveError(
                path,
                "the file stores force (N) without the spring constant and deflection "
                "sensitivity the instrument computed it with; give cantilever.spring_constant "
                "and cantilever.deflection_sensitivity (the values set in the instrument)",
            )
        volts = force / (float(k_i) * float(s_i))
    else:
        volts = force / ((k_file or 1.0) * (s_file or 1.0))
    seg = np.asarray(fd["segment"])
    name = str(path) if len(data) == 1 else f"{path}#{j}"
    split = _ibw_segments(path) if path.suffix == ".ibw" else None
    if split is not None:
        parts = (z[split[0]], volts[split[0]], z[split[1]], volts[split[1]])
    elif np.any(seg == 1):
        parts = (z[seg == 0], volts[seg == 0], z[seg == 1], volts[seg == 1])
    else:
        parts = split_at_turnaround(name, z, volts)
    meta = {
        k: md[k]
        for k in ("instrument", "software", "date", "time", "speed approach", "speed retract", "point count")
        if k in md
    }
    curve = ForceCurve(
        name,
        *parts,
        defl_units="V",
        spring_constant=k_file,
        invols=s_file,
        source_format=str(md.get("format", "afmformats")),
        metadata=meta,
    )
    return check_segments(curve)
