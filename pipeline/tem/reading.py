"""Read TEM images (TIFF, PNG/JPEG, Gatan DM3/DM4) with their pixel size in metres.

Pixel-size sources, in order: the file's own calibration (TIFF ImageJ ``unit=``
+ X/YResolution, TIFF ResolutionUnit inch/cm + X/YResolution, the microscope software's
metadata read by rosettasciio -- Gatan DigitalMicrograph, FEI/Thermo, Zeiss, JEOL, TVIPS --, DM3/DM4
calibration), then the caller's value (tip YAML ``tem.pixel_size``).  A pixel size outside
0.01-2 nm is implausible for a tip-apex image (a unit wrong by 1000x or 25.4x): refused with a
hint, or replaced by ``tem.pixel_size`` where that is given.  NaN/inf pixels are replaced by the
median (noted); an image without a finite pixel is refused.  TIFF resolutions that
give pixels larger than 1 um are treated as screen/print DPI defaults, not a
calibration.  Different x and y calibrations are corrected by resampling the
coarser axis onto the finer pixel (up to a ratio of 2); anything else is
rejected with a message naming the file.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np

from pipeline.tem.errors import EmptyImageError, PixelSizeError, TemReadError
from pipeline.units import QuantityError, parse_quantity

__all__ = ["TemImage", "read_tem_image", "unit_to_metres"]

_MAX_TEM_PIXEL = 1e-6  # m; larger "calibrations" are DPI defaults (72 dpi = 0.35 mm)
_SQUARE_TOL = 5e-3  # relative x/y mismatch still taken as square
_UNIT_ALIASES = {
    "micron": "um",
    "microns": "um",
    "µm": "um",
    "μm": "um",
    "\\u00B5m": "um",
    "a": "angstrom",
    "å": "angstrom",
    "ang": "angstrom",
    "nanometer": "nm",
    "nanometers": "nm",
    "meter": "m",
    "metre": "m",
}


@dataclass
class TemImage:
    """Greyscale image ``data`` (float64, rows x cols) with square pixels of ``pixel_size`` m."""

    data: np.ndarray
    pixel_size: float
    source: str  # "tiff tags", "imagej metadata", "dm3 calibration", "dm4 calibration", "tip YAML"
    path: str = ""
    note: str = ""


def unit_to_metres(unit: str, where: str = "") -> float:
    """Length of one ``unit`` ("nm", "µm", "micron", "A"/"Å", "pm", "m", ...) in metres."""
    u = str(unit).strip()
    u = _UNIT_ALIASES.get(u.lower(), _UNIT_ALIASES.get(u, u))
    return parse_quantity(f"1 {u}", "length", where)


def _read_file(path):
    """(data, calibration (px_y, px_x) m or None, its source) of the image file by its suffix."""
    if not path.is_file():
        raise TemReadError(path, "file not found")
    if path.stat().st_size == 0:
        raise TemReadError(path, "file is empty (0 bytes)")
    suffix = path.suffix.lower()
    if suffix in (".tif", ".tiff"):
        data, cal, source = _read_tiff(path)
    elif suffix in (".dm3", ".dm4"):
        data, cal, source = _read_dm(path)
    elif suffix in (".png", ".jpg", ".jpeg", ".bmp"):
        data, cal, source = _read_plain(path), None, ""
    else:
        raise TemReadError(path, f"unsupported image format {suffix!r} (use .tif, .dm3, .dm4, .png, .jpg)")
    return data, cal, source


def _checked_data(data, path):
    """(grey float data with NaN/inf replaced, note): refuses empty, constant or non-finite images."""
    data = _to_grey(np.asarray(data), path)
    if data.size == 0 or data.ndim != 2 or min(data.shape) < 8:
        raise EmptyImageError(path, f"empty image (shape {data.shape})")
    finite = np.isfinite(data)
    note = ""
    if not finite.any():
        raise EmptyImageError(path, "no finite pixel values (every pixel is NaN or inf): not an image")
    if not finite.all():
        note = f"{int((~finite).sum())} NaN/inf pixels replaced by the median of the others; "
        data = np.where(finite, data, float(np.median(data[finite])))
    if float(data.max() - data.min()) <= 0:
        raise EmptyImageError(path, "empty image (all pixels have the same value)")
    return data, note


def _yaml_pixel_size(pixel_size, path, check_plausible):
    """The tip YAML's tem.pixel_size (m), checked."""
    px = parse_quantity(pixel_size, "length", str(path)) if isinstance(pixel_size, str) else float(pixel_size)
    if not (0 < px < _MAX_TEM_PIXEL):
        raise PixelSizeError(path, f"pixel size {px!r} m from the tip YAML is not a TEM pixel size")
    if check_plausible and not _plausible(px):
        raise PixelSizeError(path, _implausible(px, "tem.pixel_size of the tip YAML"))
    return px


