"""Files of stage 2: the profile file it reads (:func:`read_profile`) and the fit file it writes
(:func:`write_fit_h5`) with its readers (:func:`read_fit`, and :func:`load_fit` for stage 4): the only
place the fit file's layout is spelled.

Fit file layout: /fit (combined) and /fit_left, /fit_right with datasets n, Q, ln_Q, R, S, z0,
cov_n_lnQ, axis_offset, flank_asymmetry, [edge_noise_fraction], rms_residual, fit_error_percent,
fit_height, r, z, [flank], flags, notes and attribute ``flagged``; /fit_n2 the paraboloid fit (n held
at 2) of the combined profile, used for a reference interval whose n is consistent with 2
(``pipeline.inversion.shape.shape_for_inversion``).  A fit that could not be done is a group with
attribute ``failed``.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from pipeline import h5io
from pipeline.fits.result import FitError, PowerLawFit
from pipeline.h5io import read_value, require_group
from pipeline.tem import io as tem_io

# the flank a fit group holds: group name
GROUPS = (("combined", "fit"), ("left", "fit_left"), ("right", "fit_right"))
PARABOLOID_GROUP = "fit_n2"
EDGE_NOTE_PREFIX = "TEM edge: "  # the fit notes that repeat the stage-1 edge model's warnings


def read_profile(profile_h5):
    """The profile file of stage 1 (``pipeline.tem.io.read_profile``: its layout is spelled there), its
    errors as FitError naming the file."""
    path = Path(profile_h5)
    try:
        return tem_io.read_profile(path)
    except FileNotFoundError:
        raise FitError(f"{path}: profile file not found") from None
    except (OSError, KeyError) as exc:
        raise FitError(f"{path}: unreadable or incomplete profile file ({exc})") from None


def _write_fit(group, fit: PowerLawFit):
    """One fit group."""
    w = h5io.write_dataset
    w(group, "n", fit.n, "1", "power index n (Eq. 1)")
    w(group, "Q", fit.Q, f"m^{fit.n - 1:.4g}", "Q of Eq. 1 in SI, units m^(n-1)")
    w(group, "ln_Q", fit.ln_Q, "1", "natural log of Q in SI units")
    w(group, "R", fit.R, "m", "R of Eq. 2, Q = S^(n-2) R^(n-1)")
    w(group, "S", fit.S, "1", "steepness S of Eq. 2")
    w(group, "z0", fit.z0, "m", "fitted apex offset")
    w(group, "cov_n_lnQ", fit.cov_n_lnQ, "1", "covariance of (n, ln Q)")
    w(group, "axis_offset", fit.axis_offset, "m", "common axis of the two flanks from the profile's axis")
    w(
        group,
        "flank_asymmetry",
        fit.flank_asymmetry,
        "1",
        "e of the flank-wise fit: right flank (1 + e) r(z), left (1 - e) r(z), r(z) the power law (Eq. 1)",
    )
    if fit.edge_noise_fraction is not None:
        w(
            group,
            "edge_noise_fraction",
            fit.edge_noise_fraction,
            "1",
            "share of the residual variance explained by the silhouette fit's edge noise "
            "(cov = propagated edge covariance + (1 - share) x residual covariance)",
        )
    w(group, "rms_residual", fit.rms_residual, "m", "RMS orthogonal residual")
    w(group, "fit_error_percent", fit.fit_error_percent, "%", "100 x RMS residual / fit_height")
    w(group, "fit_height", fit.fit_height, "m", "fit window above the apex")
    w(group, "r", fit.r, "m", "radial coordinate of the points used")
    w(group, "z", fit.z, "m", "height of the points used")
    if fit.flank is not None:
        w(group, "flank", fit.flank.astype(np.int8), "1", "-1 left, +1 right flank of each point")
    w(
        group,
        "flags",
        np.array(fit.flags, dtype=object) if fit.flags else np.array([], dtype=object),
        "1",
        "quality flags; empty = usable",
    )
    w(
        group,
        "notes",
        np.array(fit.notes, dtype=object) if fit.notes else np.array([], dtype=object),
        "1",
        "what the screening of the profile left out (turned-back edge, contamination on one flank), in words",
    )
    group.attrs["flagged"] = bool(fit.flags)


def read_fit(fit_h5, group="fit"):
    """Read a fit group back as a PowerLawFit."""
    import h5py

    with h5py.File(fit_h5, "r") as f:
        g = f[group]
        v = {k: g[k][()] for k in g}
    flags = (
        [x.decode() if isinstance(x, bytes) else str(x) for x in np.atleast_1d(v["flags"])] if v["flags"].size else []
    )
    nts = np.atleast_1d(v.get("notes", np.array([], dtype=object)))
    notes = [x.decode() if isinstance(x, bytes) else str(x) for x in nts] if nts.size else []
    cov = np.asarray(v["cov_n_lnQ"], float)
    sd = np.sqrt(np.where(np.isfinite(np.diag(cov)) & (np.diag(cov) >= 0), np.diag(cov), np.nan))
    enf = v.get("edge_noise_fraction")
    return PowerLawFit(
        n=float(v["n"]),
        Q=float(v["Q"]),
        ln_Q=float(v["ln_Q"]),
        R=float(v["R"]),
        S=float(v["S"]),
        z0=float(v["z0"]),
        cov_n_lnQ=cov,
        rms_residual=float(v["rms_residual"]),
        fit_error_percent=float(v["fit_error_percent"]),
        fit_height=float(v["fit_height"]),
        r=v["r"],
        z=v["z"],
        flags=flags,
        notes=notes,
        flank=v.get("flank"),
        sigma_n=float(sd[0]),
        sigma_lnQ=float(sd[1]),
        edge_noise_fraction=None if enf is None else float(enf),
        axis_offset=float(v.get("axis_offset", 0.0)),
        flank_asymmetry=float(v.get("flank_asymmetry", 0.0)),
    )


def write_fit_h5(out_h5, fits: dict, paraboloid, *, source, tip="", interval="") -> None:
    """Write the fit file (module doc, atomic): ``fits`` {"combined"|"left"|"right": PowerLawFit or
    None (failed)}, ``paraboloid`` the n = 2 fit of the combined profile or None (failed)."""
    with h5io.atomic_h5(
        out_h5,
        stage="fit",
        tip=tip,
        interval=interval,
        source=str(source),
        model="z = z0 + |r|^n/(nQ) (Eq. 1); R from Eq. 2",
    ) as f:
        for name, gname in GROUPS:
            if fits[name] is None:
                h5io.create_group(f, gname, failed=True)
                continue
            g = h5io.create_group(f, gname)
            _write_fit(g, fits[name])
        c = fits["combined"]
        f.attrs["flagged"] = bool(c.flags)
        if paraboloid is not None:
            _write_fit(
                h5io.create_group(f, PARABOLOID_GROUP, model="paraboloid z = z0 + r^2/(2R): n held at 2, Q = R"),
                paraboloid,
            )
        else:
            h5io.create_group(f, PARABOLOID_GROUP, failed=True)


def load_fit(path) -> dict:
    """Read the stage-2 power-law fit of one interval (SI) from its HDF5 file (groups ``fit`` and,
    if stage 2 wrote it, ``fit_n2``: the paraboloid fit with n held at 2).

    Returns n, u_n, ln_Q, Q (m^(n-1)), R (m), S, cov_n_lnQ (2x2), rms_residual (m), flags,
    ``edge_notes`` (stage 1's warnings about the edge, in words) and ``paraboloid`` (the n = 2 fit as
    a dict of the same keys, or None); a file without Q, ln_Q, S or R (written by an older stage 2 or
    by hand) is read with those derived from the others.
    """
    import h5py

    with h5py.File(path, "r") as f:
        para = _read_paraboloid(f)
        g = require_group(f, "fit")
        n = float(read_value(g, "n", required=True))
        ln_q, q = read_value(g, "ln_Q"), read_value(g, "Q")
        if ln_q is None:
            if q is None:
                raise KeyError(f"{path}: fit has neither ln_Q nor Q")
            ln_q = np.log(float(q))
        ln_q = float(ln_q)
        q = float(q) if q is not None else float(np.exp(ln_q))
        s = float(read_value(g, "S", 1.0))
        r = read_value(g, "R")
        r = float(r) if r is not None else float(np.exp((ln_q - (n - 2.0) * np.log(s)) / (n - 1.0)))
        cov = read_value(g, "cov_n_lnQ")
        cov = np.zeros((2, 2)) if cov is None else np.asarray(cov, dtype=float).reshape(2, 2)
        flags = read_value(g, "flags", [])
        if isinstance(flags, (str, bytes)):
            flags = [flags.decode() if isinstance(flags, bytes) else flags]
        flags = [str(x) for x in np.atleast_1d(flags) if str(x)]
        rms = read_value(g, "rms_residual", np.nan)
        notes = np.atleast_1d(read_value(g, "notes", []))
    edge_notes = [str(x.decode() if isinstance(x, bytes) else x) for x in notes]
    return {
        "n": n,
        "u_n": float(np.sqrt(max(cov[0, 0], 0.0))),
        "ln_Q": ln_q,
        "Q": q,
        "R": r,
        "S": s,
        "cov_n_lnQ": cov,
        "rms_residual": float(rms),
        "flags": flags,
        "edge_notes": [x[len(EDGE_NOTE_PREFIX) :] for x in edge_notes if x.startswith(EDGE_NOTE_PREFIX)],
        "paraboloid": para,
    }


def _read_paraboloid(f):
    """The n = 2 fit of group ``fit_n2`` (None if absent or failed)."""
    if PARABOLOID_GROUP not in f or f[PARABOLOID_GROUP].attrs.get("failed", False):
        return None
    gp = f[PARABOLOID_GROUP]
    cp = np.asarray(gp["cov_n_lnQ"][()], float).reshape(2, 2)
    fl = [x.decode() if isinstance(x, bytes) else str(x) for x in np.atleast_1d(gp["flags"][()])]
    return {
        "n": 2.0,
        "u_n": 0.0,
        "ln_Q": float(gp["ln_Q"][()]),
        "Q": float(gp["Q"][()]),
        "R": float(gp["R"][()]),
        "cov_n_lnQ": cp,
        "rms_residual": float(gp["rms_residual"][()]),
        "flags": [x for x in fl if x],
    }
