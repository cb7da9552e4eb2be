"""Rigid-tip (Bradley-type) pull-off for power-law tips (paper Sec. 3.2, Eq. 12, Sec. 4.3, Fig. 8).

Plan area within height z of the apex: A(z) = pi (n Q z)^(2/n).  With the apex at gap D from
the zero-stress separation and p = 2/n,

    F(D) = int_0^inf sigma(D + z) dA(z) = pi (nQ)^p int_0^inf (-sigma'(D+z)) z^p dz,

maximised over D >= 0.  Normalised by the rigid Dugdale value F_Dug = pi sigma_0 (n Q h)^p
(Eq. 12, maximum at D = 0), every law gives a pure function of n (u = D/h):

    Dugdale  F/F_Dug = (1-u)^p                                              (u <= 1)
    Tri1     F/F_Dug = 4/(p+1) [(1-u)^(p+1) - 2 (1/2-u)_+^(p+1)]             (u <= 1)
             u* = (1/2 - 2^(-n/2)) / (1 - 2^(-n/2)),
             ratio = n 2^(2-2/n) / ((n+2) (2^(n/2) - 1)^(2/n))
    Tri2     F/F_Dug = 1/(p+1) [(2-u)^(p+1) - 2 (1-u)_+^(p+1)]               (u <= 2)
             u* = (1 - 2^(1-n/2)) / (1 - 2^(-n/2)),
             ratio = 2 n / ((n+2) (2^(n/2) - 1)^(2/n))
    L-J 3-9  sigma(d) = 8W/(3 z0) [(z0/d)^3 - (z0/d)^9] (Eq. 14), d = z0 + D + z, z0 = h/0.974;
             using int_0^inf z^(p-1) (d+z)^(-k) dz = d^(p-k) B(p, k-p):
             F/F_Dug = (8p/3) (h/z0)^(1-p) [g^(p-3) B(p,3-p) - g^(p-9) B(p,9-p)],  g = d/z0,
             g*^6 = (9-p) B(p,9-p) / ((3-p) B(p,3-p))  (>= 1 for n >= 2; clipped to D >= 0).

All ratios equal 1 at n = 2 (DMT/Bradley 2 pi R W); Tri1 -> 2 and Tri2, L-J -> 1 as n -> inf
(flat punch: peak stress x area).  In non-dimensional form P~_rigid = ratio(n) n^(2/n) Lambda^((n-2)/n).
"""

from __future__ import annotations

import numpy as np
from scipy import special as sp

from . import _validate as V

__all__ = [
    "LJ_H_OVER_Z0",
    "rigid_pulloff_ratio",
    "rigid_pulloff_nd_raw",
    "rigid_optimal_gap",
    "rigid_force_curve",
    "traction",
]

#: h / z0 for the L-J 3-9 law tied to Dugdale (equal W and, to 0.03 %, equal peak stress).
#: The paper (Sec. 4.3, with Eq. 14) uses 0.974; the exact equal-peak value is 9 sqrt(3)/16 = 0.97428.
LJ_H_OVER_Z0 = 0.974


def _lj_terms(p):
    b3 = sp.beta(p, 3.0 - p)
    b9 = sp.beta(p, 9.0 - p)
    g_star = ((9.0 - p) * b9 / ((3.0 - p) * b3)) ** (1.0 / 6.0)
    return b3, b9, np.maximum(g_star, 1.0)


def _lj_force(p, g, b3, b9):
    """Rigid L-J 3-9 force (Eq. 14 over the plan area) over F_Dug at apex gap g = d/z0 (module doc)."""
    return 8.0 * p / 3.0 * LJ_H_OVER_Z0 ** (1.0 - p) * (g ** (p - 3.0) * b3 - g ** (p - 9.0) * b9)


def rigid_optimal_gap(n, potential="dugdale"):
    """Apex gap D*/h (measured from the zero-stress separation) at the rigid pull-off."""
    n = np.asarray(n, float)
    pot = V.potential(potential)
    q = 2.0 ** (-0.5 * n)
    if pot == "dugdale":
        return np.zeros_like(n)
    if pot == "tri1":
        return (0.5 - q) / (1.0 - q)
    if pot == "tri2":
        return (1.0 - 2.0 * q) / (1.0 - q)
    _, _, g = _lj_terms(2.0 / n)
    return (g - 1.0) / LJ_H_OVER_Z0


def rigid_force_curve(n, u, potential="dugdale"):
    """Rigid force F(D)/F_Dug(D=0) versus u = D/h >= 0 (closed forms above)."""
    n, u = np.broadcast_arrays(np.asarray(n, float), np.asarray(u, float))
    p = 2.0 / n
    pot = V.potential(potential)
    if pot == "dugdale":
        return np.clip(1.0 - u, 0.0, None) ** p
    if pot == "tri1":
        return (
            4.0
            / (p + 1.0)
            * (np.clip(1.0 - u, 0.0, None) ** (p + 1.0) - 2.0 * np.clip(0.5 - u, 0.0, None) ** (p + 1.0))
        )
    if pot == "tri2":
        return (
            1.0
            / (p + 1.0)
            * (np.clip(2.0 - u, 0.0, None) ** (p + 1.0) - 2.0 * np.clip(1.0 - u, 0.0, None) ** (p + 1.0))
        )
    b3, b9, _ = _lj_terms(p)
    return _lj_force(p, 1.0 + LJ_H_OVER_Z0 * u, b3, b9)


def rigid_pulloff_ratio(n, potential="dugdale"):
    """F_rigid(law) / F_rigid(Dugdale), a function of n only (paper Fig. 8)."""
    n = V.exponent(n)
    pot = V.potential(potential)
    if pot == "dugdale":
        return np.ones_like(n)
    if pot == "tri1":
        return n * 2.0 ** (2.0 - 2.0 / n) / ((n + 2.0) * (2.0 ** (0.5 * n) - 1.0) ** (2.0 / n))
    if pot == "tri2":
        return 2.0 * n / ((n + 2.0) * (2.0 ** (0.5 * n) - 1.0) ** (2.0 / n))
    p = 2.0 / n
    b3, b9, g = _lj_terms(p)
    return _lj_force(p, g, b3, b9)


def rigid_pulloff_nd_raw(n, lam, potential="dugdale"):
    """P~_rigid = ratio(n) n^(2/n) Lambda^((n-2)/n) (Eq. 12 in the variables of Eqs. 6, 8)."""
    n = np.asarray(n, float)
    return rigid_pulloff_ratio(n, potential) * np.exp(2.0 / n * np.log(n) + (n - 2.0) / n * np.log(lam))


def traction(s, W, h, potential="dugdale"):
    """Attractive traction sigma(s) [Pa] at separation s [m] from the zero-stress gap (ERRATA table;
    L-J 3-9: Eq. 14 with d = z0 + s, z0 = h/0.974)."""
    s = np.asarray(s, float)
    pot = V.potential(potential)
    sig0 = W / h
    if pot == "dugdale":
        return np.where((s >= 0) & (s <= h), sig0, 0.0)
    if pot == "tri1":
        return np.where(s < 0.5 * h, 4.0 * sig0 * s / h, 4.0 * sig0 * (1.0 - s / h)).clip(0.0) * (s >= 0)
    if pot == "tri2":
        return np.where(s < h, sig0 * s / h, sig0 * (2.0 - s / h)).clip(0.0) * (s >= 0)
    z0 = h / LJ_H_OVER_Z0
    r = z0 / (z0 + s)
    return 8.0 * W / (3.0 * z0) * (r**3 - r**9)
