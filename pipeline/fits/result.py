"""The result of the stage-2 power-law fit and its error."""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np


class FitError(ValueError):
    """A fit that cannot be done (no/too few points, unreadable profile file)."""


@dataclass
class PowerLawFit:
    n: float
    Q: float  # m^(n-1)
    ln_Q: float
    R: float  # m, Eq. 2
    S: float
    z0: float  # m
    cov_n_lnQ: np.ndarray  # 2x2
    rms_residual: float  # m
    fit_error_percent: float
    fit_height: float
    r: np.ndarray  # points used (m)
    z: np.ndarray
    flags: list = field(default_factory=list)
    sigma_n: float = float("nan")
    sigma_lnQ: float = float("nan")
    flank: np.ndarray | None = None
    edge_noise_fraction: float | None = None  # share of the residual variance explained by edge noise
    notes: list = field(default_factory=list)  # what the screening left out, in words
    axis_offset: float = 0.0  # m, common axis of the two flanks from the profile's axis (flank-wise fit)
    flank_asymmetry: float = 0.0  # e: right flank (1 + e) r(z), left (1 - e) r(z)
    flank_n: tuple | None = None  # n of the left and right flank fitted separately (flank disagreement)

    def z_model(self, r):
        """Fitted profile z(r) = z0 + |r|^n/(nQ) (m)."""
        return self.z0 + np.abs(r) ** self.n / (self.n * self.Q)
