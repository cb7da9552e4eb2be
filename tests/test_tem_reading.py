"""Reader: pixel size from TIFF tags / ImageJ unit / DM calibration / caller; errors name the file."""

from __future__ import annotations

import numpy as np
import pytest
import tifffile

from pipeline.synth.tem_image import render_tem_image, write_tem_tiff
from pipeline.tem.errors import EmptyImageError, PixelSizeError, TemReadError
from pipeline.tem.reading import read_tem_image, unit_to_metres


@pytest.fixture(scope="module")
def small_image():
    img, _ = render_tem_image(2, 10e-9, 0.3e-9, shape=(96, 96), seed=1)
    return img


@pytest.mark.parametrize("unit", ["nm", "um", "cm"])
def test_tiff_tags_units(tmp_path, small_image, unit):
    p = tmp_path / f"t_{unit}.tif"
    write_tem_tiff(p, small_image, 0.3e-9, unit=unit)
    im = read_tem_image(p)
    assert im.pixel_size == pytest.approx(0.3e-9, rel=1e-6)
    assert im.source.startswith("tiff tags")
    assert im.data.dtype == np.float64 and im.data.shape == (96, 96)


def test_tiff_inch_dpi_default_is_not_a_calibration(tmp_path, small_image):
    p = tmp_path / "dpi.tif"
    tifffile.imwrite(p, small_image, resolution=(72, 72), resolutionunit="INCH")
    with pytest.raises(PixelSizeError, match="dpi.tif"):
        read_tem_image(p)
    assert read_tem_image(p, pixel_size="0.2 nm").source == "tip YAML"


def test_tiff_inch_calibration(tmp_path, small_image):
    p = tmp_path / "inch.tif"
    ppi = 0.0254 / 0.25e-9
    tifffile.imwrite(p, small_image, resolution=(ppi, ppi), resolutionunit="INCH")
    assert read_tem_image(p).pixel_size == pytest.approx(0.25e-9, rel=1e-6)


def test_non_square_pixels(tmp_path, small_image):
    p = tmp_path / "ns.tif"
    tifffile.imwrite(p, small_image, resolution=(1 / (0.2e-9 * 100), 1 / (0.3e-9 * 100)), resolutionunit="CENTIMETER")
    im = read_tem_image(p)  # y pixels 1.5x larger: resampled to square 0.2 nm
    assert im.pixel_size == pytest.approx(0.2e-9, rel=1e-6)
    assert im.data.shape == (144, 96) and "resampled" in im.source
    p2 = tmp_path / "ns3.tif"
    tifffile.imwrite(p2, small_image, resolution=(1 / (0.1e-9 * 100), 1 / (0.3e-9 * 100)), resolutionunit="CENTIMETER")
    with pytest.raises(PixelSizeError, match="ns3.tif.*non-square"):
        read_tem_image(p2)


def test_png_needs_yaml_pixel_size(tmp_path, small_image):
    import cv2

    p = tmp_path / "plain.png"
    cv2.imwrite(str(p), small_image)
    with pytest.raises(PixelSizeError, match=r"plain\.png.*no pixel size"):
        read_tem_image(p)
    im = read_tem_image(p, pixel_size="0.3 nm")
    assert im.pixel_size == pytest.approx(0.3e-9) and im.source == "tip YAML"
    q = tmp_path / "plain.jpg"
    cv2.imwrite(str(q), (small_image / 256).astype(np.uint8))
    assert read_tem_image(q, pixel_size=0.3e-9).data.shape == (96, 96)


def test_calibration_wins_over_yaml(tmp_path, small_image):
    p = tmp_path / "cal.tif"
    write_tem_tiff(p, small_image, 0.3e-9)
    im = read_tem_image(p, pixel_size=0.5e-9)
    assert im.pixel_size == pytest.approx(0.3e-9) and "ignored" in im.note


@pytest.mark.parametrize(
    "unit,metres", [("nm", 1e-9), ("µm", 1e-6), ("micron", 1e-6), ("A", 1e-10), ("Å", 1e-10), ("pm", 1e-12), ("m", 1.0)]
)
def test_units(unit, metres):
    assert unit_to_metres(unit) == pytest.approx(metres)


def test_bad_files(tmp_path, small_image):
    p = tmp_path / "trunc.tif"
    write_tem_tiff(p, small_image, 0.3e-9)
    data = p.read_bytes()
    p.write_bytes(data[: len(data) // 3])
    with pytest.raises(TemReadError, match=r"trunc\.tif.*(unreadable|truncated)"):
        read_tem_image(p)
    e = tmp_path / "empty.tif"
    e.write_bytes(b"")
    with pytest.raises(TemReadError, match=r"empty\.tif.*empty"):
        read_tem_image(e)
    g = tmp_path / "garbage.dm4"
    g.write_bytes(b"\x00\x01" * 100)
    with pytest.raises(TemReadError, match=r"garbage\.dm4.*unreadable"):
        read_tem_image(g)
    c = tmp_path / "flat.tif"
    write_tem_tiff(c, np.full((64, 64), 1000, np.uint16), 0.3e-9)
    with pytest.raises(EmptyImageError, match=r"flat\.tif.*empty image"):
        read_tem_image(c)
    with pytest.raises(TemReadError, match="missing.tif.*not found"):
        read_tem_image(tmp_path / "missing.tif")
    assert issubclass(TemReadError, ValueError)


def test_float_tiff_all_nan_or_inf_is_one_line(tmp_path):
    p = tmp_path / "nan.tif"
    tifffile.imwrite(p, np.full((64, 64), np.nan, np.float32), resolution=(4e7, 4e7), resolutionunit="CENTIMETER")
    with pytest.raises(EmptyImageError, match="nan.tif: no finite pixel values"):
        read_tem_image(p)
    img = np.random.default_rng(1).normal(1000, 10, (64, 64)).astype(np.float32)
    img[3, 4] = np.inf
    tifffile.imwrite(p, img, resolution=(4e7, 4e7), resolutionunit="CENTIMETER")
    im = read_tem_image(p)
    assert np.all(np.isfinite(im.data)) and "1 NaN/inf pixels replaced" in im.note


@pytest.mark.parametrize("cm_per_px, hint", [(0.25e-4, "1000x too large"), (0.1e-7 * 25.4, "inch")])
def test_implausible_calibration_is_refused_at_reading(tmp_path, small_image, cm_per_px, hint):
    """A calibration unit wrong by 1000x (0.25 um per pixel for 0.25 nm) or 25.4x is refused at
    the reading step naming the number (before: a fit on 2 points or n = 1.05 with a flag); a
    given tem.pixel_size replaces it, with a note."""
    img = small_image
    p = tmp_path / "bad.tif"
    tifffile.imwrite(p, img, resolution=(1 / cm_per_px, 1 / cm_per_px), resolutionunit="CENTIMETER")
    with pytest.raises(PixelSizeError, match="implausible for a TEM image of a tip apex") as exc:
        read_tem_image(p)
    if "1000x" in hint:
        assert hint in str(exc.value)
    im = read_tem_image(p, pixel_size="0.25 nm")
    assert im.pixel_size == pytest.approx(0.25e-9) and im.source == "tip YAML" and "implausible" in im.note
    with pytest.raises(PixelSizeError, match="tem.pixel_size of the tip YAML"):
        read_tem_image(p, pixel_size="250 nm")
