"""Stage entry point: TEM image -> profile HDF5 + overlay figure."""
from __future__ import annotations

import numpy as np

from pipeline import h5io
from pipeline.tem.figures import plot_profile
from pipeline.tem.profiles import extract_profile
from pipeline.tem.reading import read_tem_image

__all__ = ["run_profiles", "write_profile_h5"]


def run_profiles(image_path, out_h5, out_png, *, pixel_size=None, orientation="auto", tip="", interval="",
                 profile_height=20e-9, coating="auto", refine="global") -> None:
    """Read ``image_path``, extract the apex profile, write ``out_h5`` and ``out_png`` atomically.

    pixel_size: m (used only if the file has no calibration); orientation: auto|down|up;
    profile_height: m of profile kept above the apex; coating: "auto", "none" or a
    thickness in m (lighter outer layer; the OUTER surface is reported); refine:
    "global" (one fit of all edge pixels, pipeline.tem.silhouette_fit) or "normals"
    (per-normal fits only, pipeline.tem.edges).
    Raises ValueError subclasses (pipeline.tem.errors) naming the file.
    """
    image = read_tem_image(image_path, pixel_size)
    profile = extract_profile(image, orientation=orientation, profile_height=profile_height, coating=coating,
                              refine=refine)
    write_profile_h5(out_h5, image, profile, tip=tip, interval=interval)
    plot_profile(image, profile, out_png, title=f"{tip} {interval}".strip())


def write_profile_h5(out_h5, image, profile, tip="", interval=""):
    """HDF5 layout: /image, /edge, /axis, /profile/{left,right,combined}, /asymmetry, /edge_model."""
    w = h5io.write_dataset
    with h5io.atomic_h5(out_h5, stage="tem_profiles", tip=tip, interval=interval, source=str(image.path),
                        profile_height=profile.profile_height) as f:
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
        pg = h5io.create_group(f, "profile", description="z(r), apex at z = 0, z away from the sample")
        if profile.offset_cov is not None:
            w(pg, "offset_cov", profile.offset_cov, "m^2",
              "covariance of the edge-offset B-spline coefficients c_k (silhouette fit, marginal)")
        for which, name in (("left", "left"), ("right", "right"), ("both", "combined")):
            i = profile.flank_index(which)
            sg = h5io.create_group(pg, name)
            w(sg, "r", np.abs(profile.x[i]), "m", "distance from the axis" + (", both flanks" if which == "both" else ""))
            w(sg, "z", profile.z[i], "m", "height above the apex")
            if which == "both":
                w(sg, "flank", profile.flank[i].astype(np.int8), "1", "-1 left, +1 right")
            if profile.offset_basis is not None:
                w(sg, "offset_basis", profile.offset_basis[i], "1",
                  "normal offset of each point = offset_basis @ c (c: see ../offset_cov)")
                w(sg, "normal_rz", profile.normal_rz[i], "1", "outward unit normal (n_r, n_z) of each point")
        g = h5io.create_group(f, "asymmetry")
        w(g, "mean", profile.asymmetry_mean, "m", "mean r_right - r_left at equal z")
        w(g, "rms", profile.asymmetry_rms, "m", "RMS of r_right - r_left at equal z")
        g = h5io.create_group(f, "edge_model", description="fitted Beer-Lambert edge model")
        em = profile.edge_model
        w(g, "attenuation_outer", em["k_outer_per_m"], "1/m")
        w(g, "attenuation_core", em["k_core_per_m"], "1/m")
        w(g, "coating_thickness", em["coating_thickness"], "m", "0 = single layer")
        w(g, "blur_sigma", em["blur_sigma"], "m", "Gaussian blur sigma (incl. pixel box)")
        w(g, "rms_intensity", em["rms_intensity"], "1", "RMS intensity residual relative to the background")
        w(g, "n_rejected", em["n_rejected"], "1", "edge points rejected")
        g.attrs["refine"] = em.get("refine", "normals")
        flags = list(em.get("global_flags", []))
        w(g, "flags", np.array(flags, dtype=object) if flags else np.array([], dtype=object), "1",
          "edge-model warnings (e.g. coating not identifiable)")
        ct = em.get("coating_test") or {}
        if ct:
            g.attrs["coating_model"] = ct.get("model", "")
            g.attrs["coating_ambiguous"] = bool(ct.get("ambiguous", False))
            if "skipped" in ct:
                g.attrs["coating_test_skipped"] = ct["skipped"]
            if "note" in ct:
                g.attrs["coating_note"] = ct["note"]
            px = image.pixel_size
            if "dchi2" in ct:
                w(g, "coating_dchi2", ct["dchi2"], "1",
                  "chi^2(single layer) - chi^2(best coated fit); a layer is accepted above the threshold",
                  threshold=ct.get("threshold", np.nan))
                w(g, "coating_test_thickness", ct["thickness_px"] * px, "m", "layer thickness of the best coated fit")
                w(g, "coating_test_outer_shift", ct["outer_shift_px"] * px, "m",
                  "mean outward shift of the coated fit's outer edge from the single layer's")
                w(g, "coating_test_contrast_ratio", ct["contrast_ratio"], "1",
                  "attenuation ratio outer layer / core of the best coated fit")
            if ct.get("ambiguous"):
                w(g, "coating_ambiguous_shift", ct["ambiguous_shift_px"] * px, "m",
                  "largest outward edge shift of a light layer that fits within the threshold of none "
                  "(half of it is added to the edge covariance as a common offset SD)")
        if "global_chi2_red" in em:
            w(g, "chi2_reduced", em["global_chi2_red"], "1", "reduced chi^2 of the silhouette fit")
            w(g, "n_pixels", em["global_n_pixels"], "1", "pixels in the silhouette fit")
            w(g, "binning", em.get("global_binning", 1), "1", "block size of the silhouette fit (b x b pixels)")
