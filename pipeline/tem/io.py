"""Files of stage 1: the profile file it writes (:func:`write_profile_h5`) and its reader
(:func:`read_profile`, used by stage 2): the only place the profile file's layout is spelled.

Profile file layout: /image, /edge, /axis, /profile/{left,right,combined} (r, z, [flank],
[offset_basis, normal_rz]; /profile/offset_cov), /asymmetry, /edge_model (/edge_model/faint_layer,
/edge_model/clipped_layer, /edge_model/start_contour).
"""

from __future__ import annotations

import numpy as np

from pipeline import h5io

__all__ = ["write_profile_h5", "read_profile"]


def write_profile_h5(out_h5, image, profile, tip="", interval=""):
    """HDF5 layout: /image, /edge, /axis, /profile/{left,right,combined}, /asymmetry, /edge_model."""
    with h5io.atomic_h5(
        out_h5,
        stage="tem_profiles",
        tip=tip,
        interval=interval,
        source=str(image.path),
        profile_height=profile.profile_height,
    ) as f:
        _write_image_edge_axis(f, image, profile)
        _write_profile(f, profile)
        _write_edge_model(f, image, profile)


def _write_image_edge_axis(f, image, profile):
    """Groups /image, /edge and /axis."""
    w = h5io.write_dataset
    g = h5io.create_group(f, "image")
    w(g, "pixel_size", image.pixel_size, "m", "pixel size in use", source=image.source)
    w(g, "pixel_size_source", image.source, "1", "where the pixel size came from")
    w(g, "shape", np.array(image.data.shape), "pixel")
    w(g, "path", str(image.path), "1")
    if image.note:
        g.attrs["note"] = image.note
    g = h5io.create_group(f, "edge", description="outer silhouette, sub-pixel")
    w(g, "points_image", profile.edge_px, "pixel", "(row, col) in the image, pixel centres at integers")
    w(g, "x", profile.x, "m", "lateral tip coordinate (signed, from the axis)")
    w(g, "z", profile.z, "m", "height above the apex")
    w(g, "flank", profile.flank.astype(np.int8), "1", "-1 left, +1 right")
    g = h5io.create_group(f, "axis")
    w(g, "apex_image", profile.apex_px, "pixel", "apex (row, col) in the image")
    w(g, "direction_image", profile.axis_px, "1", "unit vector (drow, dcol) from the apex up the tip")
    w(g, "rotation", profile.angle, "rad", "tilt of the axis, counter-clockwise, apex-down view")
    w(g, "orientation", profile.orientation, "1", "apex pointing down or up in the image")


def _write_profile(f, profile):
    """Groups /profile/{left,right,combined} (with the edge covariance) and /asymmetry."""
    w = h5io.write_dataset
    pg = h5io.create_group(f, "profile", description="z(r), apex at z = 0, z away from the sample")
    if profile.offset_cov is not None:
        w(
            pg,
            "offset_cov",
            profile.offset_cov,
            "m^2",
            "covariance of the edge-offset B-spline coefficients c_k (silhouette fit, marginal)",
        )
    for which, name in (("left", "left"), ("right", "right"), ("both", "combined")):
        i = profile.flank_index(which)
        sg = h5io.create_group(pg, name)
        w(sg, "r", np.abs(profile.x[i]), "m", "distance from the axis" + (", both flanks" if which == "both" else ""))
        w(sg, "z", profile.z[i], "m", "height above the apex")
        if which == "both":
            w(sg, "flank", profile.flank[i].astype(np.int8), "1", "-1 left, +1 right")
        if profile.offset_basis is not None:
            w(
                sg,
                "offset_basis",
                profile.offset_basis[i],
                "1",
                "normal offset of each point = offset_basis @ c (c: see ../offset_cov)",
            )
            w(sg, "normal_rz", profile.normal_rz[i], "1", "outward unit normal (n_r, n_z) of each point")
    g = h5io.create_group(f, "asymmetry")
    w(g, "mean", profile.asymmetry_mean, "m", "mean r_right - r_left at equal z")
    w(g, "rms", profile.asymmetry_rms, "m", "RMS of r_right - r_left at equal z")


