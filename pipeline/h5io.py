"""HDF5 intermediates: every dataset carries a ``units`` attribute, provenance goes
into attributes, and files are written atomically (a failed stage leaves nothing
that looks complete).

Light NeXus conventions (``NX_class`` on groups, ``units`` on datasets) help stock
viewers such as h5web or nexpy.
"""

from __future__ import annotations

import contextlib
import json
import os
import tempfile
from pathlib import Path

import h5py
import numpy as np


def _umask() -> int:
    """The process's file-mode creation mask (read without changing it where Linux allows)."""
    try:
        with open("/proc/self/status") as fh:
            for line in fh:
                if line.startswith("Umask:"):
                    return int(line.split()[1], 8)
    except OSError:
        pass
    mask = os.umask(0o022)  # elsewhere: read by setting and restoring it
    os.umask(mask)
    return mask


def _temporary_file_beside(path: Path, prefix: str, suffix: str) -> str:
    """An empty file in ``path``'s folder to write into and then rename onto ``path``.

    ``mkstemp`` creates it with mode 0600; it gets the mode ``open()`` would have given
    (0666 less the umask), so that results are readable by whoever the umask lets read them."""
    fd, tmp = tempfile.mkstemp(prefix=prefix, suffix=suffix, dir=path.parent)
    os.close(fd)
    os.chmod(tmp, 0o666 & ~_umask())
    return tmp


@contextlib.contextmanager
def atomic_h5(path, *, stage: str, **attrs):
    """Open a temporary HDF5 file for writing and move it to ``path`` on success.

    Root attributes: ``stage``, ``pipeline_version`` and any ``attrs`` given
    (dicts/lists are stored as JSON text).  On any exception the temporary file
    is removed and ``path`` is left untouched (or absent).  The file gets the mode ``open()``
    would give it (0666 less the umask).
    """
    from pipeline import __version__

    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = _temporary_file_beside(path, f".{path.name}.", ".part")
    try:
        with h5py.File(tmp, "w") as f:
            f.attrs["NX_class"] = "NXroot"
            f.attrs["stage"] = stage
            f.attrs["pipeline_version"] = __version__
            set_attrs(f, attrs)
            yield f
        os.replace(tmp, path)
    except BaseException:
        with contextlib.suppress(FileNotFoundError):
            os.unlink(tmp)
        raise


@contextlib.contextmanager
def atomic_output(path):
    """Yield a temporary path next to ``path``; rename it onto ``path`` on success.

    For non-HDF5 outputs (PNG, CSV) so that a failed job leaves no partial file.
    """
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = _temporary_file_beside(path, f".{path.stem}.", path.suffix)
    try:
        yield Path(tmp)
        os.replace(tmp, path)
    except BaseException:
        with contextlib.suppress(FileNotFoundError):
            os.unlink(tmp)
        raise


def _attr_value(value):
    if value is None:
        return "none"
    if isinstance(value, (dict, list, tuple)) and not (
        isinstance(value, (list, tuple)) and value and all(isinstance(v, (int, float)) for v in value)
    ):
        return json.dumps(value, default=str)
    if isinstance(value, Path):
        return str(value)
    return value


def set_attrs(obj, attrs: dict) -> None:
    """Store ``attrs`` on an h5py object; nested structures become JSON strings."""
    for key, value in attrs.items():
        obj.attrs[key] = _attr_value(value)


def write_dataset(group, name: str, data, units: str, description: str = "", **attrs):
    """Create dataset ``name`` with a mandatory ``units`` attribute ("1" for dimensionless).

    Strings are stored as variable-length UTF-8.
    """
    if units is None:
        raise ValueError(f"dataset {name!r} needs a units attribute ('1' if dimensionless)")
    arr = np.asarray(data)
    if arr.dtype.kind in ("U", "O"):
        arr = arr.astype(object)
        ds = group.create_dataset(name, data=arr, dtype=h5py.string_dtype())
    else:
        ds = group.create_dataset(name, data=arr)
    ds.attrs["units"] = units
    if description:
        ds.attrs["long_name"] = description
    set_attrs(ds, attrs)
    return ds


def create_group(parent, name: str, nx_class: str = "NXcollection", **attrs):
    grp = parent.create_group(name)
    grp.attrs["NX_class"] = nx_class
    set_attrs(grp, attrs)
    return grp


def read_dataset(group, name: str):
    """Return (array, units) for a dataset; strings are decoded to ``str``."""
    ds = group[name]
    data = ds[()]
    if isinstance(data, bytes):
        data = data.decode()
    elif isinstance(data, np.ndarray) and data.dtype.kind == "O":
        data = np.array([d.decode() if isinstance(d, bytes) else d for d in data.ravel()], dtype=object).reshape(
            data.shape
        )
    return data, ds.attrs.get("units", None)


def read_attr_json(obj, key: str):
    """Read an attribute written by :func:`set_attrs` (JSON text is decoded)."""
    value = obj.attrs[key]
    if isinstance(value, bytes):
        value = value.decode()
    if isinstance(value, str):
        try:
            return json.loads(value)
        except ValueError:
            return value
    return value


def require_group(f, name: str):
    """The group ``name`` of an open file, or a KeyError naming the file and the group."""
    if name in f:
        return f[name]
    raise KeyError(f"{f.file.filename}: no group {name!r}")


def read_value(group, name: str, default=None, *, required: bool = False):
    """A dataset's value (strings decoded) or else an attribute's; ``default`` when neither is
    there, a KeyError naming file, group and key when ``required``."""
    if name in group:
        return read_dataset(group, name)[0]
    if name in group.attrs:
        return group.attrs[name]
    if required:
        raise KeyError(f"{group.file.filename}:{group.name}: missing {name!r}")
    return default
