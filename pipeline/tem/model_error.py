"""The edge error the Beer-Lambert image model does not know (Fresnel fringes and phase contrast, a
layer read wrongly, the detector), shared by stage 1 (the edge covariance) and stage 2 (the fit's
covariance).

Where the silhouette fit's reduced chi^2 says the image is not the model's (chi2_red above
1 + 3 sqrt(2 / N), N its pixels: the reduced chi^2 of a model-true image scatters by sqrt(2 / N)
about 1), each flank's edge carries a smooth offset along its normal of SD ``EDGE_SYSTEMATIC_PX`` x g
pixels in each of the Legendre components 1, t, t^2 (t = 2 z / h - 1) over the fit window, the two
flanks independent, g = min(1, sqrt(chi2_red - 1 - 3 sqrt(2 / N))).  On wave-optical images
(``benchmarks/bench_tem_independent.py``) the Beer-Lambert edge lies a median 0.5 nm (1-5 px) off the
true silhouette; of 0.5, 0.75 and 1 px (83, 87, 92 % of n within 2 sigma_n) 1 px is the smallest that
reaches 90 % (set on that grid, not derived).  An image the model describes keeps the noise-only
covariance.

The part of it common to both flanks (their mean constant offset, SD ``EDGE_SYSTEMATIC_PX`` / sqrt 2
x g) is a property of the edge itself: stage 1 puts it into the edge covariance (a common offset of
the whole edge, ``common_offset_sd_px``), together with ``LAYER_SD`` x a found light layer (a layer the
fit found may be phase contrast read as one: false layers of 0.6-2.3 nm on 11 of 40 uncoated grid
images), and stage 2 then leaves that mode out of its own term.  With it the edge covariance covers the
edge's mean error at 2 sigma in 90 % of the grid's used images (39 % without; 88 % of a held-out set).
"""

from __future__ import annotations

import math

EDGE_SYSTEMATIC_PX = 1.0  # SD (px) of each smooth per-flank component, at full misfit
EDGE_SYSTEMATIC_DEGREE = 2  # Legendre degrees 0..2
LAYER_SD = 0.5  # common-offset SD per unit of a found light layer's thickness, at full misfit


def misfit_gain(chi2_red, n_pixels) -> float:
    """g in [0, 1] of the module doc: 0 where the image fit's reduced chi^2 is within 3 of its own
    SDs sqrt(2 / N) of 1 (or unknown), 1 where it exceeds 2 + that allowance."""
    if chi2_red is None or not math.isfinite(chi2_red):
        return 0.0
    allow = 3.0 * math.sqrt(2.0 / n_pixels) if n_pixels else 0.0
    return min(1.0, math.sqrt(max(float(chi2_red) - 1.0 - allow, 0.0)))


def common_offset_sd_px(chi2_red, n_pixels, coat_px=0.0) -> float:
    """SD (px) of the common offset of the whole edge that stage 1 adds to the edge covariance:
    g x sqrt(EDGE_SYSTEMATIC_PX^2 / 2 + (LAYER_SD x coat_px)^2)."""
    g = misfit_gain(chi2_red, n_pixels)
    return g * math.sqrt(EDGE_SYSTEMATIC_PX**2 / 2.0 + (LAYER_SD * float(coat_px)) ** 2)
