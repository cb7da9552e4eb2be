"""Figures for stages 4-5 (matplotlib Agg, PNG).

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
* ``plot_rigid_laws``: rigid pull-off of the four laws vs n normalised by rigid Dugdale
  (paper Fig. 8).
"""
from __future__ import annotations

import matplotlib

matplotlib.use("Agg")
import h5py  # noqa: E402
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402
from matplotlib.ticker import FuncFormatter, LogLocator, NullFormatter  # noqa: E402

from pipeline.adhesion_range import CI_PCTS, load_range  # noqa: E402
from pipeline.h5io import atomic_output  # noqa: E402
from pipeline.inversion import LJ_Z0_OVER_H, lambda_boundary  # noqa: E402

LAW_TITLES = {"dugdale": "Dugdale", "lj": "Lennard-Jones 3-9 (z0 = h/0.974)", "tri1": "Tri1",
              "tri2": "Tri2 (h = peak-stress separation; full range 2h)"}
_LO, _HI = CI_PCTS.index(2.5), CI_PCTS.index(97.5)


def _plain_log_axis(axis):
    """Log axis with plain-number labels at 1-2-5 steps and unlabelled minor ticks."""
    axis.set_major_locator(LogLocator(base=10, subs=(1.0, 2.0, 5.0)))
    axis.set_major_formatter(FuncFormatter(lambda v, _: f"{v:g}"))
    axis.set_minor_formatter(NullFormatter())


def _save(fig, out_png, dpi=130):
    with atomic_output(out_png) as tmp:
        fig.savefig(tmp, dpi=dpi, format="png")
    plt.close(fig)


def _colors(k):
    cmap = plt.get_cmap("viridis")
    return [cmap(0.85 * i / max(k - 1, 1)) for i in range(k)]