def _write_edge_model(f, image, profile):
    """Group /edge_model: the fitted Beer-Lambert edge model, its coating test and the silhouette fit."""
    w = h5io.write_dataset
    g = h5io.create_group(f, "edge_model", description="fitted Beer-Lambert edge model")
    em = profile.edge_model
    w(g, "attenuation_outer", em["k_outer_per_m"], "1/m")
    w(g, "attenuation_core", em["k_core_per_m"], "1/m")
    w(g, "coating_thickness", em["coating_thickness"], "m", "0 = single layer")
    w(g, "blur_sigma", em["blur_sigma"], "m", "Gaussian blur sigma (incl. pixel box)")
    w(g, "rms_intensity", em["rms_intensity"], "1", "RMS intensity residual relative to the background")
    w(g, "n_rejected", em["n_rejected"], "1", "edge points rejected")
    g.attrs["refine"] = em.get("refine", "normals")
    # the vacuum beyond 30 nm of the tip (its quadratic surface) over the window's background plane next to
    # the tip, - 1 (pipeline.tem.vacuum_level)
    g.attrs["vacuum_gain"] = float(em.get("vacuum_gain", np.nan))
    flags = list(em.get("global_flags", []))
    from pipeline.tem.silhouette_fit import edge_not_fitted

    g.attrs["edge_not_fitted"] = edge_not_fitted(flags)  # the edge is the starting contour (stage 2: unusable)
    w(
        g,
        "flags",
        np.array(flags, dtype=object) if flags else np.array([], dtype=object),
        "1",
        "edge-model warnings (e.g. coating not identifiable)",
    )
    ct = em.get("coating_test") or {}
    if ct:
        _write_coating_test(g, ct, image.pixel_size)
    if em.get("faint_layer"):
        _write_faint_layer(g, em["faint_layer"])
    if em.get("clipped_layer"):
        _write_clipped_layer(g, em["clipped_layer"])
    if em.get("start_contour"):
        _write_start_contour(g, em["start_contour"])
    if em.get("global_fringe"):
        _write_fringe(g, em["global_fringe"], image.pixel_size)
    if "global_chi2_red" in em:
        w(g, "chi2_reduced", em["global_chi2_red"], "1", "reduced chi^2 of the silhouette fit")
        w(g, "n_pixels", em["global_n_pixels"], "1", "pixels in the silhouette fit")
        w(
            g,
            "model_error_offset_sd",
            em.get("global_model_error_px", 0.0) * image.pixel_size,
            "m",
            "SD of the common edge offset for the edge model's error, included in /profile/offset_cov "
            "(pipeline.tem.model_error; 0 where the model fits the image to its noise)",
        )
        w(g, "binning", em.get("global_binning", 1), "1", "block size of the silhouette fit (b x b pixels)")


def _write_fringe(g, fr, px):
    """The defocus-fringe correction of the silhouette fit (``pipeline.tem.fringe_correction``)."""
    w = h5io.write_dataset
    g.attrs["fringe_applied"] = bool(fr["applied"])
    w(g, "fringe_offset", fr["offset_px"] * px, "m", "uniform outward edge offset of the coherent rendering")
    w(g, "fringe_offset_sd", fr["offset_sd_px"] * px, "m", "its standard error (added to the edge covariance)")
    w(
        g,
        "fringe_model_sd",
        fr.get("model_sd_px", 0.0) * px,
        "m",
        "its model error, half the offset (where the shape is refitted, half of fringe_shape_move is in the edge "
        "covariance instead, as a mode along the move)",
    )
    w(g, "fringe_lambda_defocus", fr["A_px2"] * px**2, "m^2", "wavelength x defocus fitted (> 0 underfocus)")
    w(g, "fringe_attenuation_scale", fr["attenuation_scale"], "1", "common scale of the attenuations fitted with it")
    w(g, "fringe_dchi2", fr["dchi2"], "1", "chi^2(Beer-Lambert) - chi^2(coherent rendering)")
    if "shape_move_px" in fr:  # the edge's shape refitted with the coherent rendering (``fringe_shape``)
        w(
            g,
            "fringe_shape_move",
            np.asarray(fr["shape_move_px"], float) * px,
            "m",
            "outward move of each edge knot against the Beer-Lambert fit (uniform offset and shape; half of it is "
            "a mode of the edge covariance)",
        )
        w(
            g,
            "fringe_shape_dchi2",
            fr["shape_dchi2"],
            "1",
            "chi^2 at the uniform offset - chi^2 with the shape refitted",
        )
        w(g, "fringe_shape_lambda_defocus", fr["shape_A_px2"] * px**2, "m^2", "wavelength x defocus refitted with it")
        g.attrs["fringe_shape_iterations"] = int(fr["shape_iterations"])
        g.attrs["fringe_shape_converged"] = bool(fr["shape_converged"])
    g.attrs["fringe_defocus_sign_given"] = int(fr.get("sign", 0))  # +1 underfocus, -1 overfocus, 0 not given
    # with an overfocus given: the fitted thin light layer read as the dark fringe, the edge one material's
    g.attrs["fringe_layer_taken_back"] = bool("layer_as_fringe_dchi2" in fr)
    if "free_A_px2" in fr:
        w(
            g,
            "fringe_free_lambda_defocus",
            fr["free_A_px2"] * px**2,
            "m^2",
            "wavelength x defocus the fit of both signs took, against the sign given (then refitted at that sign)",
        )


