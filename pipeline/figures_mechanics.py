"""Mechanics figure like the paper's Fig. 7: pull-off force against the adhesion range h for the
four traction laws, elastic (the solver of pipeline.mechanics.elastic_contact) and rigid.

The paper's cases (Sec. 4.2, 4.3): E* = 164.8 GPa, W_A = 0.1 J/m^2 (ERRATA 3), tips R = 30 nm,
S = 1 and R = 10 nm, S = 2, h = 0.3-6 nm.  One row per tip; per chosen n a panel of F_p(h)
(markers: elastic; dashed: rigid closed forms; black line: M-D-n, the exact Dugdale solution)
and a panel of the elastic-vs-rigid difference (paper Fig. 7b, d) and of each law against M-D-n
(the "+17 % / -23 %" of Sec. 4.3 at n = 5).
"""
from __future__ import annotations

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402
from matplotlib.ticker import FuncFormatter, LogLocator, NullFormatter  # noqa: E402

from pipeline.h5io import atomic_output  # noqa: E402

NM = 1e-9
PAPER_TIPS = ((30 * NM, 1.0), (10 * NM, 2.0))
FILLS = ("none", "full", "left", "bottom")  # marker fill per n in the difference panels
LAW_STYLE = {"dugdale": ("k", "s", "Dugdale"), "lj": ("tab:blue", "o", "L-J 3-9 (z0 = h/0.974)"),
             "tri1": ("tab:green", "^", "Tri1"), "tri2": ("tab:red", "v", "Tri2 (h = peak separation)")}


def _h_axis(ax):
    ax.set_xscale("log")
    ax.xaxis.set_major_locator(LogLocator(base=10, subs=(1.0, 2.0, 5.0)))
    ax.xaxis.set_major_formatter(FuncFormatter(lambda v, _: f"{v:g}"))
    ax.xaxis.set_minor_formatter(NullFormatter())
    ax.set_xlabel("adhesion range h (nm)")


def fig7_data(ns=(2.0, 5.0), h_nm=None, E_star=164.8e9, W=0.1, tips=PAPER_TIPS, direct=True):
    """Pull-offs [N] per (tip, n, law): elastic (direct solve or table), rigid, and M-D-n."""
    import pipeline.mechanics as M
    from pipeline.mechanics.scaling import log_force_scale

    h = np.geomspace(0.3, 6.0, 9) if h_nm is None else np.asarray(h_nm, float)
    out = {"h_nm": h, "cases": []}
    for R, S in tips:
        for n in ns:
            Q = float(M.q_from_rs(n, R, S))
            lam = np.asarray(M.transition_parameter(n, Q, E_star, W, h * NM), float)
            scale = np.exp(log_force_scale(n, Q, E_star, W))
            case = {"R": R, "S": S, "n": n, "Lambda": lam,
                    "mdn": np.asarray(M.pulloff_force(n, Q, E_star, W, h * NM, exact=True), float), "laws": {}}
            for law in LAW_STYLE:
                rigid = np.asarray(M.pulloff_force(n, Q, E_star, W, h * NM, potential=law, model="rigid"), float)
                if direct:
                    el = np.array([M.elastic_pulloff(n, float(lv), law).pulloff_nd for lv in lam]) * scale
                else:
                    el = np.asarray(M.pulloff_force(n, Q, E_star, W, h * NM, potential=law, model="elastic"), float)
                case["laws"][law] = {"elastic": el, "rigid": rigid}
            out["cases"].append(case)
    return out


