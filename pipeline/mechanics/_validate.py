"""Input validation shared by the public mechanics API (clear ValueErrors, never NaN)."""

from __future__ import annotations

import numpy as np

N_MIN, N_MAX = 2.0, 20.0
LAMBDA_MIN, LAMBDA_MAX = 1e-6, 1e6
_REL = 1e-12  # tolerance on the domain edges for round-off in derived quantities

POTENTIALS = ("dugdale", "lj", "tri1", "tri2")
MODELS = ("mdn", "rigid", "auto", "elastic")


def positive(name, value):
    """Return value as a float array; ValueError naming ``name`` unless finite and > 0."""
    arr = np.asarray(value, dtype=float)
    if arr.size == 0:
        return arr
    if not np.all(np.isfinite(arr)):
        raise ValueError(f"{name} must be finite (got non-finite values)")
    if not np.all(arr > 0.0):
        raise ValueError(f"{name} must be > 0 (got min {arr.min():.6g})")
    return arr


def exponent(n):
    """Power-law index n as a float array, checked against the supported domain [2, 20]."""
    arr = positive("n", n)
    if arr.size and np.any(arr < N_MIN * (1 - _REL)) or np.any(arr > N_MAX * (1 + _REL)):
        raise ValueError(
            f"n must lie in the supported domain [{N_MIN:g}, {N_MAX:g}] (got range [{arr.min():.6g}, {arr.max():.6g}])"
        )
    return np.clip(arr, N_MIN, N_MAX)


def transition(lam):
    """Transition parameter Lambda, checked against the supported domain [1e-6, 1e6]."""
    arr = positive("Lambda", lam)
    if arr.size == 0:
        return arr
    lo, hi = arr.min(), arr.max()
    if lo < LAMBDA_MIN * (1 - _REL) or hi > LAMBDA_MAX * (1 + _REL):
        raise ValueError(
            f"transition parameter Lambda outside the supported domain [{LAMBDA_MIN:g}, {LAMBDA_MAX:g}] "
            f"(got range [{lo:.6g}, {hi:.6g}]); check units (SI: m, Pa, J/m^2) and the inputs"
        )
    return np.clip(arr, LAMBDA_MIN, LAMBDA_MAX)


def potential(name):
    key = str(name).lower().replace("-", "").replace("_", "")
    key = {"lennardjones": "lj", "lj39": "lj"}.get(key, key)
    if key not in POTENTIALS:
        raise ValueError(f"unknown potential {name!r}; expected one of {POTENTIALS}")
    return key


def model(name, pot):
    key = str(name).lower()
    if key not in MODELS:
        raise ValueError(f"unknown model {name!r}; expected one of {MODELS}")
    if key == "mdn" and pot != "dugdale":
        raise ValueError(
            f"model='mdn' is the M-D-n solution, which exists only for the Dugdale potential "
            f"(got potential={pot!r}); use model='elastic' (elastic solver, any law) or 'rigid'"
        )
    return key