def read_tem_image(path, pixel_size=None, check_plausible=True) -> TemImage:
    """Read ``path`` and return a :class:`TemImage` (data float, pixel size m, source).

    ``pixel_size`` (m, or a string such as "0.25 nm") is used only when the file
    has no calibration (or an implausible one).  ``check_plausible``: refuse pixel sizes outside
    ``PLAUSIBLE_PIXEL`` (a tip-apex image; off for reading any micrograph).  Raises TemReadError /
    PixelSizeError / EmptyImageError (ValueError subclasses) naming the file.
    """
    path = Path(path)
    data, cal, source = _read_file(path)
    data, note = _checked_data(data, path)

    if check_plausible and cal is not None and not _plausible(min(cal)) and pixel_size is not None:
        note += (
            f"the file's calibration ({min(cal) * 1e9:.4g} nm per pixel) is implausible for a tip image: the tip "
            "YAML's tem.pixel_size is used instead; "
        )
        cal = None
    if cal is None:
        if pixel_size is None:
            raise PixelSizeError(
                path,
                "no pixel size: the file carries no length calibration "
                "and none was given (set tem.pixel_size in the tip YAML)",
            )
        px = _yaml_pixel_size(pixel_size, path, check_plausible)
        return TemImage(data, px, "tip YAML", str(path), note.rstrip("; "))
    px_y, px_x = cal
    if check_plausible and not _plausible(min(px_y, px_x)):
        raise PixelSizeError(
            path,
            _implausible(min(px_y, px_x), f"the file's calibration ({source})")
            + "; give tem.pixel_size to override it",
        )
    if pixel_size is not None:
        note += "tip YAML pixel_size ignored: the file carries a calibration"
    data, px, extra = _square_pixels(data, px_y, px_x, path)
    return TemImage(data, px, source + extra, str(path), note.rstrip("; "))


PLAUSIBLE_PIXEL = (0.01e-9, 2e-9)  # m: a TEM image that resolves a worn tip's apex profile to ~0.1 nm


def _plausible(px: float) -> bool:
    return PLAUSIBLE_PIXEL[0] <= px <= PLAUSIBLE_PIXEL[1]


def _implausible(px: float, what: str) -> str:
    hint = ""
    for factor, cause in (
        (1000.0, "nm written as um, or pm as nm"),
        (25.4, "a millimetre read as an inch"),
        (10.0, "Angstrom read as nm"),
    ):
        for f in (factor, 1.0 / factor):
            if _plausible(px / f):
                hint = f" ({f:g}x too {'large' if f > 1 else 'small'}? {cause})"
                break
        if hint:
            break
    return (
        f"this pixel size ({px * 1e9:.4g} nm) from {what} is implausible for a TEM image of a tip apex "
        f"(expected {PLAUSIBLE_PIXEL[0] * 1e9:g}-{PLAUSIBLE_PIXEL[1] * 1e9:g} nm){hint}"
    )


def _square_pixels(data, px_y, px_x, path):
    if abs(px_x - px_y) <= _SQUARE_TOL * max(px_x, px_y):
        return data, 0.5 * (px_x + px_y), ""
    ratio = max(px_x, px_y) / min(px_x, px_y)
    if ratio > 2.0:
        raise PixelSizeError(
            path,
            f"non-square pixels ({px_x:.4g} m x {px_y:.4g} m, ratio {ratio:.2f}) "
            "cannot be corrected reliably; resample the image to square pixels",
        )
    import cv2

    px = min(px_x, px_y)
    h, w = data.shape
    new = (int(round(w * px_x / px)), int(round(h * px_y / px)))
    out = cv2.resize(data.astype(np.float64), new, interpolation=cv2.INTER_CUBIC)
    return out, px, f" (non-square {px_x:.4g} x {px_y:.4g} m resampled to square)"


def _to_grey(data, path):
    if data.dtype.names:  # DM RGBA structured
        data = np.stack([data[n] for n in data.dtype.names[:3]], axis=-1)
    if np.iscomplexobj(data):
        raise TemReadError(path, "complex image (FFT?) is not a TEM micrograph")
    if data.ndim == 3 and data.shape[-1] in (3, 4):
        data = data[..., :3].astype(np.float64) @ np.array([0.299, 0.587, 0.114])
    while data.ndim > 2:  # stacks: first frame
        data = data[0]
    return data.astype(np.float64)


def _read_plain(path):
    import cv2

    img = cv2.imread(str(path), cv2.IMREAD_UNCHANGED)
    if img is None:
        raise TemReadError(path, "unreadable or truncated image file")
    if img.ndim == 3:
        img = img[..., ::-1]  # BGR(A) -> RGB(A)
    return img


