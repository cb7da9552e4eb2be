"""Mechanics figures (matplotlib Agg, PNG).

``plot_fig7`` is like the paper's Fig. 7: pull-off force against the adhesion range h for the
four traction laws, elastic (the solver of pipeline.mechanics.elastic_contact) and rigid.

The paper's cases (Sec. 4.2, 4.3): E* = 164.8 GPa, W_A = 0.1 J/m^2 (ERRATA 3), tips R = 30 nm,
S = 1 and R = 10 nm, S = 2, h = 0.3-6 nm.  One row per tip; per chosen n a panel of F_p(h)
(markers: elastic; dashed: rigid closed forms; black line: M-D-n, the exact Dugdale solution)
and a panel of the elastic-vs-rigid difference (paper Fig. 7b, d) and of each law against M-D-n
(the "+17 % / -23 %" of Sec. 4.3 at n = 5).

``plot_rigid_laws`` is the paper's Fig. 8: the rigid pull-off of the L-J (Eq. 14), Tri1 and Tri2
laws over the rigid Dugdale one (Eq. 12) against n.
"""

from __future__ import annotations

import numpy as np

from pipeline import mechanics as M
from pipeline.mechanics.scaling import log_force_scale
from pipeline.plotting import plain_log_axis, plt, save_png

NM = 1e-9
PAPER_TIPS = ((30 * NM, 1.0), (10 * NM, 2.0))
FILLS = ("none", "full", "left", "bottom")  # marker fill per n in the difference panels
LAW_STYLE = {
    "dugdale": ("k", "s", "Dugdale"),
    "lj": ("tab:blue", "o", "L-J 3-9 (z0 = h/0.974)"),
    "tri1": ("tab:green", "^", "Tri1"),
    "tri2": ("tab:red", "v", "Tri2 (h = peak separation)"),
}


def _h_axis(ax):
    ax.set_xscale("log")
    plain_log_axis(ax.xaxis)
    ax.set_xlabel("adhesion range h (nm)")


def fig7_data(ns=(2.0, 5.0), h_nm=None, E_star=164.8e9, W=0.1, tips=PAPER_TIPS, direct=True):
    """Pull-offs [N] per (tip, n, law): elastic (direct solve or table), rigid, and M-D-n."""
    h = np.geomspace(0.3, 6.0, 9) if h_nm is None else np.asarray(h_nm, float)
    out = {"h_nm": h, "cases": []}
    for R, S in tips:
        for n in ns:
            Q = float(M.q_from_rs(n, R, S))
            lam = np.asarray(M.transition_parameter(n, Q, E_star, W, h * NM), float)
            scale = np.exp(log_force_scale(n, Q, E_star, W))
            case = {
                "R": R,
                "S": S,
                "n": n,
                "Lambda": lam,
                "mdn": np.asarray(M.pulloff_force(n, Q, E_star, W, h * NM, exact=True), float),
                "laws": {},
            }
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
            _pulloff_panel(axes[row, col], h, c)
        _rigid_difference_panel(axes[row, len(ns)], h, cases)
        _mdn_difference_panel(axes[row, len(ns) + 1], h, cases)
    handles = [plt.Line2D([], [], color="k", lw=1.2, label="M-D-n (Dugdale, exact)")]
    for law, (color, mk, lab) in LAW_STYLE.items():
        handles.append(
            plt.Line2D(
                [],
                [],
                color=color,
                marker=mk,
                ls="none",
                label=f"{lab}, elastic",
                mfc="none" if law == "dugdale" else color,
            )
        )
        handles.append(plt.Line2D([], [], color=color, ls="--", label=f"{lab}, rigid"))
    fig.legend(handles=handles, loc="lower center", ncol=5, fontsize=8, frameon=False)
    src = "direct elastic solves" if direct else "elastic fast path (table)"
    fills = ", ".join(f"{f} n = {n:g}" for f, n in zip(("open", "filled", "left-filled", "bottom-filled"), ns))
    fig.suptitle(
        f"Pull-off vs adhesion range for four traction laws (paper Fig. 7): E* = 164.8 GPa, W$_A$ = 0.1 J/m$^2$; "
        f"elastic = {src}; difference panels: {fills}",
        fontsize=10,
    )
    fig.tight_layout(rect=(0, 0.07, 1, 0.96))
    save_png(fig, out_png, 120)
    return data


