"""Figures of stage 5 (matplotlib Agg, PNG).

* ``plot_w_of_h``: W_A(h) per interval with the Monte-Carlo 16-84 % band, the reference
  band, each crossing with its 95 % CI and the global estimate (paper Fig. 3b/d), one
  panel per traction law.
* ``plot_adhesion_map``: R/h vs sigma_0/E* (log-log) with the Eq. 13 boundaries
  Lambda = Lambda_b(n) for n = 2..6 and this tip's intervals as lines over the h grid at
  the estimated W_A (paper Fig. 5).  With Q = S^(n-2) R^(n-1) and W_A = sigma_0 h, Eq. 8
  (corrected) gives Lambda^(2n-1) = (sigma_0/E*)^n (R/h)^(n-1) S^(n-2), i.e.
  Lambda = (sigma_0/E*)^(n/(2n-1)) (R_eff/h)^((n-1)/(2n-1)) with R_eff = Q^(1/(n-1)) =
  R S^((n-2)/(n-1)): plotting R_eff/h makes the map independent of S (R_eff = R for S = 1).
  Boundary: R_eff/h = (Lambda_b^(2n-1) / (sigma_0/E*)^n)^(1/(n-1)).

The rigid pull-off of the four laws against n (Fig. 8) is a mechanics figure
(``pipeline.mechanics.figures.plot_rigid_laws``).
"""

from __future__ import annotations

import numpy as np

from pipeline.adhesion_range.curves import CI_PCTS
from pipeline.adhesion_range.io import load_range
from pipeline.mechanics import lambda_boundary
from pipeline.plotting import plain_log_axis, plt, save_png

LAW_TITLES = {
    "dugdale": "Dugdale",
    "lj": "Lennard-Jones 3-9 (z0 = h/0.974)",
    "tri1": "Tri1",
    "tri2": "Tri2 (h = peak-stress separation; full range 2h)",
}
_LO, _HI = CI_PCTS.index(2.5), CI_PCTS.index(97.5)


DPI = 130


def _colors(k):
    cmap = plt.get_cmap("viridis")
    return [cmap(0.85 * i / max(k - 1, 1)) for i in range(k)]


def plot_w_of_h(range_h5, out_png, *, tip: str = ""):
    """W_A(h) curves with MC bands, the reference band and the crossings (Fig. 3b/d)."""
    rng = load_range(range_h5)
    tip = tip or rng["tip"]
    laws = rng["law_order"]
    ncol = 2 if len(laws) > 1 else 1
    nrow = int(np.ceil(len(laws) / ncol))
    fig, axes = plt.subplots(nrow, ncol, figsize=(6.2 * ncol, 4.6 * nrow), squeeze=False)
    worn = [nm for nm in rng["order"] if not rng["intervals"][nm]["reference"]]
    cols = dict(zip(worn, _colors(len(worn))))
    for ax, law in zip(axes.ravel(), laws):
        _w_of_h_panel(ax, rng, law, cols, tip)
    for ax in axes.ravel()[len(laws) :]:
        ax.set_visible(False)
    fig.suptitle(
        f"Tip {tip}: W$_A$(h) per wear interval (bands: MC 16-84 %; markers: crossings with 95 % CI)", fontsize=11
    )
    fig.tight_layout()
    save_png(fig, out_png, DPI)


def _w_of_h_panel(ax, rng: dict, law: str, cols: dict, tip: str) -> None:
    """One law's panel: every interval's W_A(h) with its band and crossing, the reference, the
    global estimate."""
    h_nm = rng["h"] * 1e9
    L = rng["laws"][law]
    ymin, ymax = [], []
    for nm in rng["order"]:
        lo, hi = _interval_curve(ax, h_nm, nm, rng["intervals"][nm], L["intervals"][nm], cols)
        if lo is not None:
            ymax.append(np.nanmax(hi[np.isfinite(hi)]) if np.any(np.isfinite(hi)) else np.nan)
            ymin.append(np.nanmin(lo[np.isfinite(lo)]) if np.any(np.isfinite(lo)) else np.nan)
    ref = L.get("reference")
    if ref is not None:
        rp = np.asarray(ref["W_ref_pcts"], float) * 1e3
        ax.fill_between(h_nm, rp[_LO], rp[_HI], color="tab:red", alpha=0.12, lw=0, label="reference W_A, 95 % band")
        ax.plot(h_nm, np.asarray(ref["W_ref"]) * 1e3, color="tab:red", lw=1.2, label="reference W_A")
    _global_marker(ax, h_nm, L.get("global", {}))
    ax.set_xscale("log")
    ax.set_yscale("log")
    fin_max = [v for v in ymax if np.isfinite(v)]
    fin_min = [v for v in ymin if np.isfinite(v) and v > 0]
    if fin_max and fin_min:
        ax.set_ylim(max(min(fin_min) * 0.8, 1e-3), max(fin_max) * 1.25)
    ax.set_xlim(h_nm[0], h_nm[-1])
    plain_log_axis(ax.xaxis)
    plain_log_axis(ax.yaxis)
    if rng["solver_mode"] == "auto":
        full = "M-D-n" if law == "dugdale" else "elastic solver"
        ax.text(
            0.98,
            0.98,
            f"solver auto: rigid where $\\Lambda < \\Lambda_b(n)$, else {full}\n(a step of <= 5 % where it switches)",
            transform=ax.transAxes,
            ha="right",
            va="top",
            fontsize=6.5,
            color="0.3",
        )
    ax.set_xlabel("adhesion range h (nm)")
    ax.set_ylabel("work of adhesion W$_A$ (mJ/m$^2$)")
    ax.set_title(f"{tip}: {LAW_TITLES.get(law, law)}", fontsize=10)
    ax.grid(True, which="both", alpha=0.25)
    ax.legend(fontsize=6.5, loc="best")


