"""Images of the INDEPENDENT wave-optical simulator (``pipeline.synth.tem_wave``) shared by the TEM
tests: a clean tip, so that what a test varies is what it names; any image graded through the stage."""

from __future__ import annotations


def clean_tip(seed, layer, pixel_size, side, **kw):
    """A wave-simulator image of a clean tip (no particles, in focus, SNR 20, 16 bit, R 12 nm; ``kw``
    overrides or adds ``draw_params`` fields): (TemImage, truth, params)."""
    from pipeline.synth.tem_wave import draw_params, simulate
    from pipeline.tem.reading import TemImage

    fields = dict(
        layer=layer,
        apex_particles=False,
        shank_contamination=False,
        defocus=0.0,
        pixel_size=pixel_size,
        snr=20.0,
        bits=16,
        shape=(side, side),
        R=12e-9,
    )
    fields.update(kw)
    p = draw_params(seed, **fields)
    img, truth = simulate(p)
    return TemImage(img.astype(float), p.pixel_size, "synthetic"), truth, p


def graded_wave_image(tmp_path, p, **kw):
    """Render the independent wave-optical image of parameters ``p``, save it as ``tmp_path/img.tif``
    and grade the stage's profile of it against the true silhouette (``tem_wave_truth.evaluate_file``,
    with ``kw``, e.g. the tip YAML's ``defocus``)."""
    from pipeline.synth.tem_wave import simulate, write_image
    from pipeline.synth.tem_wave_truth import evaluate_file

    img, truth = simulate(p)
    write_image(tmp_path / "img.tif", img, p.pixel_size)
    return evaluate_file(tmp_path / "img.tif", truth, **kw)