def plot_w_of_h(range_h5, out_png, *, tip: str = ""):
    """W_A(h) curves with MC bands, the reference band and the crossings (Fig. 3b/d)."""
    rng = load_range(range_h5)
    tip = tip or rng["tip"]
    h_nm = rng["h"] * 1e9
    laws = rng["law_order"]
    ncol = 2 if len(laws) > 1 else 1
    nrow = int(np.ceil(len(laws) / ncol))
    fig, axes = plt.subplots(nrow, ncol, figsize=(6.2 * ncol, 4.6 * nrow), squeeze=False)
    worn = [nm for nm in rng["order"] if not rng["intervals"][nm]["reference"]]
    cols = dict(zip(worn, _colors(len(worn))))
    for ax, law in zip(axes.ravel(), laws):
        L = rng["laws"][law]
        ymax, ymin = [], []
        for nm in rng["order"]:
            d = rng["intervals"][nm]
            iv = L["intervals"][nm]
            w = np.asarray(iv["W_A"], float) * 1e3
            if not np.any(np.isfinite(w)):
                continue
            lo, hi = np.asarray(iv["W_A_p16"], float) * 1e3, np.asarray(iv["W_A_p84"], float) * 1e3
            ref = d["reference"]
            c = "0.25" if ref else cols[nm]
            lab = f"{nm} (n = {float(d['n']):.2f}{', ref.' if ref else ''}) [{iv['status']}]"
            ax.plot(h_nm, w, color=c, lw=2.2 if ref else 1.4, ls="--" if ref else "-", label=lab)
            ax.fill_between(h_nm, lo, hi, color=c, alpha=0.18 if not ref else 0.12, lw=0)
            ymax.append(np.nanmax(hi[np.isfinite(hi)]) if np.any(np.isfinite(hi)) else np.nan)
            ymin.append(np.nanmin(lo[np.isfinite(lo)]) if np.any(np.isfinite(lo)) else np.nan)
            if iv["status"] == "ok":
                hc = float(iv["h_cross"]) * 1e9
                wc = float(np.interp(np.log(hc), np.log(h_nm), w))
                hp = np.asarray(iv["h_pcts"], float) * 1e9
                xerr = [[hc - hp[_LO] if np.isfinite(hp[_LO]) else 0.0], [hp[_HI] - hc if np.isfinite(hp[_HI]) else 0.0]]
                ax.errorbar([hc], [wc], xerr=xerr, fmt="o", color=c, mec="k", ms=6, capsize=3, zorder=5)
        ref = L.get("reference")
        if ref is not None:
            rp = np.asarray(ref["W_ref_pcts"], float) * 1e3
            ax.fill_between(h_nm, rp[_LO], rp[_HI], color="tab:red", alpha=0.12, lw=0,
                            label="reference W_A, 95 % band")
            ax.plot(h_nm, np.asarray(ref["W_ref"]) * 1e3, color="tab:red", lw=1.2, label="reference W_A")
        g = L.get("global", {})
        if g and g.get("status") == "ok":
            hg = float(g["h"]) * 1e9
            hp = np.asarray(g["h_pcts"], float) * 1e9
            lo_, hi_ = (hp[_LO] if np.isfinite(hp[_LO]) else h_nm[0]), (hp[_HI] if np.isfinite(hp[_HI]) else h_nm[-1])
            ax.axvspan(lo_, hi_, color="tab:blue", alpha=0.08)
            ax.axvline(hg, color="tab:blue", lw=1.0, ls=":")
            ax.plot([hg], [float(g["W_A"]) * 1e3], marker="*", ms=14, color="tab:blue", mec="k", zorder=6,
                    label=f"global: h = {hg:.2f} nm [{lo_:.2f}, {hi_:.2f}], W_A = {float(g['W_A']) * 1e3:.1f} mJ/m$^2$")
        else:
            ax.text(0.02, 0.02, f"global estimate: {g.get('status', 'n/a') if g else 'n/a'}", transform=ax.transAxes,
                    fontsize=8, color="tab:blue")
        ax.set_xscale("log")
        ax.set_yscale("log")
        fin_max = [v for v in ymax if np.isfinite(v)]
        fin_min = [v for v in ymin if np.isfinite(v) and v > 0]
        if fin_max and fin_min:
            ax.set_ylim(max(min(fin_min) * 0.8, 1e-3), max(fin_max) * 1.25)
        ax.set_xlim(h_nm[0], h_nm[-1])
        _plain_log_axis(ax.xaxis)
        _plain_log_axis(ax.yaxis)
        if rng["solver_mode"] == "auto":
            full = "M-D-n" if law == "dugdale" else "elastic solver"
            ax.text(0.98, 0.98, f"solver auto: rigid where $\\Lambda < \\Lambda_b(n)$, else {full}\n(a step of <= 5 % where it switches)",
                    transform=ax.transAxes, ha="right", va="top", fontsize=6.5, color="0.3")
        ax.set_xlabel("adhesion range h (nm)")
        ax.set_ylabel("work of adhesion W$_A$ (mJ/m$^2$)")
        ax.set_title(f"{tip}: {LAW_TITLES.get(law, law)}", fontsize=10)
        ax.grid(True, which="both", alpha=0.25)
        ax.legend(fontsize=6.5, loc="best")
    for ax in axes.ravel()[len(laws):]:
        ax.set_visible(False)
    fig.suptitle(f"Tip {tip}: W$_A$(h) per wear interval (bands: MC 16-84 %; markers: crossings with 95 % CI)",
                 fontsize=11)
    fig.tight_layout()
    _save(fig, out_png)


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
    with h5py.File(range_h5, "r") as f:
        E_star = float(f.attrs["E_star"])
    h = rng["h"]
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
        ax.plot(x, map_boundary(n, x, lb), color=greys(0.4 + 0.12 * k), lw=1.3,
                label=f"boundary n = {n} ($\\Lambda_b$ = {lb:.3f})")
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
        ax.plot(xs, ys, color=c, lw=1.5 + 2.5 * (nint - 1 - i) / max(nint - 1, 1), solid_capstyle="butt",
                label=f"{nm}: n = {n_used:.2f}, R$_{{eff}}$ = {np.exp(np.log(q) / (n_used - 1)) * 1e9:.3g} nm")
        ax.plot([xs[0]], [ys[0]], "o", color=c, ms=4)
        if i == 0:
            ax.annotate(f"h = {h[0] * 1e9:.2g} nm", (xs[0], ys[0]), xytext=(5, 2), textcoords="offset points", fontsize=7)
            ax.annotate(f"h = {h[-1] * 1e9:.3g} nm", (xs[-1], ys[-1]), xytext=(5, -8), textcoords="offset points", fontsize=7)
        if np.isfinite(h_est):
            xe, ye = map_coordinates(W, h_est, n_used, q, E_star)
            ax.plot([xe], [ye], "*", color=c, mec="k", ms=12, zorder=5)
            lam = (xe ** n_used * ye ** (n_used - 1)) ** (1 / (2 * n_used - 1))
            lb = float(lambda_boundary(n_used))
            lines.append(f"{nm}: $\\Lambda$ = {lam:.3g} {'<' if lam < lb else '>='} $\\Lambda_b$ = {lb:.3g}"
                         f" -> {'rigid valid' if lam < lb else 'M-D-n needed'}")
    if lines:
        ax.text(0.03, 0.97, f"at h = {h_est * 1e9:.3g} nm:\n" + "\n".join(lines) if np.isfinite(h_est) else "\n".join(lines),
                transform=ax.transAxes, fontsize=7, va="top", family="monospace",
                bbox=dict(boxstyle="round", fc="white", ec="0.7", alpha=0.9))
    ax.set_xscale("log")
    ax.set_yscale("log")
    ax.set_xlim(1e-6, 1)
    ax.set_ylim(1, 1e4)
    ax.set_xlabel(r"$\sigma_0/E^*$  ($\sigma_0 = W_A/h$)")
    ax.set_ylabel(r"$R\,S^{(n-2)/(n-1)}/h$  (= R/h for S = 1)")
    ax.text(0.97, 0.04, "rigid regime: below/left of the boundary line of the interval's n\n"
            f"(E* = {E_star / 1e9:.3g} GPa, W$_A$ = {W * 1e3:.3g} mJ/m$^2$ from the {src};\n"
            "star = estimated h)", transform=ax.transAxes, fontsize=7.5, va="bottom", ha="right")
    ax.set_title(f"Tip {tip}: adhesion map ({law}), Eq. 13 boundaries n = 2-6")
    ax.grid(True, which="both", alpha=0.2)
    ax.legend(fontsize=7, loc="upper right")
    fig.tight_layout()
    _save(fig, out_png)


