"""Checks and corrections of the stage-3 forces before they are inverted.

* the spring constant k belongs to the lever: one per tip (:func:`tip_calibration`);
* a mean pull-off far off the tip's others is a unit or calibration mistake
  (:func:`implausible_forces`);
* a contact-slope InvOLS includes the tip's own indentation (:func:`correct_contact_compliance`).
"""

from __future__ import annotations

import numpy as np


def tip_calibration(forces: dict, names: list) -> tuple[dict, list]:
    """(calibration of the tip, notes): k is one per tip, so the first interval's is used and
    the others are checked against it; InvOLS is each interval's own (the chip is remounted)
    unless stage 3 says one InvOLS serves the whole tip, which is then checked the same way."""
    cal = forces[names[0]]
    notes = []
    keys = ("k",) if not all(forces[nm]["invols_shared"] for nm in names) else ("k", "invols")
    for nm in names[1:]:
        for key in keys:
            a, b = cal[key], forces[nm][key]
            if np.isfinite(a) and np.isfinite(b) and not np.isclose(a, b, rtol=1e-9):
                notes.append(f"{key} of {nm} ({b:g}) differs from {names[0]} ({a:g}); using {names[0]}'s")
    return cal, notes


def implausible_forces(F_p: dict, factor: float = 10.0) -> list:
    """Words for intervals whose mean pull-off is more than ``factor`` times above or below the
    median of the tip's other intervals: a wear test changes F_p by a few times at most (a blunter
    tip), so such a step is a unit or calibration mistake (a deflection written in nm read as V)."""
    notes = []
    for nm, F in F_p.items():
        others = [v for k, v in F_p.items() if k != nm and np.isfinite(v) and v > 0]
        if not others or not (np.isfinite(F) and F > 0):
            continue
        ratio = F / float(np.median(others))
        if ratio > factor or ratio < 1.0 / factor:
            notes.append(
                f"interval {nm}: its mean pull-off {F * 1e9:.4g} nN is {ratio:.3g} x the median of the tip's other "
                f"intervals ({np.median(others) * 1e9:.4g} nN): check its deflection unit and calibration "
                "(force_curves.deflection_unit, the InvOLS source)"
            )
    return notes


def correct_contact_compliance(forces: dict, n: float, Q: float, E_star: float):
    """Forces of an interval whose InvOLS came from its own contact slopes, corrected for the
    tip's finite contact stiffness (``pipeline.forces.contact_compliance``): F_p, its SEM and
    InvOLS divided by c, half of c - 1 added (relative) to the InvOLS uncertainty.  Returns
    (forces, c); c = 1 (forces unchanged) for other InvOLS sources or an unknown shape."""
    # here, not at the top: the reports use this module's checks and need no scipy.special
    from pipeline.forces.contact_compliance import contact_compliance_factor

    if forces.get("invols_method") != "contact" or forces.get("invols_shared", True):
        return forces, 1.0
    F_adh = forces["F_p_mean"]  # DMT: the adhesion outside the contact adds to the load on either segment
    c = contact_compliance_factor(
        forces["k"], forces.get("contact_fit_deflection", (np.nan, np.nan)), F_adh, n, Q, E_star
    )
    if c == 1.0:
        return forces, 1.0
    inv = forces["invols"] / c
    u_inv = float(np.hypot(np.nan_to_num(forces["u_invols"]) / c, 0.5 * (c - 1.0) * inv))
    out = {
        **forces,
        "F_p_mean": forces["F_p_mean"] / c,
        "F_p_sem": forces["F_p_sem"] / c,
        "F_p_std": forces["F_p_std"] / c,
        "F_p_curves": np.asarray(forces["F_p_curves"]) / c,
        "invols": inv,
        "u_invols": u_inv,
        "contact_compliance_factor": c,
    }
    return out, c