def _read_tiff(path):
    """TIFF data and calibration: the microscope software's own metadata through rosettasciio
    (Gatan DigitalMicrograph, FEI/Thermo, Zeiss, JEOL, TVIPS, ImageJ), else the resolution tags."""
    data, cal, source = _read_tiff_tags(path)
    if cal is None:
        rs = _rsciio_tiff_calibration(path)
        if rs is not None:
            cal, source = rs
    return data, cal, source


def _rsciio_tiff_calibration(path):
    """((px_y, px_x) m, source) from rosettasciio's TIFF reader, or None where it has no length axes."""
    import logging

    try:
        from rsciio.tiff import file_reader
    except ImportError:
        return None
    log = logging.getLogger("rsciio")
    old = log.level
    log.setLevel(logging.ERROR)
    try:
        items = file_reader(str(path), lazy=False)  # lazy would leave the file open
    except Exception:  # noqa: BLE001 - the tag reader has already read the data; no calibration then
        return None
    finally:
        log.setLevel(old)
    if not items:
        return None
    axes = [a for a in items[0]["axes"] if a.get("navigate") is not True]
    if len(axes) < 2:
        return None
    try:
        cal = tuple(float(a["scale"]) * unit_to_metres(str(a.get("units") or ""), str(path)) for a in axes[-2:])
    except (QuantityError, TypeError, ValueError):
        return None
    if min(cal) <= 0:
        return None
    software = str(items[0].get("original_metadata", {}).get("Software", "") or "").strip()
    return cal, "tiff metadata (rosettasciio" + (f", {software[:40]}" if software else "") + ")"


def _read_tiff_tags(path):
    import tifffile

    try:
        with tifffile.TiffFile(path) as tif:
            page = tif.pages[0]
            data = page.asarray()
            ij = tif.imagej_metadata or {}
            tags = page.tags
            xres = tags.get("XResolution")
            yres = tags.get("YResolution")
            runit = tags.get("ResolutionUnit")
            xres = _ratio(xres.value) if xres is not None else None
            yres = _ratio(yres.value) if yres is not None else None
            runit = int(runit.value) if runit is not None else 2
    except Exception as exc:  # tifffile raises many types for damaged files
        raise TemReadError(path, f"unreadable or truncated TIFF ({type(exc).__name__}: {exc})") from None
    if not xres or not yres:
        return data, None, ""
    unit = ij.get("unit")
    if unit:
        try:
            metres = unit_to_metres(unit, str(path))
        except QuantityError:
            metres = None  # "pixel", "inch" in ImageJ means uncalibrated here
        if metres is not None:
            cal = (metres / yres, metres / xres)
            return data, _check_cal(cal), "tiff tags (ImageJ unit)"
    per = {2: 0.0254, 3: 0.01}.get(runit)  # inch, centimetre; 1 = none
    if per is None:
        return data, None, ""
    cal = (per / yres, per / xres)
    return data, _check_cal(cal), "tiff tags"


def _ratio(value):
    if isinstance(value, tuple):
        return value[0] / value[1] if value[1] else 0.0
    return float(value)


def _check_cal(cal):
    """None if the TIFF resolution is a DPI default rather than a TEM calibration."""
    if min(cal) <= 0 or max(cal) > _MAX_TEM_PIXEL:
        return None
    return cal


def _read_dm(path):
    from rsciio.digitalmicrograph import file_reader

    kind = path.suffix.lower().lstrip(".")
    try:
        items = file_reader(str(path))
    except Exception as exc:
        raise TemReadError(path, f"unreadable or truncated {kind.upper()} file ({type(exc).__name__}: {exc})") from None
    images = [d for d in items if np.asarray(d["data"]).ndim >= 2]
    if not images:
        raise EmptyImageError(path, f"no 2-D image in the {kind.upper()} file")
    item = max(images, key=lambda d: np.asarray(d["data"]).size)
    axes = [a for a in item["axes"] if a.get("navigate") is not True] or item["axes"]
    data = np.asarray(item["data"])
    if len(axes) < 2:
        return data, None, ""
    ay, ax = axes[-2], axes[-1]
    units = (str(ay.get("units") or "").strip(), str(ax.get("units") or "").strip())
    if not units[0] and not units[1]:
        return data, None, ""
    try:
        cal = tuple(float(a["scale"]) * unit_to_metres(u, str(path)) for a, u in zip((ay, ax), units))
    except QuantityError:
        raise PixelSizeError(
            path, f"{kind.upper()} calibration units {units} are not lengths (diffraction pattern or spectrum?)"
        ) from None
    if min(cal) <= 0:
        raise PixelSizeError(path, f"{kind.upper()} calibration {cal} is not positive")
    return data, cal, f"{kind} calibration"
