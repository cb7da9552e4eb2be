"""Figure of the profile stage: apex region with the detected silhouette and axis (nm)."""

from __future__ import annotations

import numpy as np

from pipeline import h5io


def plot_profile(image, profile, out_png, title=""):
    """Apex region of ``image`` (TemImage) with ``profile`` (TipProfile) edge, axis and apex."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    px = profile.pixel_size
    hpx = profile.profile_height / px
    e = profile.edge_px
    pad = 0.4 * hpx + 10
    r0 = int(max(0, np.floor(e[:, 0].min() - pad)))
    r1 = int(min(image.data.shape[0], np.ceil(e[:, 0].max() + pad)))
    c0 = int(max(0, np.floor(e[:, 1].min() - pad)))
    c1 = int(min(image.data.shape[1], np.ceil(e[:, 1].max() + pad)))
    crop = image.data[r0:r1, c0:c1]
    ext = np.array([c0 - 0.5, c1 - 0.5, r1 - 0.5, r0 - 0.5]) * px * 1e9
    fig, axes = plt.subplots(1, 2, figsize=(10, 4.6), gridspec_kw=dict(width_ratios=[1.2, 1]))
    ax = axes[0]
    ax.imshow(crop, cmap="gray", extent=ext, interpolation="nearest")
    left = profile.flank < 0
    ax.plot(e[left, 1] * px * 1e9, e[left, 0] * px * 1e9, ".", ms=1.5, color="tab:orange", label="left flank")
    ax.plot(e[~left, 1] * px * 1e9, e[~left, 0] * px * 1e9, ".", ms=1.5, color="tab:cyan", label="right flank")
    ol = (profile.edge_model.get("faint_layer") or {}).get("outer_layer") or {}
    if "core_edge_px" in ol:  # the edge was moved out to a faint layer: the fitted (core's) edge
        ce = ol["core_edge_px"]
        ax.plot(ce[:, 1] * px * 1e9, ce[:, 0] * px * 1e9, ".", ms=1.0, color="gold", label="fitted edge (core)")
    a = profile.apex_px
    u = profile.axis_px
    L = 1.1 * hpx
    ax.plot(
        [a[1] * px * 1e9, (a[1] + L * u[1]) * px * 1e9],
        [a[0] * px * 1e9, (a[0] + L * u[0]) * px * 1e9],
        "--",
        color="tab:red",
        lw=1,
        label="axis",
    )
    ax.plot(a[1] * px * 1e9, a[0] * px * 1e9, "+", color="tab:red", ms=10)
    ax.set_xlabel("x (nm)")
    ax.set_ylabel("y (nm)")
    ax.set_title(title or "apex region")
    ax.legend(fontsize=7, loc="best")
    ax = axes[1]
    for which, col in (("left", "tab:orange"), ("right", "tab:cyan")):
        r, z = profile.flank_rz(which)
        ax.plot((-r if which == "left" else r) * 1e9, z * 1e9, ".", ms=2, color=col)
    ax.set_xlabel("r (nm)")
    ax.set_ylabel("z (nm)")
    ax.set_aspect("equal")
    ax.set_title(
        f"profile, asymmetry {profile.asymmetry_mean * 1e9:+.2f} nm (rms {profile.asymmetry_rms * 1e9:.2f})", fontsize=9
    )
    _notes_below(fig, profile, ol)
    with h5io.atomic_output(out_png) as tmp:
        fig.savefig(tmp, dpi=120, format="png")
    plt.close(fig)


def _notes_below(fig, profile, ol):
    """The faint-layer and outer-layer notes (words) under the panels, and the layout."""
    import textwrap

    note = (profile.edge_model.get("faint_layer") or {}).get("note", "")
    if ol.get("note"):
        note = f"{note}; {ol['note']}"
    if not note:
        fig.tight_layout()
        return
    lines = textwrap.wrap(note, 150)
    fig.text(0.01, 0.01, "\n".join(lines), fontsize=7, va="bottom")
    fig.tight_layout(rect=(0, 0.03 * len(lines) + 0.035, 1, 1))
