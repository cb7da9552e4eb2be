"""REAL microscope files through the reader.

HyperSpy 1.7.6 (GPL-3, on PyPI) ships real Gatan DM3 files and ImageJ/DM TIFFs
in its wheel (hyperspy/tests/io/...).  They are NOT copied into this repository:
the test downloads the wheel with pip into a cache directory
($PIPELINE_TEST_CACHE or ~/.cache/wear-adhesion-pipeline) and reads the
members from there; it is skipped with a reason when PyPI is unreachable.
"""

from __future__ import annotations

import os
import subprocess
import sys
import zipfile
from pathlib import Path

import pytest

from pipeline.tem.errors import EmptyImageError, PixelSizeError
from pipeline.tem.reading import read_tem_image

WHEEL_SPEC = "hyperspy==1.7.6"
MEMBERS = {
    "stem": "hyperspy/tests/io/dm3_2D_data/test_STEM_image.dm3",
    "um": "hyperspy/tests/io/tiff_files/test_dm_image_um_unit.dm3",
    "imagej": "hyperspy/tests/io/tiff_files/test_loading_image_saved_with_imageJ.tif",
    "imagej_noscale": "hyperspy/tests/io/tiff_files/test_loading_image_saved_with_imageJ_no_scale.tif",
    "dm_tif": "hyperspy/tests/io/tiff_files/test_loading_image_saved_with_DM.tif",
    "dm4_tiny": "hyperspy/tests/io/dm4_2D_data/test-1.dm4",
    "fei_zip": "hyperspy/tests/io/tiff_files/tiff_FEI_Helios.zip",
    "zeiss_zip": "hyperspy/tests/io/tiff_files/tiff_Zeiss_SEM.zip",
    "jeol_gz": "hyperspy/tests/io/tiff_files/JEOL-SightX-TEM-mag-dummy.tif.gz",
}


@pytest.fixture(scope="module")
def real_files():
    cache = Path(os.environ.get("PIPELINE_TEST_CACHE", Path.home() / ".cache" / "wear-adhesion-pipeline"))
    dest = cache / "hyperspy-1.7.6"
    if not all((dest / m).is_file() for m in MEMBERS.values()):
        dest.mkdir(parents=True, exist_ok=True)
        wheels = list(dest.glob("hyperspy-1.7.6-*.whl"))
        if not wheels:
            cmd = [
                sys.executable,
                "-m",
                "pip",
                "download",
                "--no-deps",
                "--only-binary",
                ":all:",
                "--disable-pip-version-check",
                "-q",
                WHEEL_SPEC,
                "-d",
                str(dest),
            ]
            try:
                subprocess.run(cmd, check=True, timeout=300, capture_output=True)
            except (subprocess.SubprocessError, OSError) as exc:
                pytest.skip(f"cannot download {WHEEL_SPEC} wheel from PyPI (offline?): {exc}")
            wheels = list(dest.glob("hyperspy-1.7.6-*.whl"))
            if not wheels:
                pytest.skip(f"no {WHEEL_SPEC} wheel for this platform")
        with zipfile.ZipFile(wheels[0]) as z:
            for m in MEMBERS.values():
                z.extract(m, dest)
    out = {k: dest / m for k, m in MEMBERS.items()}
    tiffs = out["fei_zip"].parent
    for key in ("fei_zip", "zeiss_zip"):  # archives inside the wheel: unpacked in the cache, read in place
        with zipfile.ZipFile(out[key]) as z:
            z.extractall(tiffs)
    import gzip

    jeol = tiffs / "JEOL-SightX-TEM-mag-dummy.tif"
    if not jeol.is_file():
        jeol.write_bytes(gzip.decompress(out["jeol_gz"].read_bytes()))
    out.update(fei=tiffs / "FEI-Helios-Ebeam-8bits.tif", zeiss=tiffs / "test_tiff_Zeiss_SEM_512pix.tif", jeol=jeol)
    return out


def test_real_dm3_stem_image_nm(real_files):
    im = read_tem_image(real_files["stem"])
    assert im.source == "dm3 calibration"
    assert im.pixel_size == pytest.approx(0.24853801727294922e-9, rel=1e-6)
    assert im.data.shape == (68, 68)


def test_real_dm3_tecnai_um_calibration_and_imagej_copy(real_files):
    """FEI Tecnai image in µm (DM3) and the same image saved by ImageJ (unit=micron)."""
    dm = read_tem_image(real_files["um"], check_plausible=False)  # 169 nm pixels: no tip-apex image
    ij = read_tem_image(real_files["imagej"], check_plausible=False)
    assert dm.pixel_size == pytest.approx(0.16867469e-6, rel=1e-6)
    assert ij.pixel_size == pytest.approx(dm.pixel_size, rel=1e-5)
    assert ij.source.startswith("tiff tags")


def test_real_uncalibrated_files_need_yaml(real_files):
    for key in ("imagej_noscale",):
        with pytest.raises(PixelSizeError, match=real_files[key].name):
            read_tem_image(real_files[key])
        assert read_tem_image(real_files[key], pixel_size="0.2 nm").source == "tip YAML"
    with pytest.raises(EmptyImageError, match="test-1.dm4"):
        read_tem_image(real_files["dm4_tiny"])  # 2x2 px DM4 written by Digital Micrograph


def test_microscope_software_tiff_calibrations_are_read(real_files):
    """Calibrated TIFFs written by Gatan DigitalMicrograph, FEI/Thermo (Helios), Zeiss and JEOL
    (SightX) software keep their calibration (rosettasciio reads their metadata; hyperspy's test
    files, values as hyperspy's own tests give them).  These are SEM / low-magnification images, so
    the tip-image plausibility check refuses them at reading, with the reason and the number."""
    from pipeline.tem.reading import _rsciio_tiff_calibration

    for key, px in (("dm_tif", 0.16867469e-6), ("fei", 3.3724e-6), ("zeiss", 1.1649976e-8), ("jeol", 1.8207885e-9)):
        cal, source = _rsciio_tiff_calibration(real_files[key])
        assert cal == pytest.approx((px, px), rel=1e-5), key
        assert source.startswith("tiff metadata (rosettasciio")
    im = read_tem_image(real_files["fei"], check_plausible=False)
    assert im.pixel_size == pytest.approx(3.3724e-6, rel=1e-5) and "rosettasciio" in im.source
    with pytest.raises(
        PixelSizeError, match=r"this pixel size \(1\.165e\+04 nm\)|this pixel size \(11650 nm\)|implausible"
    ):
        read_tem_image(real_files["zeiss"])
    with pytest.raises(PixelSizeError, match=r"168\.7 nm.*implausible.*1000x too large"):
        read_tem_image(real_files["dm_tif"])
