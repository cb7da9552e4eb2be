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
        for which in ("left", "right"):
            r, z = profile.flank_rz(which)
            sg = h5io.create_group(pg, which)
            w(sg, "r", r, "m", "distance from the axis")
            w(sg, "z", z, "m", "height above the apex")
        m = profile.z <= profile.profile_height
        o = np.argsort(profile.z[m], kind="stable")
        sg = h5io.create_group(pg, "combined")
        w(sg, "r", np.abs(profile.x[m])[o], "m", "distance from the axis, both flanks")
        w(sg, "z", profile.z[m][o], "m", "height above the apex")
        w(sg, "flank", profile.flank[m][o].astype(np.int8), "1", "-1 left, +1 right")
        g = h5io.create_group(f, "asymmetry")
        w(g, "mean", profile.asymmetry_mean, "m", "mean r_right - r_left at equal z")
        w(g, "rms", profile.asymmetry_rms, "m", "RMS of r_right - r_left at equal z")
        g = h5io.create_group(f, "edge_model", description="fitted Beer-Lambert edge model")
        em = profile.edge_model
        w(g, "attenuation_outer", em["k_outer_per_m"], "1/m")
        w(g, "attenuation_core", em["k_core_per_m"], "1/m")
        w(g, "coating_thickness", em["coating_thickness"], "m", "0 = single layer")
        w(g, "blur_sigma", em["blur_sigma"], "m", "Gaussian blur sigma (incl. pixel box)")
        w(g, "rms_intensity", em["rms_intensity"], "1", "median per-normal RMS intensity residual")
        w(g, "n_rejected", em["n_rejected"], "1", "edge points rejected")
