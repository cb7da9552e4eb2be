"""Mechanics core: M-D-n (Zheng & Yu 2007) and rigid power-law adhesion, forward and inverse.

Specification: adhesion-power-law-paper Sec. 3.1, 3.2, 4.2, 4.3 with ERRATA corrections.
SI units throughout: Q [m^(n-1)] (tip z = r^n/(nQ), Q = S^(n-2) R^(n-1)), E* [Pa], W [J/m^2],
h [m] (Dugdale range, sigma_0 = W/h), forces [N].  Supported domain: n in [2, 20],
Lambda in [1e-6, 1e6]; anything else raises ValueError.

Public API
----------
pulloff_nd(n, Lambda, potential="dugdale", model="mdn", exact=False)
pulloff_force(n, Q, E_star, W, h, potential="dugdale", model="mdn", exact=False)
work_of_adhesion(F_p, n, Q, E_star, h, potential="dugdale", model="mdn", exact=False)
work_of_adhesion_and_regime(...): the same and, from the same solve, where the rigid solution was used
lambda_from_g(G, n, potential="dugdale", model="mdn", exact=False)
model_used(n, Q, E_star, h, W=None, F_p=None, potential="dugdale")
    models: "rigid", "mdn" (Dugdale), "elastic" (any law), "auto" (rigid below rigid_boundary(n, law),
    the 5 % boundary: Eq. 13 for Dugdale, the law's own for L-J, Tri1, Tri2; else elastic)
pulloff_with_model(law, n, Q, E_star, W, h, mode="auto"), work_of_adhesion_with_model(law, F_p, ...)
    values and the model that made each ("rigid" / "mdn" / "elastic"), pipeline solver_mode names
elastic_pulloff(n, Lambda, law, level=2, estimate_error=False), elastic_path(n, Lambda, law)
    direct elastic solve for any traction law (elastic_contact); get_law(name), tabulated_law(s, tau)
lambda_boundary(n), lambda_boundary_solved(n, tol=0.05), rigid_error(n, Lambda, exact=True)
transition_parameter(n, Q, E_star, W, h), maugis_parameter(R, E_star, W, h),
maugis_from_transition(Lambda), q_from_rs(n, R, S=1), r_from_q(n, Q, S=1)
mdn_branch(n, Lambda, num=400), mdn_branch_si(n, Q, E_star, W, h, num=400), jkr_limit_nd(n)
rigid_pulloff_ratio(n, potential), rigid_optimal_gap(n, potential),
rigid_force_curve(n, u, potential), traction(s, W, h, potential)
"""

from __future__ import annotations

import importlib
from typing import NamedTuple

import numpy as np

from . import _validate

# The public names and the module of each, imported on first use (PEP 562): a job that needs only
# Eq. 13 (the adhesion-map figure) does not load scipy's integrators and splines (~0.4 s).
_LAZY = {
    ".api": (
        "lambda_from_g",
        "model_used",
        "pulloff_force",
        "pulloff_nd",
        "pulloff_with_model",
        "rigid_boundary",
        "work_of_adhesion",
        "work_of_adhesion_and_regime",
        "work_of_adhesion_with_model",
    ),
    ".boundary": ("lambda_boundary", "lambda_boundary_solved", "rigid_error"),
    ".elastic_contact": ("ElasticPulloff", "elastic_path", "elastic_pulloff"),
    ".mdn": ("MDNBranch", "jkr_limit_nd"),
    ".rigid": ("LJ_H_OVER_Z0", "rigid_force_curve", "rigid_optimal_gap", "rigid_pulloff_ratio", "traction"),
    ".scaling": (
        "log_displacement_scale",
        "log_force_scale",
        "log_length_scale",
        "maugis_from_transition",
        "maugis_parameter",
        "q_from_rs",
        "r_from_q",
        "transition_parameter",
    ),
    ".tables": ("build_table",),
    ".traction_laws": ("TractionLaw", "get_law", "tabulated_law"),
}
_MODULE_OF = {name: mod for mod, names in _LAZY.items() for name in names}


def __getattr__(name):
    """A public name (or a submodule) of the package, imported when first asked for."""
    if name in _MODULE_OF:
        value = getattr(importlib.import_module(_MODULE_OF[name], __name__), name)
        globals()[name] = value
        return value
    try:
        return importlib.import_module(f".{name}", __name__)
    except ModuleNotFoundError as exc:
        if exc.name != f"{__name__}.{name}":  # a submodule that exists but lacks a dependency: say so
            raise
        raise AttributeError(f"module {__name__!r} has no attribute {name!r}") from None


def __dir__():
    return sorted(set(globals()) | set(_MODULE_OF))


__all__ = [
    "pulloff_nd",
    "pulloff_force",
    "work_of_adhesion",
    "lambda_from_g",
    "model_used",
    "lambda_boundary",
    "lambda_boundary_solved",
    "rigid_error",
    "transition_parameter",
    "maugis_parameter",
    "maugis_from_transition",
    "q_from_rs",
    "r_from_q",
    "mdn_branch",
    "mdn_branch_si",
    "MDNBranch",
    "MDNBranchSI",
    "jkr_limit_nd",
    "rigid_pulloff_ratio",
    "rigid_optimal_gap",
    "rigid_force_curve",
    "traction",
    "LJ_H_OVER_Z0",
    "build_table",
    "pulloff_with_model",
    "work_of_adhesion_with_model",
    "work_of_adhesion_and_regime",
    "rigid_boundary",
    "elastic_pulloff",
    "elastic_path",
    "ElasticPulloff",
    "TractionLaw",
    "get_law",
    "tabulated_law",
]


def mdn_branch(n, Lambda, num=400):
    """Full non-dimensional M-D-n curve (a~, delta~, P~, m) for scalar n, Lambda (Eqs. 9-11)."""
    from .mdn import mdn_branch as _mdn_branch

    n = float(_validate.exponent(n))
    lam = float(_validate.transition(Lambda))
    return _mdn_branch(n, lam, num=num)


class MDNBranchSI(NamedTuple):
    """Dimensional M-D-n curve: contact radius a [m], approach delta [m], load P [N], m = c/a."""

    a: np.ndarray
    delta: np.ndarray
    P: np.ndarray
    m: np.ndarray
    pulloff: float  # F_p [N], positive
    i_pulloff: int


def mdn_branch_si(n, Q, E_star, W, h, num=400):
    """M-D-n curve in SI units for one case (scalars), via Eqs. 4-6."""
    from .scaling import log_displacement_scale, log_force_scale, log_length_scale, transition_parameter

    lam = float(transition_parameter(n, Q, E_star, W, h))
    b = mdn_branch(n, lam, num=num)
    n = float(n)
    la, ld, lp = (
        log_length_scale(n, Q, E_star, W),
        log_displacement_scale(n, Q, E_star, W),
        log_force_scale(n, Q, E_star, W),
    )
    return MDNBranchSI(
        b.a * np.exp(la), b.delta * np.exp(ld), b.P * np.exp(lp), b.m, b.pulloff * float(np.exp(lp)), b.i_pulloff
    )
