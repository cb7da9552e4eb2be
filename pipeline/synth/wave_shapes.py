"""The shape of every interval of a wear test measured as the workflow measures it: a
wave-optical TEM image (``pipeline.synth.tem_wave``, physics the edge fit does not share) run
through stage 1 (``extract_profile``) and stage 2 (``run_fit``), for the end-to-end study of
``pipeline.synth.calibration_study`` (``run_case(..., shapes="wave")``).

One tip keeps its materials over the wear test (the outer layer's kind, thickness and contrast,
the core's absorption, the shank); every interval is a new TEM session, so the imaging (voltage,
defocus, pixel, dose, detector, illumination, rotation) and the contamination near the apex are
drawn again, as are slight non-axisymmetric wear (flanks differing by up to 10 %).  The interval's
true pull-off scales with the true section area of the imaged body against the axisymmetric power
law (Eq. 12, rigid Dugdale: F = (W_A / h) pi r(h)^2; the limacon section of asymmetry e has
1 + e^2 / 2 times the area): ``area_factor``.

An interval whose stage 1 or 2 raises is lost, as a user would drop it after the workflow stopped
on it; one that stage 2 flags unusable is passed on (the inversion drops it and says so; an unusable
reference leaves the tip without an h, status ``no_reference``).
"""

from __future__ import annotations

import dataclasses
import tempfile
from pathlib import Path

import numpy as np

FIT_HEIGHT = 6e-9  # m, the stage-2 fit window
LAYERS = ("none", "oxide", "DLC")
IMAGE_SEED0 = 7_000_000  # image seeds: IMAGE_SEED0 + 16 x tip seed + interval (no overlap with the TEM grid's)


def tip_materials(seed: int) -> dict:
    """The tip's own draws for ``tem_wave.draw_params`` (kept over its intervals): the layer
    (none / oxide / DLC by ``seed`` mod 3) with its thickness and contrast, the core's absorption
    length, the contamination's contrast and the shank."""
    from pipeline.synth.tem_wave import draw_params

    p = draw_params(IMAGE_SEED0 + 16 * int(seed) + 15, layer=LAYERS[int(seed) % 3])
    keep = (
        "layer",
        "layer_thickness",
        "layer_contrast",
        "core_absorption_length_200kv",
        "contamination_contrast",
        "z_join",
        "shank_half_angle_deg",
        "blend_length",
    )
    out = {k: getattr(p, k) for k in keep}
    out["z_join"] = max(out["z_join"], 2.0 * FIT_HEIGHT)  # the power law holds over the fit window
    return out


def interval_params(seed: int, interval: int, n: float, R: float, S: float, materials: dict):
    """``TemWaveParams`` of one interval's image: the tip's shape and materials fixed, the rest
    drawn; the pixel is coarsened (x 1.15 per step) until the tip fits the 1024 px field."""
    from pipeline.synth.tem_wave import _fits, draw_params

    fixed = dict(materials, n=float(n), R=float(R), S=float(S))
    image_seed = IMAGE_SEED0 + 16 * int(seed) + int(interval)
    p = draw_params(image_seed, **fixed)
    while not _fits(dataclasses.asdict(p), p.shape[1] * p.pixel_size):
        fixed["pixel_size"] = p.pixel_size * 1.15
        p = draw_params(image_seed, **fixed)
    return p


def wave_interval_fit(p, fit_h5, workdir, S: float, h: float, defocus_known=False) -> dict:
    """Render ``p``, run stages 1 and 2 on it (the workflow defaults; with ``defocus_known`` stage 1
    is given the sign of the image's defocus, ``tem.defocus``) and write the stage-2 file ``fit_h5``.
    Returns a record: ``area_factor`` (true section area at the adhesion range
    ``h`` (m) over pi r_axi(h)^2 of the axisymmetric power law), the true and fitted n, sigma_n,
    the flags, ``lost`` and its reason, ``raised`` (the stage raised: no fit file)."""
    from pipeline.fits.io import read_fit
    from pipeline.fits.stage import run_fit
    from pipeline.synth.tem_wave import simulate, write_image
    from pipeline.synth.tem_wave_truth import lost_reason, sigma_n, true_section_area
    from pipeline.tem.io import write_profile_h5
    from pipeline.tem.profiles import extract_profile
    from pipeline.tem.reading import read_tem_image

    img, truth = simulate(p)
    h = np.asarray([h], float)
    r_axi = (p.n * p.Q * h) ** (1.0 / p.n)
    rec = dict(
        n_true=float(p.n),
        layer=p.layer,
        defocus_um=p.defocus * 1e6,
        pixel_nm=p.pixel_size * 1e9,
        snr=float(p.snr),
        asymmetry=float(p.asymmetry),
        area_factor=float(true_section_area(truth, h)[0] / (np.pi * r_axi[0] ** 2)),
    )
    with tempfile.TemporaryDirectory(dir=workdir) as tmp:
        path = Path(tmp) / "image.tif"
        write_image(path, img, p.pixel_size)
        try:
            image = read_tem_image(path, None)
            sign = ("underfocus" if p.defocus > 0 else "overfocus") if defocus_known and p.defocus else "auto"
            profile = extract_profile(image, defocus=sign)
            write_profile_h5(Path(tmp) / "profile.h5", image, profile)
            run_fit(Path(tmp) / "profile.h5", fit_h5, fit_height=FIT_HEIGHT, S=S)
        except Exception as exc:  # noqa: BLE001 - any failure of the stage: the user drops the interval
            Path(fit_h5).unlink(missing_ok=True)
            failed = dict(n_fit=np.nan, sigma_n=np.nan, flags="", raised=True)
            return dict(rec, **failed, lost=True, lost_reason=f"{type(exc).__name__}: {exc}")
    fit = read_fit(fit_h5)
    reason = lost_reason(fit)
    fitted = dict(n_fit=float(fit.n), sigma_n=sigma_n(fit), flags=" | ".join(fit.flags), raised=False)
    return dict(rec, **fitted, lost=bool(reason), lost_reason=reason)