def _write_coating_test(g, ct, px):
    """The coating test's decision and numbers (in /edge_model)."""
    w = h5io.write_dataset
    g.attrs["coating_model"] = ct.get("model", "")
    g.attrs["coating_ambiguous"] = bool(ct.get("ambiguous", False))
    if "skipped" in ct:
        g.attrs["coating_test_skipped"] = ct["skipped"]
    if "note" in ct:
        g.attrs["coating_note"] = ct["note"]
    if "dchi2" in ct:
        w(
            g,
            "coating_dchi2",
            ct["dchi2"],
            "1",
            "chi^2(single layer) - chi^2(best coated fit); a layer is accepted above the threshold",
            threshold=ct.get("threshold", np.nan),
        )
        w(g, "coating_test_thickness", ct["thickness_px"] * px, "m", "layer thickness of the best coated fit")
        w(
            g,
            "coating_test_outer_shift",
            ct["outer_shift_px"] * px,
            "m",
            "mean outward shift of the coated fit's outer edge from the single layer's",
        )
        w(
            g,
            "coating_test_contrast_ratio",
            ct["contrast_ratio"],
            "1",
            "attenuation ratio outer layer / core of the best coated fit",
        )
    if ct.get("ambiguous"):
        w(
            g,
            "coating_ambiguous_shift",
            ct["ambiguous_shift_px"] * px,
            "m",
            "largest outward edge shift of a light layer that fits within the threshold of none "
            "(half of it is added to the edge covariance as a common offset SD)",
        )


def _write_start_contour(g, st):
    """Group /edge_model/start_contour: the iso-level the silhouette fit started from, and where the first
    level folded in something faint, how far beyond the final edge (``pipeline.tem.start_contour``)."""
    w = h5io.write_dataset
    sg = h5io.create_group(g, "start_contour", description="the silhouette fit's starting iso-contour")
    sg.attrs["note"] = st.get("note", "")
    w(sg, "level", st["level"], "1", "first iso-level, share of the flattened vacuum")
    w(sg, "fold_share", st["fold_share"], "1", "share of its points near the apex that turn back")
    w(sg, "start_level", st["start_level"], "1", "the level the fit started from (= level unless it folded)")
    if "dim_zone" in st:
        w(sg, "dim_zone", st["dim_zone"], "m", "median distance of the folded first contour beyond the final edge")


def _write_clipped_layer(g, cl):
    """Group /edge_model/clipped_layer: the test for a light layer a clipped vacuum hides, seen by its
    outer surface's Fresnel fringe beyond the edge (``pipeline.tem.clipped_layer``); ``note`` says it."""
    w = h5io.write_dataset
    sg = h5io.create_group(g, "clipped_layer", description="light layer hidden by a clipped vacuum: its outer fringe")
    sg.attrs["found"] = bool(cl.get("found", False))
    sg.attrs["edge_is_core"] = bool(cl.get("edge_is_core", False))
    sg.attrs["note"] = cl.get("note", "")
    for key, what in (
        ("thickness", "distance of the fringe beyond the fitted (core's) edge: the edge was moved out by it"),
        ("thickness_sd", "its standard error (in the edge covariance)"),
        ("left", "the distance on the left flank"),
        ("right", "the distance on the right flank"),
        ("band", "where no fringe: how far unclipped pixels run on beyond the edge (the shorter flank's)"),
    ):
        if key in cl:
            w(sg, key, cl[key], "m", what)