def plot_fig7(out_png, ns=(2.0, 5.0), direct=True, data=None):
    """Write the figure (one row per paper tip; F_p(h) per n, then the differences)."""
    data = data or fig7_data(ns=ns, direct=direct)
    h = data["h_nm"]
    ns = sorted({c["n"] for c in data["cases"]})
    tips = [(c["R"], c["S"]) for c in data["cases"][:: len(ns)]]
    fig, axes = plt.subplots(len(tips), len(ns) + 2, figsize=(4.2 * (len(ns) + 2), 3.9 * len(tips)), squeeze=False)
    for row, (R, S) in enumerate(tips):
        cases = [c for c in data["cases"] if c["R"] == R and c["S"] == S]
        for col, c in enumerate(cases):
            ax = axes[row, col]
            ax.plot(h, c["mdn"] * 1e9, "k-", lw=1.2, label="M-D-n (Dugdale, exact)")
            for law, (color, mk, lab) in LAW_STYLE.items():
                d = c["laws"][law]
                ax.plot(h, d["rigid"] * 1e9, ls="--", color=color, lw=1.0)
                ax.plot(h, d["elastic"] * 1e9, mk, color=color, ms=5, mfc="none" if law == "dugdale" else color,
                        label=f"{lab}: elastic (markers), rigid (dashed)")
            _h_axis(ax)
            if c["n"] > 2.0:
                ax.set_yscale("log")
                ax.yaxis.set_major_locator(LogLocator(base=10, subs=(1.0, 2.0, 5.0)))
                ax.yaxis.set_major_formatter(FuncFormatter(lambda v, _: f"{v:g}"))
                ax.yaxis.set_minor_formatter(NullFormatter())
            ax.set_ylabel("pull-off force F$_p$ (nN)")
            ax.set_title(f"R = {R / NM:g} nm, S = {S:g}, n = {c['n']:g}", fontsize=10)
            ax.grid(True, which="both", alpha=0.25)
        ax = axes[row, len(ns)]
        for c, fill in zip(cases, FILLS):
            for law, (color, mk, lab) in LAW_STYLE.items():
                d = c["laws"][law]
                ax.plot(h, 100 * (d["elastic"] / d["rigid"] - 1), mk + "-", color=color, ms=5, lw=0.8,
                        fillstyle=fill, label=f"{lab}, n = {c['n']:g}")
        ax.axhline(0, color="0.5", lw=0.8)
        _h_axis(ax)
        ax.set_ylabel("(elastic - rigid) / rigid (%)")
        ax.set_title("elastic vs rigid (paper Fig. 7b, d)", fontsize=10)
        ax.grid(True, which="both", alpha=0.25)
        ax = axes[row, len(ns) + 1]
        for c, fill in zip(cases, FILLS):
            for law, (color, mk, lab) in LAW_STYLE.items():
                d = c["laws"][law]
                ax.plot(h, 100 * (d["elastic"] / c["mdn"] - 1), mk + "-", color=color, ms=5, lw=0.8, fillstyle=fill)
            last = cases[-1]
            if c is last:
                for law in ("tri1", "tri2"):
                    v = 100 * (last["laws"][law]["elastic"][-1] / last["mdn"][-1] - 1)
                    ax.annotate(f"{v:+.1f} % (n = {last['n']:g})", (h[-1], v), xytext=(-75, -12 if v > 0 else 7),
                                textcoords="offset points",
                                fontsize=7.5, color=LAW_STYLE[law][0])
        ax.axhline(0, color="0.5", lw=0.8)
        _h_axis(ax)
        ax.set_ylabel("(elastic law - M-D-n) / M-D-n (%)")
        ax.set_title("vs M-D-n (paper: Tri1 +17 %, Tri2 -23 %, n = 5)", fontsize=10)
        ax.grid(True, which="both", alpha=0.25)
    handles = [plt.Line2D([], [], color="k", lw=1.2, label="M-D-n (Dugdale, exact)")]
    for law, (color, mk, lab) in LAW_STYLE.items():
        handles.append(plt.Line2D([], [], color=color, marker=mk, ls="none", label=f"{lab}, elastic",
                                  mfc="none" if law == "dugdale" else color))
        handles.append(plt.Line2D([], [], color=color, ls="--", label=f"{lab}, rigid"))
    fig.legend(handles=handles, loc="lower center", ncol=5, fontsize=8, frameon=False)
    src = "direct elastic solves" if direct else "elastic fast path (table)"
    fills = ", ".join(f"{f} n = {n:g}" for f, n in zip(("open", "filled", "left-filled", "bottom-filled"), ns))
    fig.suptitle(f"Pull-off vs adhesion range for four traction laws (paper Fig. 7): E* = 164.8 GPa, W$_A$ = 0.1 J/m$^2$; "
                 f"elastic = {src}; difference panels: {fills}", fontsize=10)
    fig.tight_layout(rect=(0, 0.07, 1, 0.96))
    with atomic_output(out_png) as tmp:
        fig.savefig(tmp, dpi=120, format="png")
    plt.close(fig)
    return data