def _pulloff_panel(ax, h, c: dict) -> None:
    """F_p(h) of one (tip, n): M-D-n, and every law elastic (markers) and rigid (dashed)."""
    ax.plot(h, c["mdn"] * 1e9, "k-", lw=1.2, label="M-D-n (Dugdale, exact)")
    for law, (color, mk, lab) in LAW_STYLE.items():
        d = c["laws"][law]
        ax.plot(h, d["rigid"] * 1e9, ls="--", color=color, lw=1.0)
        ax.plot(
            h,
            d["elastic"] * 1e9,
            mk,
            color=color,
            ms=5,
            mfc="none" if law == "dugdale" else color,
            label=f"{lab}: elastic (markers), rigid (dashed)",
        )
    _h_axis(ax)
    if c["n"] > 2.0:
        ax.set_yscale("log")
        plain_log_axis(ax.yaxis)
    ax.set_ylabel("pull-off force F$_p$ (nN)")
    ax.set_title(f"R = {c['R'] / NM:g} nm, S = {c['S']:g}, n = {c['n']:g}", fontsize=10)
    ax.grid(True, which="both", alpha=0.25)


def _rigid_difference_panel(ax, h, cases) -> None:
    """(elastic - rigid) / rigid of every law and n of one tip (paper Fig. 7b, d)."""
    for c, fill in zip(cases, FILLS):
        for law, (color, mk, lab) in LAW_STYLE.items():
            d = c["laws"][law]
            ax.plot(
                h,
                100 * (d["elastic"] / d["rigid"] - 1),
                mk + "-",
                color=color,
                ms=5,
                lw=0.8,
                fillstyle=fill,
                label=f"{lab}, n = {c['n']:g}",
            )
    ax.axhline(0, color="0.5", lw=0.8)
    _h_axis(ax)
    ax.set_ylabel("(elastic - rigid) / rigid (%)")
    ax.set_title("elastic vs rigid (paper Fig. 7b, d)", fontsize=10)
    ax.grid(True, which="both", alpha=0.25)


def _mdn_difference_panel(ax, h, cases) -> None:
    """(elastic law - M-D-n) / M-D-n of every law and n of one tip, Tri1 and Tri2 at the largest
    h and n annotated (the paper's +17 % / -23 % at n = 5)."""
    for c, fill in zip(cases, FILLS):
        for law, (color, mk, _label) in LAW_STYLE.items():
            d = c["laws"][law]
            ax.plot(h, 100 * (d["elastic"] / c["mdn"] - 1), mk + "-", color=color, ms=5, lw=0.8, fillstyle=fill)
        last = cases[-1]
        if c is last:
            for law in ("tri1", "tri2"):
                v = 100 * (last["laws"][law]["elastic"][-1] / last["mdn"][-1] - 1)
                ax.annotate(
                    f"{v:+.1f} % (n = {last['n']:g})",
                    (h[-1], v),
                    xytext=(-75, -12 if v > 0 else 7),
                    textcoords="offset points",
                    fontsize=7.5,
                    color=LAW_STYLE[law][0],
                )
    ax.axhline(0, color="0.5", lw=0.8)
    _h_axis(ax)
    ax.set_ylabel("(elastic law - M-D-n) / M-D-n (%)")
    ax.set_title("vs M-D-n (paper: Tri1 +17 %, Tri2 -23 %, n = 5)", fontsize=10)
    ax.grid(True, which="both", alpha=0.25)


def plot_rigid_laws(out_png, *, n_max: float = 20.0):
    """Rigid pull-off of the L-J, Tri1 and Tri2 laws over rigid Dugdale vs n (Fig. 8)."""
    n = np.linspace(2.0, n_max, 181)
    fig, ax = plt.subplots(figsize=(6.4, 4.4))
    styles = {"dugdale": ("k", "-"), "lj": ("tab:blue", "-"), "tri1": ("tab:green", "--"), "tri2": ("tab:red", "-.")}
    for law, (c, ls) in styles.items():
        r = np.asarray(M.rigid_pulloff_ratio(n, law), float) * np.ones_like(n)
        lab = {
            "dugdale": "Dugdale",
            "lj": f"L-J 3-9 (z0 = h/0.974, 1/0.974 = {1.0 / M.LJ_H_OVER_Z0:.4f})",
            "tri1": "Tri1 (peak 2$\\sigma_0$ at h/2, range h)",
            "tri2": "Tri2 (peak $\\sigma_0$ at h, range 2h)",
        }[law]
        ax.plot(n, r, color=c, ls=ls, lw=1.8, label=lab)
        if law != "dugdale":
            r5 = float(np.asarray(M.rigid_pulloff_ratio(5.0, law), float))
            ax.plot([5.0], [r5], "o", color=c, ms=4)
            ax.annotate(
                f"{r5:.3f}",
                (5.0, r5),
                xytext=(4, -10 if law == "tri1" else 4),
                textcoords="offset points",
                fontsize=7,
                color=c,
            )
    ax.set_xlabel("power index n")
    ax.set_ylabel(r"$F_{p,r}$ / $F_{p,r,\mathrm{Dugdale}}$  (same W$_A$, h)")
    ax.set_title("Rigid pull-off of the traction laws vs n (paper Fig. 8)")
    ax.set_xlim(2, n_max)
    ax.grid(True, alpha=0.3)
    ax.legend(fontsize=8)
    fig.tight_layout()
    save_png(fig, out_png, 130)
