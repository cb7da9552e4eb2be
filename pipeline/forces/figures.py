"""Figure of an interval's retract curves with baselines and detected pull-offs."""
from __future__ import annotations

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402

from pipeline.h5io import atomic_output  # noqa: E402


def plot_retracts(out_png, items, *, title="", n_total=None):
    """``items``: dicts with x (m, piezo distance from the pull-off point, positive away
    from the sample), force (N, relative to the baseline at the pull-off), baseline (N, same x), x_po, F_po (N),
    accepted, outlier, label.  Force in nN vs distance in nm."""
    fig, ax = plt.subplots(figsize=(7, 4.5), dpi=110)
    for j, it in enumerate(items):
        color = f"C{j % 10}" if it["accepted"] else "0.6"
        ax.plot(it["x"] * 1e9, it["force"] * 1e9, lw=0.7, color=color, alpha=0.8 if it["accepted"] else 0.5)
        if it.get("baseline") is not None:
            ax.plot(it["x"] * 1e9, it["baseline"] * 1e9, ls="--", lw=0.8, color=color)
        if it["accepted"]:
            ax.plot([it["x_po"] * 1e9], [it["F_po"] * 1e9], marker="x" if it["outlier"] else "o", ms=6, mfc="none", color=color)
    ax.set_xlabel("piezo distance from pull-off (nm, away from sample)")
    ax.set_ylabel("force (nN)")
    ax.axhline(0, color="k", lw=0.4)
    n_ok = sum(it["accepted"] for it in items)
    ax.set_title(f"{title}  ({n_ok}/{n_total or len(items)} curves accepted; o pull-off, x outlier, grey rejected, -- baseline)", fontsize=8)
    fig.tight_layout()
    with atomic_output(out_png) as tmp:
        fig.savefig(tmp, format="png")
    plt.close(fig)