def _interval_curve(ax, h_nm, nm: str, d: dict, iv: dict, cols: dict):
    """An interval's W_A(h) with its 16-84 % band and, where it crosses the reference, the
    crossing with its 95 % CI; returns the band (lo, hi) in mJ/m^2, (None, None) without a curve."""
    w = np.asarray(iv["W_A"], float) * 1e3
    if not np.any(np.isfinite(w)):
        return None, None
    lo, hi = np.asarray(iv["W_A_p16"], float) * 1e3, np.asarray(iv["W_A_p84"], float) * 1e3
    ref = d["reference"]
    c = "0.25" if ref else cols[nm]
    lab = f"{nm} (n = {float(d['n']):.2f}{', ref.' if ref else ''}) [{iv['status']}]"
    ax.plot(h_nm, w, color=c, lw=2.2 if ref else 1.4, ls="--" if ref else "-", label=lab)
    ax.fill_between(h_nm, lo, hi, color=c, alpha=0.18 if not ref else 0.12, lw=0)
    if iv["status"] == "ok":
        hc = float(iv["h_cross"]) * 1e9
        wc = float(np.interp(np.log(hc), np.log(h_nm), w))
        hp = np.asarray(iv["h_pcts"], float) * 1e9
        xerr = [[hc - hp[_LO] if np.isfinite(hp[_LO]) else 0.0], [hp[_HI] - hc if np.isfinite(hp[_HI]) else 0.0]]
        ax.errorbar([hc], [wc], xerr=xerr, fmt="o", color=c, mec="k", ms=6, capsize=3, zorder=5)
    return lo, hi


def _global_marker(ax, h_nm, g: dict) -> None:
    """The global estimate with its 95 % interval of h, or its status."""
    if g and g.get("status") == "ok":
        hg = float(g["h"]) * 1e9
        hp = np.asarray(g["h_pcts"], float) * 1e9
        lo_, hi_ = (hp[_LO] if np.isfinite(hp[_LO]) else h_nm[0]), (hp[_HI] if np.isfinite(hp[_HI]) else h_nm[-1])
        ax.axvspan(lo_, hi_, color="tab:blue", alpha=0.08)
        ax.axvline(hg, color="tab:blue", lw=1.0, ls=":")
        ax.plot(
            [hg],
            [float(g["W_A"]) * 1e3],
            marker="*",
            ms=14,
            color="tab:blue",
            mec="k",
            zorder=6,
            label=f"global: h = {hg:.2f} nm [{lo_:.2f}, {hi_:.2f}], W_A = {float(g['W_A']) * 1e3:.1f} mJ/m$^2$",
        )
    else:
        ax.text(
            0.02,
            0.02,
            f"global estimate: {g.get('status', 'n/a') if g else 'n/a'}",
            transform=ax.transAxes,
            fontsize=8,
            color="tab:blue",
        )


def map_boundary(n, x, lam_b=None):
    """R_eff/h on the Eq. 13 boundary for sigma_0/E* = x (see module docstring)."""
    if lam_b is None:
        lam_b = float(lambda_boundary(float(n)))
    return (lam_b ** (2 * n - 1) / np.asarray(x, float) ** n) ** (1.0 / (n - 1.0))


def map_coordinates(W, h, n, Q, E_star):
    """(sigma_0/E*, R_eff/h) of a case: sigma_0 = W/h, R_eff = Q^(1/(n-1))."""
    h = np.asarray(h, float)
    return W / h / E_star, np.exp(np.log(Q) / (n - 1.0)) / h


