"""Stage 5 entry point: a tip's inversion -> reference W_A, per-interval crossings, global h and
W_A per traction law (``adhesion_range.h5``), the per-tip CSV and, if asked, the figures."""

from __future__ import annotations

import logging
import time
from pathlib import Path

import numpy as np

from pipeline.adhesion_range.analysis import analyse_law
from pipeline.adhesion_range.io import write_range_h5
from pipeline.adhesion_range.report import write_tip_report
from pipeline.inversion.io import load_inversion

log = logging.getLogger(__name__)


def run_adhesion_range(
    inversion_h5,
    out_h5,
    report_csv=None,
    fig_dir=None,
    *,
    tip: str = "",
    w_of_h_png=None,
    adhesion_map_png=None,
    inconsistency: str = "random_effects",
):
    """Stage 5: reference W_A, per-interval crossings, global h and W_A per traction law.

    Writes ``out_h5``; if given, the per-tip report CSV (``pipeline.adhesion_range.report``) and
    the figures ``fig_dir/W_A_vs_h.png`` and ``fig_dir/adhesion_map.png`` (or the explicit
    paths ``w_of_h_png`` / ``adhesion_map_png``).  Returns {law: analysis dict}.
    """
    t0 = time.perf_counter()
    inv = load_inversion(inversion_h5, samples_on_grid=False)  # each law interpolated when analysed
    tip = tip or inv.get("tip") or ""
    results = {}
    for j, law in enumerate(inv["laws"]):
        results[law] = analyse_law(inv, law, inconsistency)
        log.info(
            "%s: law %d/%d (%s) analysed, %.1f s so far", tip, j + 1, len(inv["laws"]), law, time.perf_counter() - t0
        )
    for law, res in results.items():
        _log_law(tip, law, res)
    write_range_h5(out_h5, inv, results, tip=tip, source=str(inversion_h5))
    if report_csv is not None:
        write_tip_report(out_h5, report_csv, tip=tip)
    if fig_dir is not None:
        w_of_h_png = w_of_h_png or Path(fig_dir) / "W_A_vs_h.png"
        adhesion_map_png = adhesion_map_png or Path(fig_dir) / "adhesion_map.png"
    if w_of_h_png is not None or adhesion_map_png is not None:
        from pipeline.adhesion_range import figures  # matplotlib only where a figure is drawn

        if w_of_h_png is not None:
            figures.plot_w_of_h(out_h5, w_of_h_png, tip=tip)
        if adhesion_map_png is not None:
            figures.plot_adhesion_map(out_h5, adhesion_map_png, tip=tip)
    log.info("adhesion range for %s done in %.2f s (h grid %d points)", tip, time.perf_counter() - t0, inv["h"].size)
    return results


def _log_law(tip: str, law: str, res: dict) -> None:
    """Each interval's status and crossing, and the global estimate, in plain lines."""
    g = res.get("global", {})
    for nm, info in res["intervals"].items():
        log.info(
            "%s %s %s: %s%s%s",
            tip,
            law,
            nm,
            info["status"],
            f", crosses the reference at h = {info['h'] * 1e9:.3g} nm" if np.isfinite(info.get("h", np.nan)) else "",
            f" ({info['note']})" if info.get("note") else "",
        )
    if g.get("status") == "ok":
        hp, wp = g["h_pcts"], g["W_pcts"]
        log.info(
            "%s %s: h = %.3g nm [%.3g, %.3g], W_A = %.4g mJ/m^2 [%.4g, %.4g] (95 %% Monte Carlo percentiles; "
            "chi2 %.3g for %d dof; %s)",
            tip,
            law,
            g["h"] * 1e9,
            hp[0] * 1e9,
            hp[-1] * 1e9,
            g["W_A"] * 1e3,
            wp[0] * 1e3,
            wp[-1] * 1e3,
            g["chi2_min"],
            g["dof"],
            g.get("note", "").strip() or "consistent",
        )
    else:
        log.info("%s %s: %s %s", tip, law, g.get("status", res.get("status", "")), g.get("note", ""))
