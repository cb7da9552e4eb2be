"""Stage 2's figure: the profiles and power-law fits of all intervals of a tip."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from pipeline import h5io
from pipeline.fits.io import read_fit


def plot_tip_fits(fit_h5_paths, out_png, labels=None) -> None:
    """Profiles (points) and fits (lines) of all intervals of a tip on one plot (like Fig. 3a/c), nm axes."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(5.5, 4.2))
    labels = labels or [Path(p).stem for p in fit_h5_paths]
    cmap = plt.get_cmap("viridis")
    for i, (p, lab) in enumerate(zip(fit_h5_paths, labels)):
        fit = read_fit(p)
        col = cmap(i / max(1, len(fit_h5_paths) - 1))
        sgn = np.where(fit.flank < 0, -1.0, 1.0) if fit.flank is not None else 1.0
        ax.plot(sgn * fit.r * 1e9, (fit.z - fit.z0) * 1e9, "s", ms=2.5, mfc="none", color=col, alpha=0.6)
        rr = np.linspace(0, max(fit.r.max(), 1e-12), 200)
        flag = " (flagged)" if fit.flags else ""
        zm, e, xa = (fit.z_model(rr) - fit.z0) * 1e9, fit.flank_asymmetry, fit.axis_offset
        ax.plot(
            (xa + (1 + e) * rr) * 1e9,
            zm,
            "-",
            color=col,
            label=f"{lab}: n = {fit.n:.2f}, R = {fit.R * 1e9:.1f} nm{flag}",
        )
        ax.plot((xa - (1 - e) * rr) * 1e9, zm, "-", color=col)
    ax.set_xlabel("r (nm)")
    ax.set_ylabel("z (nm)")
    ax.set_title("TEM profiles and power-law fits (Eq. 1)")
    ax.legend(fontsize=7, loc="upper center")
    fig.tight_layout()
    with h5io.atomic_output(out_png) as tmp:
        fig.savefig(tmp, dpi=130, format="png")
    plt.close(fig)