def plot_adhesion_map(range_h5, out_png, *, tip: str = "", law: str = "dugdale"):
    """Adhesion map (Fig. 5) with this tip's intervals as lines over the h grid."""
    rng = load_range(range_h5)
    tip = tip or rng["tip"]
    E_star = rng["E_star"]
    L = rng["laws"].get(law) or rng["laws"][rng["law_order"][0]]
    g = L.get("global", {})
    if g and g.get("status") == "ok":
        W, src, h_est = float(g["W_A"]), "global estimate", float(g["h"])
    else:
        W = float(g.get("W_ref_at_h", np.nan)) if g else np.nan
        src, h_est = "reference W_A (no h estimate)", np.nan
    fig, ax = plt.subplots(figsize=(7.2, 5.6))
    x = np.logspace(-6, 0, 200)
    greys = plt.get_cmap("Greys")
    for k, n in enumerate(range(2, 7)):
        lb = float(lambda_boundary(float(n)))
        ax.plot(
            x,
            map_boundary(n, x, lb),
            color=greys(0.4 + 0.12 * k),
            lw=1.3,
            label=f"boundary n = {n} ($\\Lambda_b$ = {lb:.3f})",
        )
    lines = _map_intervals(ax, rng, W, h_est, E_star)
    if lines:
        ax.text(
            0.03,
            0.97,
            f"at h = {h_est * 1e9:.3g} nm:\n" + "\n".join(lines) if np.isfinite(h_est) else "\n".join(lines),
            transform=ax.transAxes,
            fontsize=7,
            va="top",
            family="monospace",
            bbox=dict(boxstyle="round", fc="white", ec="0.7", alpha=0.9),
        )
    ax.set_xscale("log")
    ax.set_yscale("log")
    ax.set_xlim(1e-6, 1)
    ax.set_ylim(1, 1e4)
    ax.set_xlabel(r"$\sigma_0/E^*$  ($\sigma_0 = W_A/h$)")
    ax.set_ylabel(r"$R\,S^{(n-2)/(n-1)}/h$  (= R/h for S = 1)")
    ax.text(
        0.97,
        0.04,
        "rigid regime: below/left of the boundary line of the interval's n\n"
        f"(E* = {E_star / 1e9:.3g} GPa, W$_A$ = {W * 1e3:.3g} mJ/m$^2$ from the {src};\n"
        "star = estimated h)",
        transform=ax.transAxes,
        fontsize=7.5,
        va="bottom",
        ha="right",
    )
    ax.set_title(f"Tip {tip}: adhesion map ({law}), Eq. 13 boundaries n = 2-6")
    ax.grid(True, which="both", alpha=0.2)
    ax.legend(fontsize=7, loc="upper right")
    fig.tight_layout()
    save_png(fig, out_png, DPI)


def _map_intervals(ax, rng: dict, W: float, h_est: float, E_star: float) -> list:
    """Each interval as a line over the h grid at W (its point at ``h_est`` starred); returns a
    line of text per interval: its Lambda against Lambda_b (Eq. 13) at h_est, or why it is
    not drawn."""
    h = rng["h"]
    cols = _colors(len(rng["order"]))
    lines = []
    nint = len(rng["order"])
    for i, (c, nm) in enumerate(zip(cols, rng["order"])):
        d = rng["intervals"][nm]
        n_used = float(d["n_used"])
        if not (np.isfinite(n_used) and np.isfinite(W)):
            lines.append(f"{nm}: not usable ({d['n_flag']})")
            continue
        q = float(np.exp(d["ln_Q_used"]))
        xs, ys = map_coordinates(W, h, n_used, q, E_star)
        # thicker lines first so that coinciding cases (same R_eff) stay visible
        ax.plot(
            xs,
            ys,
            color=c,
            lw=1.5 + 2.5 * (nint - 1 - i) / max(nint - 1, 1),
            solid_capstyle="butt",
            label=f"{nm}: n = {n_used:.2f}, R$_{{eff}}$ = {np.exp(np.log(q) / (n_used - 1)) * 1e9:.3g} nm",
        )
        ax.plot([xs[0]], [ys[0]], "o", color=c, ms=4)
        if i == 0:
            ax.annotate(
                f"h = {h[0] * 1e9:.2g} nm", (xs[0], ys[0]), xytext=(5, 2), textcoords="offset points", fontsize=7
            )
            ax.annotate(
                f"h = {h[-1] * 1e9:.3g} nm", (xs[-1], ys[-1]), xytext=(5, -8), textcoords="offset points", fontsize=7
            )
        if np.isfinite(h_est):
            xe, ye = map_coordinates(W, h_est, n_used, q, E_star)
            ax.plot([xe], [ye], "*", color=c, mec="k", ms=12, zorder=5)
            lam = (xe**n_used * ye ** (n_used - 1)) ** (1 / (2 * n_used - 1))
            lb = float(lambda_boundary(n_used))
            lines.append(
                f"{nm}: $\\Lambda$ = {lam:.3g} {'<' if lam < lb else '>='} $\\Lambda_b$ = {lb:.3g}"
                f" -> {'rigid valid' if lam < lb else 'M-D-n needed'}"
            )
    return lines
