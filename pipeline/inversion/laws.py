"""The traction laws the inversion solves for, its solver modes, and how each law reports h.

The L-J law is tied to Dugdale by z0 = h / 0.974 (Eq. 14 with equal peak stress and W_A, paper
Sec. 4.3; ``pipeline.mechanics.rigid.LJ_H_OVER_Z0``): its h column is the Dugdale-equivalent h.
For Tri2, h is the separation of the peak stress; the full range is 2h.
"""

from __future__ import annotations

LAWS = ("dugdale", "lj", "tri1", "tri2")
SOLVER_MODES = ("auto", "mdn", "rigid")
LJ_Z0_OVER_H = 1.0 / 0.974
CONVENTIONS = {
    "dugdale": "h = range of the constant Dugdale stress sigma_0 = W_A/h",
    "lj": "Dugdale-equivalent h with L-J 3-9 equilibrium gap z0 = h/0.974 (equal peak stress and W_A)",
    "tri1": "h = range (stress zero beyond h), peak 2 sigma_0 at h/2",
    "tri2": "h = separation of the peak stress sigma_0 (Dugdale-equivalent h); full range is 2h",
}


def full_model_name(law: str) -> str:
    """The law's full (elastic) model as the output names it: "mdn" for Dugdale, else "elastic"."""
    return "mdn" if law == "dugdale" else "elastic"