def plot_rigid_laws(out_png, *, n_max: float = 20.0, mechanics=None):
    """Rigid pull-off of the L-J, Tri1 and Tri2 laws over rigid Dugdale vs n (Fig. 8)."""
    from pipeline.inversion import _mechanics

    mech = _mechanics(mechanics)
    n = np.linspace(2.0, n_max, 181)
    fig, ax = plt.subplots(figsize=(6.4, 4.4))
    styles = {"dugdale": ("k", "-"), "lj": ("tab:blue", "-"), "tri1": ("tab:green", "--"), "tri2": ("tab:red", "-.")}
    for law, (c, ls) in styles.items():
        r = np.asarray(mech.rigid_pulloff_ratio(n, law), float) * np.ones_like(n)
        lab = {"dugdale": "Dugdale", "lj": f"L-J 3-9 (z0 = h/0.974, 1/0.974 = {LJ_Z0_OVER_H:.4f})",
               "tri1": "Tri1 (peak 2$\\sigma_0$ at h/2, range h)", "tri2": "Tri2 (peak $\\sigma_0$ at h, range 2h)"}[law]
        ax.plot(n, r, color=c, ls=ls, lw=1.8, label=lab)
        if law != "dugdale":
            r5 = float(np.asarray(mech.rigid_pulloff_ratio(5.0, law), float))
            ax.plot([5.0], [r5], "o", color=c, ms=4)
            ax.annotate(f"{r5:.3f}", (5.0, r5), xytext=(4, -10 if law == "tri1" else 4), textcoords="offset points",
                        fontsize=7, color=c)
    ax.set_xlabel("power index n")
    ax.set_ylabel(r"$F_{p,r}$ / $F_{p,r,\mathrm{Dugdale}}$  (same W$_A$, h)")
    ax.set_title("Rigid pull-off of the traction laws vs n (paper Fig. 8)")
    ax.set_xlim(2, n_max)
    ax.grid(True, alpha=0.3)
    ax.legend(fontsize=8)
    fig.tight_layout()
    _save(fig, out_png)