def _write_faint_layer(g, fl):
    """Group /edge_model/faint_layer: the test for a faint layer beyond the fitted edge and the
    detection limit (``pipeline.tem.faint_layer``); ``note`` (attribute) says it in words."""
    w = h5io.write_dataset
    sg = h5io.create_group(g, "faint_layer", description="faint outer layer beyond the fitted edge; detection limit")
    sg.attrs["tested"] = bool(fl.get("tested", False))
    sg.attrs["found"] = bool(fl.get("found", False))
    sg.attrs["edge_is_core"] = bool(fl.get("edge_is_core", False))
    sg.attrs["note"] = fl.get("note", "")
    ol = fl.get("outer_layer")
    if ol:
        # where the edge was the core's: the layer's thickness read from the image (``outer_layer``)
        sg.attrs["edge_moved_out"] = bool(ol.get("usable", False))
        sg.attrs["outer_layer_note"] = ol.get("note", "")
        for key, what in (
            ("thickness_apex", "layer thickness beyond the fitted edge at the apex, read from the image"),
            ("thickness_apex_sd", "its standard error (in the edge covariance where the edge was moved)"),
            ("thickness_flank", "the same on the flanks, from ramp_height above the core's apex up"),
            ("thickness_flank_sd", "its standard error"),
            ("ramp_height", "height above the core's apex where the thickness reaches its flank value"),
        ):
            if key in ol:
                w(sg, f"outer_{key}", ol[key], "m", what)
    if "bright_band" in fl:
        w(sg, "bright_band", fl["bright_band"], "m", "band beyond the edge's blur brighter than the vacuum")
        sd = fl.get("bright_band_sd", 0.0)
        w(sg, "bright_band_sd", sd, "m", "common offset SD of the edge for a layer hidden there (0: none)")
    if not fl.get("tested"):
        return
    w(sg, "start", fl["start"], "m", "distance beyond the fitted edge from which layers are tested")
    w(sg, "thickness", fl["thickness"], "m", "layer thicknesses (beyond the fitted edge) tested")
    w(
        sg,
        "contrast_limit",
        fl["contrast_limit"],
        "1",
        "layer/core attenuation ratio a layer of each thickness needs to be seen with 90 % probability",
    )
    w(sg, "z_both", fl["z_both"], "1", "fitted layer attenuation / its SE, both flanks together")
    w(sg, "z_left", fl["z_left"], "1", "the same, left flank (shared background)")
    w(sg, "z_right", fl["z_right"], "1", "the same, right flank (shared background)")
    w(sg, "core_attenuation", fl["core_attenuation"], "1/m", "the core's attenuation the contrasts refer to")
    if fl.get("found"):
        w(sg, "found_thickness", fl["found_thickness"], "m", "thickness of the layer seen, beyond the fitted edge")
        w(sg, "found_contrast", fl["found_contrast"], "1", "its attenuation relative to the core's")


def read_profile(profile_h5):
    """The profile file: ({"left"|"right"|"combined": (r, z, edge), "flank", "chi2_red", "n_pixels",
    "model_error_sd", "edge_flags", "edge_is_core"}, pixel size (m)); edge is None or dict(edge_basis,
    edge_cov, normal_rz); model_error_sd (m) the model-error common offset already in edge_cov, None in
    files written before it was;
    edge_flags the edge model's warnings in words (a coating not identifiable, a faint layer beyond the
    edge, a singular covariance); edge_is_core True where a faint outer layer was seen beyond the
    fitted edge on each flank alone and the edge was not moved out to it (the profile is the core's).  h5py's errors
    (FileNotFoundError, OSError, KeyError) pass through for the caller to word."""
    import h5py

    with h5py.File(profile_h5, "r") as f:
        g = f["profile"]
        out = {}
        cov = g["offset_cov"][()] if "offset_cov" in g else None
        for name in ("left", "right", "combined"):
            sg = g[name]
            edge = None
            if cov is not None and "offset_basis" in sg:
                edge = dict(edge_basis=sg["offset_basis"][()], edge_cov=cov, normal_rz=sg["normal_rz"][()])
            out[name] = (sg["r"][()], sg["z"][()], edge)
        out["flank"] = g["combined"]["flank"][()]
        em = f.get("edge_model")
        out["chi2_red"] = float(em["chi2_reduced"][()]) if em is not None and "chi2_reduced" in em else None
        out["n_pixels"] = float(em["n_pixels"][()]) if em is not None and "n_pixels" in em else None
        has = em is not None and "model_error_offset_sd" in em
        out["model_error_sd"] = float(em["model_error_offset_sd"][()]) if has else None
        flags = np.atleast_1d(em["flags"][()]) if em is not None and "flags" in em else []
        out["edge_flags"] = [x.decode() if isinstance(x, bytes) else str(x) for x in flags if len(x)]
        fl = em.get("faint_layer") if em is not None else None
        out["edge_is_core"] = bool(fl is not None and fl.attrs.get("edge_is_core", False))
        out["edge_not_fitted"] = bool(em is not None and em.attrs.get("edge_not_fitted", False))
        px = float(f["image"]["pixel_size"][()])
        return out, px
