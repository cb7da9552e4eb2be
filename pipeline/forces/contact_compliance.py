"""The contact slope of a stiff lever is not 1/InvOLS: the tip indents the counter-surface.

In contact the piezo travel is the lever's deflection plus the indentation, dz = dd + d(delta),
so the deflection-vs-travel slope is 1/InvOLS x 1/(1 + d(delta)/dd): a contact-slope InvOLS is
too large by the factor c = 1 + [delta(F_hi) - delta(F_lo)] / (d_hi - d_lo) over the deflection
range (d_lo, d_hi) of the fit, and every F_p converted with it is too large by c.  The contact is
DMT-like on these hard counter-surfaces (the adhesion outside the contact adds to the load):
the elastic force is F = F_adh + k d, and the indentation of the power-law tip z = r^n/(nQ)
follows Sneddon (1965) for an axisymmetric punch:

    delta = B k_n a^n,   F = 2 E* n/(n+1) B k_n a^(n+1),   B = 1/(nQ),
    k_n = sqrt(pi) Gamma(n/2 + 1) / Gamma(n/2 + 1/2)            (n = 2: Hertz, delta = a^2/R)

c - 1 is about k / (2 E* a): 0.1-0.3 % for a 0.1-0.5 N/m lever, ~1 % at 2 N/m, several % at
10-40 N/m on a nanometre-sized apex at 100 GPa.  The stage-4 inversion, which knows the tip shape
and E*, divides F_p of an interval whose InvOLS came from its own contact slopes by c and adds
half of c - 1 (DMT vs JKR, the shape of the very apex) to the interval's calibration uncertainty.
"""

from __future__ import annotations

import numpy as np
from scipy.special import gammaln


def sneddon_indentation(F, n, Q, E_star):
    """Indentation delta (m) of a rigid power-law punch z = r^n/(nQ) pressed with force F (N)
    into a half-space of reduced modulus E* (Pa) (Sneddon 1965); F <= 0 gives 0."""
    F = np.maximum(np.asarray(F, float), 0.0)
    B = 1.0 / (n * Q)
    kn = np.exp(0.5 * np.log(np.pi) + gammaln(n / 2 + 1) - gammaln(n / 2 + 0.5))
    a = (F / (2.0 * E_star * n / (n + 1.0) * B * kn)) ** (1.0 / (n + 1.0))
    return B * kn * a**n


def contact_compliance_factor(k, d_range, F_adh, n, Q, E_star) -> float:
    """c = 1 + [delta(F_adh + k d_hi) - delta(F_adh + k d_lo)] / (d_hi - d_lo) (module doc);
    1 where the range or the shape is unknown.  k (N/m), d_range (m), F_adh (N), Q (m^(n-1)), E* (Pa)."""
    d_lo, d_hi = (float(x) for x in d_range)
    if not (
        np.isfinite(d_lo)
        and np.isfinite(d_hi)
        and d_hi > d_lo
        and np.isfinite(n)
        and n > 0
        and np.isfinite(Q)
        and Q > 0
        and np.isfinite(E_star)
        and E_star > 0
        and k > 0
    ):
        return 1.0
    F_adh = max(float(F_adh), 0.0) if np.isfinite(F_adh) else 0.0
    dd = sneddon_indentation(F_adh + k * d_hi, n, Q, E_star) - sneddon_indentation(F_adh + k * d_lo, n, Q, E_star)
    return float(1.0 + dd / (d_hi - d_lo))
