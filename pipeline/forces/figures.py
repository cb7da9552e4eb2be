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
    accepted, outlier, label.  Force in nN vs distance in nm: the whole retract (left) and the
    adhesive part around the pull-offs (right; a stiff lever's small dip is invisible at the
    scale of its contact part)."""
    fig, (ax, az) = plt.subplots(1, 2, figsize=(11, 4.5), dpi=110, gridspec_kw={"width_ratios": [1, 1]})
    for a in (ax, az):
        for j, it in enumerate(items):
            color = f"C{j % 10}" if it["accepted"] else "0.6"
            a.plot(
                it["x"] * 1e9,
                it["force"] * 1e9,
                lw=0.7,
                color=color,
                alpha=0.8 if it["accepted"] else 0.5,
                marker="." if a is az else None,
                ms=2,
            )
            if it.get("baseline") is not None:
                a.plot(it["x"] * 1e9, it["baseline"] * 1e9, ls="--", lw=0.8, color=color)
            if it["accepted"]:
                a.plot(
                    [it["x_po"] * 1e9],
                    [it["F_po"] * 1e9],
                    marker="x" if it["outlier"] else "o",
                    ms=7,
                    mfc="none",
                    color=color,
                    mew=1.5,
                )
        a.axhline(0, color="k", lw=0.4)
        a.set_xlabel("piezo distance from pull-off (nm, away from sample)")
    ax.set_ylabel("force (nN)")
    F = np.array([it["F_po"] for it in items if it["accepted"]])
    if F.size:  # zoom: from the deepest pull-off to half of it above the baseline, a few dips wide
        depth = float(np.max(-F)) * 1e9
        spans = []
        for it in items:
            if it["accepted"]:
                near = (it["force"] < 0.5 * it["F_po"]) & (it["x"] < 0)
                spans.append(float(-it["x"][near].min()) * 1e9 if near.any() else depth)
        w = max(np.median(spans), 1e-3)
        az.set_xlim(-3.0 * w, 1.5 * w)
        az.set_ylim(-1.3 * depth, 0.6 * depth)
    az.set_title("adhesive part", fontsize=8)
    n_ok = sum(it["accepted"] for it in items)
    fig.suptitle(
        f"{title}  ({n_ok}/{n_total or len(items)} curves accepted; o pull-off, x outlier, grey rejected, -- baseline)",
        fontsize=8,
    )
    fig.tight_layout()
    with atomic_output(out_png) as tmp:
        fig.savefig(tmp, format="png")
    plt.close(fig)
