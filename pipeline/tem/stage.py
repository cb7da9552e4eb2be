"""Stage entry point: TEM image -> profile HDF5 + overlay figure."""

from __future__ import annotations

from pipeline.tem.figures import plot_profile
from pipeline.tem.io import write_profile_h5
from pipeline.tem.profiles import extract_profile
from pipeline.tem.reading import read_tem_image

__all__ = ["run_profiles", "write_profile_h5"]


def run_profiles(
    image_path,
    out_h5,
    out_png,
    *,
    pixel_size=None,
    orientation="auto",
    tip="",
    interval="",
    profile_height=20e-9,
    coating="auto",
    refine="global",
    fringe_correction=True,
    defocus="auto",
) -> None:
    """Read ``image_path``, extract the apex profile, write ``out_h5`` and ``out_png`` atomically.

    pixel_size: m (used only if the file has no calibration); orientation: auto|down|up;
    profile_height: m of profile kept above the apex; coating: "auto", "none" or a
    thickness in m (lighter outer layer; the OUTER surface is reported); refine:
    "global" (one fit of all edge pixels, pipeline.tem.silhouette_fit) or "normals"
    (per-normal fits only, pipeline.tem.edges); fringe_correction: the defocus-fringe correction
    of the global fit's edge (pipeline.tem.fringe_correction); defocus: "auto", "underfocus" or
    "overfocus" (the sign of the defocus if the operator knows it).
    Raises ValueError subclasses (pipeline.tem.errors) naming the file.
    """
    image = read_tem_image(image_path, pixel_size)
    profile = extract_profile(
        image,
        orientation=orientation,
        profile_height=profile_height,
        coating=coating,
        refine=refine,
        fringe_correction=fringe_correction,
        defocus=defocus,
    )
    write_profile_h5(out_h5, image, profile, tip=tip, interval=interval)
    fl = profile.edge_model.get("faint_layer") or {}
    if fl.get("note"):
        print(f"{image_path}: {fl['note']}")  # the job's log
    plot_profile(image, profile, out_png, title=f"{tip} {interval}".strip())
