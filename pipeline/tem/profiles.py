"""TEM image -> apex profile z(r) of both flanks (SI metres).

Tip frame: axis = line of symmetry of the two flanks between 0.15 and 1 x
``profile_height`` above the apex (in-plane rotation up to about +-20 deg is
corrected by working in this rotated frame, no image resampling); apex = where
the silhouette crosses the axis; z = 0 there, increasing away from the sample;
r = |x| measured from the axis.  Asymmetry = mean and RMS of r_right - r_left at
equal z over the profile window.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from pipeline.single_thread import single_threaded
from pipeline.tem.edges import (
    TipFrame,
    _Fail,
    curve_normals,
    flatten_background,
    initial_contour,
    locate_tip,
    refine_edges,
    saturated_pixels,
)
from pipeline.tem.errors import ApexAtBorderError, NoTipError
from pipeline.tem.reading import TemImage
from pipeline.tem.start_contour import DIM_ZONE_NM, clip_height, dim_zone, unfolded_start

__all__ = ["TipProfile", "extract_profile"]


@dataclass
class TipProfile:
    """Silhouette and profile of one tip image; lengths in metres, angles in rad."""

    pixel_size: float
    pixel_size_source: str
    orientation: str  # "down" or "up" as found
    angle: float  # tilt of the tip axis from the image vertical (rad, counter-clockwise as
    #               displayed with the apex pointing down; "up" images: after a vertical flip)
    apex_px: np.ndarray  # (row, col) in the original image
    axis_px: np.ndarray  # unit vector (drow, dcol) pointing up the tip body, original image
    edge_px: np.ndarray  # (N, 2) refined silhouette points (row, col), original image
    x: np.ndarray  # (N,) lateral tip coordinate (m), signed
    z: np.ndarray  # (N,) height above the apex (m)
    flank: np.ndarray  # (N,) -1 left, +1 right
    profile_height: float
    asymmetry_mean: float
    asymmetry_rms: float
    edge_model: dict = field(default_factory=dict)
    # edge uncertainty (global fit): normal offset of point i = offset_basis[i] @ c, cov(c) = offset_cov (m^2);
    # normal_rz = outward unit normal of each point in (r, z)
    offset_basis: np.ndarray | None = None
    offset_cov: np.ndarray | None = None
    normal_rz: np.ndarray | None = None

    def flank_index(self, which):
        """Indices of the edge points of one flank ("left", "right") or "both" within
        profile_height, sorted by z (the order of ``flank_rz``)."""
        m = self.z <= self.profile_height
        if which == "left":
            m &= self.flank < 0
        elif which == "right":
            m &= self.flank > 0
        i = np.nonzero(m)[0]
        return i[np.argsort(self.z[i], kind="stable")]

    def flank_rz(self, which):
        """(r, z) of one flank ("left", "right") or "both", sorted by z, within profile_height."""
        i = self.flank_index(which)
        return np.abs(self.x[i]), self.z[i]


def _coating_hint(coating, px, path):
    """ "auto" -> None (detect), "none" -> 0, thickness (m or "1.5 nm") -> px."""
    if coating is None or coating == "auto":
        return None
    if coating == "none":
        return 0.0
    if isinstance(coating, str):
        from pipeline.units import parse_quantity

        coating = parse_quantity(coating, "length", str(path))
    return float(coating) / px if coating > 0 else 0.0


def _fail(path, exc):
    msg = str(exc)
    if "apex touches" in msg:
        return ApexAtBorderError(path, msg)
    return NoTipError(path, msg)


def _window_and_contour(img, coarse, hpx, path, px, background=None):
    """(window, its origin in ``img``, flattened window, noise, initial contour, tip frame, clipped
    pixels of the window or None) of ``extract_profile``.  The window is flattened on the vacuum
    beyond any layer where a faint thick layer pulled its own background down
    (``vacuum_level.vacuum_flattening``); its reading goes into ``background`` (a dict) if given."""
    from pipeline.tem.vacuum_level import vacuum_flattening

    H, W = img.shape
    # window: bounding box of the tip within 1.3 x profile_height of the apex, + margins;
    # grown where the outer contour runs into a window side (light coatings may be
    # missing from the coarse mask)
    ca = coarse.apex
    th = coarse.angle
    (br0, br1), (bc0, bc1) = coarse.bbox
    m = dict(top=24, bottom=24, left=24, right=24)
    grow = max(24, int(0.5 * hpx))
    for attempt in range(5):
        r0, r1 = int(max(0, br0 - m["top"])), int(min(H, br1 + m["bottom"]))
        c0, c1 = int(max(0, bc0 - m["left"])), int(min(W, bc1 + m["right"]))
        win = img[r0:r1, c0:c1].astype(np.float64)
        origin = np.array([r0, c0], float)
        saturated = saturated_pixels(win)
        try:
            flat, noise = flatten_background(win, saturated)
        except _Fail as exc:
            raise _fail(path, exc) from None
        flat, vac = vacuum_flattening(img, (r0, r1, c0, c1), win, flat, px)
        if vac["used"]:  # the noise in units of the vacuum's plane (per square root of the level if clipped)
            noise = noise / (1.0 + vac["plane_gain"]) ** (1.0 if saturated is None else 0.5)
        if background is not None:
            background.clear()
            background.update(vac)
        level = _edge_level(flat, noise)
        try:
            cont = initial_contour(flat, level, ca - origin, smooth=2.0)
        except _Fail as exc:
            # the coarse mask left out a light layer: the outer contour lies a layer's thickness
            # beyond the coarse (core's) apex, further than the window-sized tolerance of
            # ``initial_contour`` (0.1 x window + 5 px); grow the window on every side, which also
            # widens that tolerance (so a contour of something else can be taken: the apex and
            # flank checks after the fit are what catch it)
            if attempt == 4 or all(m[s] >= _max_margin(s, br0, br1, bc0, bc1, H, W) for s in m):
                raise _fail(path, exc) from None
            for side in m:
                m[side] += grow
            continue
        frame = TipFrame(ca - origin, th)
        cont = clip_height(cont, frame, 1.3 * hpx + 8)
        cont, folded, start = unfolded_start(flat, noise, cont, level, ca - origin, frame, hpx, px)
        hit = _sides_hit(cont if folded is None else np.vstack([cont, folded]), win.shape, r1, c0, c1, H, W)
        if not any(hit.values()):
            break
        for side, h in hit.items():
            m[side] += grow if h else 0
    if len(cont) < 10:
        raise NoTipError(path, "no tip in the image (edge too short near the apex)")
    _check_border(cont, win.shape, frame, hpx, path, r0, c0, H, W)
    if folded is not None:  # one at the image border can neither start the fit nor say where a layer ends
        folded = None if _at_border(folded, frame, hpx, r0, c0, H, W) else folded
    if background is not None:
        background["start"], background["folded"] = start, folded
    return win, origin, flat, noise, cont, frame, saturated


def _refined_edge(
    win, flat, noise, cont, frame, hpx, px, coat_hint, refine, fringe_correction=True, saturated=None, defocus_sign=0
):
    """(edge points, symmetry frame, edge model, extra edge-model entries, (basis, cov_c, normals) or
    None) of ``extract_profile``: the global silhouette fit, or the per-normal fits where it is not
    asked for or fails.  ``saturated``: the window's clipped pixels (censored in the global fit)."""
    extra, uncertainty, gf = {}, None, None
    if refine == "global":
        from pipeline.tem.silhouette_fit import fit_silhouette

        sym = _symmetry_frame(cont, frame, hpx)
        try:
            gf = fit_silhouette(
                flat,
                cont,
                sym,
                hpx,
                noise,
                pixel_size=px,
                coat_hint=coat_hint,
                fringe_correction=fringe_correction,
                censored=saturated,
                defocus_sign=defocus_sign,
            )
        except (ValueError, IndexError, np.linalg.LinAlgError) as exc:  # fall back to per-normal fits
            extra = dict(refine="normals", global_flags=[f"global fit failed: {exc}"])
    if gf is not None:
        pts = gf.points
        frame = _symmetry_frame(pts, gf.frame, hpx)
        edge_model = dict(
            k_outer=gf.k_outer,
            k_core=gf.k_core,
            coat_px=gf.coat_px,
            sigma_px=gf.sigma_px,
            rms_intensity=gf.rms_intensity,
            n_rejected=0,
        )
        extra = dict(
            refine="global",
            global_flags=list(gf.flags),
            global_chi2_red=gf.chi2_red,
            global_n_pixels=gf.n_pixels,
            global_model_error_px=gf.model_error_px,
            global_iterations=gf.n_iter,
            global_stderr=gf.stderr,
            global_binning=gf.binning,
            coating_test=gf.coating_test,
            global_fringe=gf.fringe,
        )
        uncertainty = (gf.basis, gf.cov_c, gf.normals)
    else:
        fit = refine_edges(win, cont, frame, coat_hint=coat_hint, frame_update=lambda p: _symmetry_frame(p, frame, hpx))
        pts = fit.points[fit.good]
        frame = _symmetry_frame(pts, frame, hpx)
        edge_model = dict(
            k_outer=fit.k_outer,
            k_core=fit.k_core,
            coat_px=fit.coat_px,
            sigma_px=fit.sigma_px,
            rms_intensity=fit.rms_intensity,
            n_rejected=int((~fit.good).sum()),
        )
    return pts, frame, edge_model, extra, uncertainty


def _faint_layer(img, origin, pts, frame, edge_model, hpx, px, extra):
    """``faint_layer.faint_layer_test`` on the fitted edge; a layer it sees is also a flag."""
    from pipeline.tem.faint_layer import faint_layer_test

    coated = edge_model["coat_px"] > 0
    k_body = edge_model["k_core"] if coated else edge_model["k_outer"]
    model = (extra.get("coating_test") or {}).get("model", "single")
    out = faint_layer_test(img, origin, pts, frame, edge_model["sigma_px"], k_body, hpx, px, coat_model=model)
    if out.get("found"):
        _add_flag(extra, out["note"])
    return out


def _add_flag(extra, note):
    """``note`` appended to the edge model's flags in words (``extra["global_flags"]``)."""
    extra["global_flags"] = list(extra.get("global_flags", [])) + [note]


def _with_offset_columns(uncertainty, new_basis, normals, columns, sds):
    """The edge uncertainty (basis, covariance, normals) of the points whose basis is ``new_basis`` and
    normals ``normals`` (an edge moved out to a layer, or the same edge), plus one basis column per entry
    of ``columns`` (each point's weight of an independent offset) with standard deviation ``sds`` (px)."""
    K = uncertainty[1].shape[0]
    cov = np.zeros((K + len(sds), K + len(sds)))
    cov[:K, :K] = uncertainty[1]
    cov[K:, K:] = np.diag(np.square(sds))
    return np.column_stack([new_basis, *columns]), cov, normals


def _fit_from_start(win, flat, noise, cont, frame, fit_args, background):
    """``_refined_edge`` from the start contour ``cont``; where that was a lower level than the first
    (``start_contour``) and the fit found no edge there, from the folded first contour after all
    (``background`` says which). ``fit_args``: (hpx, px, coat_hint, refine, fringe_correction, saturated,
    defocus sign)."""
    fit = _refined_edge(win, flat, noise, cont, frame, *fit_args)
    if background["folded"] is not None and _no_fit(fit[3], fit_args[3]):
        fit = _refined_edge(win, flat, noise, background["folded"], frame, *fit_args)
        st = background["start"]
        st["note"] = (
            f"the fit from the iso-level {100 * (1 - st['start_level']):.0f} % below the vacuum found no edge; "
            f"the first level ({100 * (1 - st['level']):.0f} %), whose contour folds, started it"
        )
        st.update(start_level=st["level"], lower_level_not_fitted=True)
        background["folded"] = None
    return fit


def _no_fit(extra, refine):
    """True where the silhouette fit found no edge: its body reached none of the pixels (the edge is the
    starting contour), or the global fit failed and the per-normal fits stood in."""
    from pipeline.tem.silhouette_fit import edge_not_fitted

    return edge_not_fitted(extra.get("global_flags", [])) or (refine == "global" and extra.get("refine") != "global")


def _beyond_the_fold(pts, frame, hpx, px, background, extra, uncertainty):
    """Where the first start contour folded and a lower level started the fit (``start_contour``): how
    far the folded contour lies beyond the final edge; more than ``DIM_ZONE_NM`` widens the edge
    covariance by a common offset of that SD, with a flag in words (not where the edge is already marked
    the core's). Returns the uncertainty."""
    start = dict(background.get("start") or {})
    folded = background.get("folded")
    if folded is not None:
        start["dim_zone"] = dim_zone(folded, pts, frame, hpx) * px
    extra["start_contour"] = start
    if folded is None or start["dim_zone"] <= DIM_ZONE_NM * 1e-9 or extra.get("faint_layer", {}).get("edge_is_core"):
        return uncertainty
    d = start["dim_zone"]
    carried = _carried_words(d, uncertainty)
    note = (
        f"the iso-level {100 * (1 - start['level']):.0f} % below the vacuum folds back in something faint "
        f"a median {d * 1e9:.1f} nm beyond the final edge that no layer test placed (a coating too faint "
        f"to fit?): the fit started {100 * (1 - start['start_level']):.0f} % below the vacuum, and {carried}"
    )
    start.update(note=note, widened=uncertainty is not None)
    _add_flag(extra, note)
    return _with_common_offset(uncertainty, len(pts), d / px)


def _carried_words(sd, uncertainty):
    """The end of a widening flag: the common uncertainty ``sd`` (m) the edge now carries, or that the
    per-normal fits (``uncertainty`` None) have no edge covariance to carry it."""
    if uncertainty is None:
        return "the per-normal edge fits carry no edge covariance to widen: this uncertainty is not in the result"
    return f"the whole edge carries a common uncertainty of {sd * 1e9:.1f} nm"


def _with_common_offset(uncertainty, n_points, sd_px):
    """``uncertainty`` with one more column: an offset common to all ``n_points`` edge points of SD
    ``sd_px`` (px); None stays None (per-normal fits)."""
    if uncertainty is None:
        return None
    return _with_offset_columns(uncertainty, uncertainty[0], uncertainty[2], [np.ones(n_points)], [sd_px])


def _in_the_bright_band(n_points, px, extra, uncertainty, layer_dims_window):
    """Where a faint layer dims the window (``layer_dims_window``: the window was flattened on the vacuum
    read beyond it, ``vacuum_level``), a bright band (a Fresnel fringe) wider than
    ``faint_layer.BRIGHT_BAND_NM`` lies beyond the edge's blur, and the faint-layer test ran and saw no
    layer beyond it: the layer's outer surface may lie anywhere up to where that test starts (``start``,
    beyond the band), where neither it nor the coating test sees it, so the whole edge may lie up to
    ``start`` inside the tip's outer surface.  ``start`` / 2 joins the edge covariance as the SD of a
    common offset (95 % of it within +- ``start``; ``faint_layer["bright_band_sd"]``, m), with a flag in
    words; not where the fold of the starting contour (``_beyond_the_fold``) has already widened the
    edge, nor where a layer or a clipped vacuum's fringe has moved it or marked it the core's.  Returns
    the uncertainty."""
    from pipeline.tem.faint_layer import BRIGHT_BAND_NM

    fl = extra.get("faint_layer") or {}
    band = float(fl.get("bright_band", 0.0))
    placed = fl.get("found") or fl.get("edge_is_core") or (extra.get("clipped_layer") or {}).get("found")
    widened = (extra.get("start_contour") or {}).get("widened", False)
    if not layer_dims_window or band <= BRIGHT_BAND_NM * 1e-9 or not fl.get("tested") or placed or widened:
        return uncertainty
    sd = 0.5 * float(fl["start"])
    carried = _carried_words(sd, uncertainty)
    _add_flag(
        extra,
        f"a faint layer dims the window, and the image is brighter than the vacuum up to {band * 1e9:.1f} nm "
        "beyond the edge's blur (a Fresnel fringe; at one sign of the defocus a faint coating's fringe lies "
        "inside its outer surface): a layer whose outer surface lies within "
        f"{fl['start'] * 1e9:.1f} nm of the edge (where the faint-layer test starts) is seen by no test, so the "
        f"edge may lie up to that far inside the tip's outer surface, and {carried}",
    )
    if uncertainty is not None:
        fl["bright_band_sd"] = sd
    return _with_common_offset(uncertainty, n_points, sd / px)


def _note_background(extra, background):
    """The vacuum reading of ``_window_and_contour`` into the edge model's entries: its gain, and
    where the window was flattened on the vacuum beyond a faint layer, a flag in words."""
    extra["vacuum_gain"] = float(background.get("gain", np.nan))
    if background.get("used"):
        _add_flag(extra, background["note"])


def _beyond_the_edge(img, origin, pts, frame, edge_model, hpx, px, extra, uncertainty, saturated=False):
    """The faint-layer test after the global fit, and where it finds the edge to be the core's, the
    move out to the layer (``_outer_from_layer``); where the window is ``saturated`` (a clipped
    detector), the test for a layer the clipped vacuum hides (``_outer_from_fringe``). Returns (points,
    frame, uncertainty)."""
    extra["faint_layer"] = _faint_layer(img, origin, pts, frame, edge_model, hpx, px, extra)
    if extra["faint_layer"].get("edge_is_core"):
        return _outer_from_layer(img, origin, pts, frame, edge_model, hpx, px, extra, uncertainty)
    if saturated:
        return _outer_from_fringe(img, origin, pts, frame, hpx, px, extra, uncertainty)
    return pts, frame, uncertainty


def _outer_from_fringe(img, origin, pts, frame, hpx, px, extra, uncertainty):
    """Where a clipped vacuum hides a light layer whose outer surface shows as a Fresnel fringe beyond
    the edge (``clipped_layer``): the edge moved out by the fringe's distance, whose standard error joins
    the edge covariance as one more basis column (a common offset). Returns (points, frame, uncertainty)."""
    from pipeline.tem.clipped_layer import fringe_beyond_the_edge
    from pipeline.tem.outer_layer import move_edge_out

    clipped = saturated_pixels(np.asarray(img))
    if clipped is None:
        return pts, frame, uncertainty
    fr = fringe_beyond_the_edge(img, origin, pts, frame, px, clipped)
    extra["clipped_layer"] = {k: v for k, v in fr.items() if k not in ("profiles", "distances")}
    if fr.get("edge_is_core"):  # stage 2 then flags the shape unusable (``edge_is_core``), in these words
        extra["faint_layer"]["edge_is_core"] = True
        _add_flag(extra, fr["note"])
    if not fr["found"]:
        return pts, frame, uncertainty
    basis = uncertainty[0] if uncertainty is not None else None
    new_pts, new_basis, normals, _ = move_edge_out(pts, frame, fr["thickness"] / px, basis)
    if uncertainty is not None:
        uncertainty = _with_offset_columns(
            uncertainty, new_basis, normals, [np.ones(len(new_pts))], [fr["thickness_sd"] / px]
        )
    extra["clipped_layer"]["note"] = (
        fr["note"] + "; the edge is moved out by that distance, its SE joins the edge covariance"
    )
    _add_flag(extra, extra["clipped_layer"]["note"])
    return new_pts, _symmetry_frame(new_pts, frame, hpx), uncertainty


def _outer_from_layer(img, origin, pts, frame, edge_model, hpx, px, extra, uncertainty):
    """Where the fitted edge is the core's: the layer's thickness read from the image and the edge moved
    out by it (``outer_layer``), or left as it is with the reason in words. Returns (points, frame,
    uncertainty); the thicknesses' standard errors join the edge covariance as two more basis columns
    (the weights of T_apex and T_flank at each point)."""
    from pipeline.tem.outer_layer import move_edge_out, outer_surface, ramp

    fl = extra["faint_layer"]
    try:
        ol = outer_surface(img, origin, pts, frame, edge_model["sigma_px"], hpx, px)
    except (ValueError, np.linalg.LinAlgError) as exc:  # a singular fit: the profile stays the core's
        ol = dict(usable=False, note=f"the layer's thickness could not be fitted ({exc})")
    fl["outer_layer"] = ol
    if not ol["usable"]:
        ol["note"] = f"edge not moved out to the layer: {ol['note']}"
        _add_flag(extra, ol["note"])
        return pts, frame, uncertainty
    ta, tf = ol["thickness_apex"] / px, ol["thickness_flank"] / px
    _, z = frame.to_tip(pts)
    w = ramp(z, hpx)
    basis = uncertainty[0] if uncertainty is not None else None
    new_pts, new_basis, normals, src = move_edge_out(pts, frame, ta + (tf - ta) * w, basis)
    if uncertainty is not None:
        wf = np.interp(src, np.arange(len(w)), w)
        sds = [ol["thickness_apex_sd"] / px, ol["thickness_flank_sd"] / px]
        uncertainty = _with_offset_columns(uncertainty, new_basis, normals, [1.0 - wf, wf], sds)
    fl["edge_is_core"] = False
    ol["_core_pts"] = np.asarray(pts, float)  # the fitted (core's) edge, window px: for the figure
    ol["note"] = (
        f"edge moved out by the faint layer's thickness, read from the image: {ol['note']}; the outer surface "
        "is the fitted edge plus this layer, whose own edge is too faint to fit; the thicknesses' SEs join "
        "the edge covariance"
    )
    _add_flag(extra, ol["note"])
    return new_pts, _symmetry_frame(new_pts, frame, hpx), uncertainty


def _core_edge_in_image(extra, frame, origin, flipped, n_rows):
    """Where the edge was moved out to a faint layer, the fitted (core's) edge in image px, for the
    figure (``outer_layer["core_edge_px"]``)."""
    ol = (extra.get("faint_layer") or {}).get("outer_layer") or {}
    if "_core_pts" in ol:
        ol["core_edge_px"] = _in_image(ol.pop("_core_pts"), frame, origin, flipped, n_rows)[0]


def _edge_uncertainty(uncertainty, keep, x, px, frame):
    """The kept points' edge-offset basis, the offsets' covariance (m^2) and the outward
    normals in (r, z) (all None without the silhouette fit's ``uncertainty``)."""
    basis = cov = normal_rz = None
    if uncertainty is not None:
        basis, cov_c, nrm = uncertainty
        basis = basis[keep]
        cov = cov_c * px**2
        nx, nz = nrm[keep] @ frame.v, nrm[keep] @ frame.u
        normal_rz = np.column_stack([np.where(x < 0, -nx, nx), nz])
    return basis, cov, normal_rz


def _in_image(pts, frame, origin, flipped, n_rows):
    """Edge points, apex, axis and angle back in the original image's coordinates (``n_rows``
    rows; ``flipped``: the window was taken from the image upside down)."""
    pts_img = pts + origin
    apex_img = frame.apex + origin
    axis = frame.u.copy()
    angle = -frame.angle  # counter-clockwise as displayed (apex pointing down)
    if flipped:
        pts_img[:, 0] = n_rows - 1 - pts_img[:, 0]
        apex_img[0] = n_rows - 1 - apex_img[0]
        axis[0] = -axis[0]
    return pts_img, apex_img, axis, angle


DEFOCUS_SIGNS = {"auto": 0, "underfocus": 1, "overfocus": -1}  # tem.defocus -> the fit's defocus_sign


def _defocus_sign(refine, defocus):
    """+1 (underfocus), -1 (overfocus) or 0 (auto) of the tip YAML's ``tem.defocus``, after checking it
    and ``refine``."""
    if refine not in ("normals", "global"):
        raise ValueError(f"refine must be 'normals' or 'global', got {refine!r}")
    if defocus not in DEFOCUS_SIGNS:
        raise ValueError(f"defocus must be one of {', '.join(DEFOCUS_SIGNS)}, got {defocus!r}")
    return DEFOCUS_SIGNS[defocus]


@single_threaded
def extract_profile(
    image: TemImage,
    orientation="auto",
    profile_height=20e-9,
    coating="auto",
    refine="global",
    fringe_correction=True,
    defocus="auto",
) -> TipProfile:
    """Sub-pixel silhouette of the tip in ``image`` and its flanks z(r) (see module doc).

    ``refine``: "normals" (per-normal model fits, ``edges.refine_edges``) or "global" (one global fit
    of all edge pixels, ``silhouette_fit.fit_silhouette``, on b x b blocks of pixels finer than 0.2 nm);
    ``fringe_correction``: its defocus-fringe correction (``pipeline.tem.fringe_correction``) on/off;
    ``defocus``: "auto", or the sign of the defocus as the operator knows it, "underfocus" or
    "overfocus" (``silhouette_fit``, "The sign of the defocus given").
    After the global fit, a faint layer seen beyond the edge on each flank alone (``faint_layer``)
    moves the edge out by the layer's thickness read from the image (``outer_layer``), or, where that
    cannot be read at the apex, marks the profile the core's (``edge_is_core``).  Runs on one BLAS
    thread whatever the environment says (``pipeline.single_thread``): the result does not depend on
    the machine's core count."""
    sign = _defocus_sign(refine, defocus)
    path = image.path or "<image>"
    px = image.pixel_size
    coat_hint = _coating_hint(coating, px, path)
    hpx = profile_height / px
    try:
        coarse, flipped = locate_tip(image.data, 1.3 * hpx, orientation)
    except _Fail as exc:
        raise _fail(path, exc) from None
    img = image.data[::-1] if flipped else image.data
    background = {}
    win, origin, flat, noise, cont, frame, saturated = _window_and_contour(img, coarse, hpx, path, px, background)
    fit_args = (hpx, px, coat_hint, refine, fringe_correction, saturated, sign)
    pts, frame, edge_model, extra, uncertainty = _fit_from_start(win, flat, noise, cont, frame, fit_args, background)
    _note_background(extra, background)
    if extra.get("refine") == "global":
        pts, frame, uncertainty = _beyond_the_edge(
            img, origin, pts, frame, edge_model, hpx, px, extra, uncertainty, saturated is not None
        )
    uncertainty = _beyond_the_fold(pts, frame, hpx, px, background, extra, uncertainty)
    uncertainty = _in_the_bright_band(len(pts), px, extra, uncertainty, bool(background.get("used")))
    x, z = frame.to_tip(pts)
    keep = z <= 1.02 * hpx
    pts, x, z = pts[keep], x[keep], z[keep]
    flank = np.where(x < 0, -1, 1)
    a_mean, a_rms = _asymmetry(x, z, hpx)
    basis, cov, normal_rz = _edge_uncertainty(uncertainty, keep, x, px, frame)
    pts_img, apex_img, axis, angle = _in_image(pts, frame, origin, flipped, image.data.shape[0])
    _check_apex_found(apex_img, image.data.shape, x, z, hpx, path)
    _core_edge_in_image(extra, frame, origin, flipped, image.data.shape[0])
    return TipProfile(
        pixel_size=px,
        pixel_size_source=image.source,
        orientation="up" if flipped else "down",
        angle=float(angle),
        apex_px=apex_img,
        axis_px=axis,
        edge_px=pts_img,
        x=x * px,
        z=z * px,
        flank=flank,
        profile_height=float(profile_height),
        asymmetry_mean=a_mean * px,
        asymmetry_rms=a_rms * px,
        edge_model=dict(
            k_outer_per_m=edge_model["k_outer"] / px,
            k_core_per_m=edge_model["k_core"] / px,
            coating_thickness=edge_model["coat_px"] * px,
            blur_sigma=edge_model["sigma_px"] * px,
            rms_intensity=edge_model["rms_intensity"],
            n_points=int(len(pts)),
            n_rejected=edge_model["n_rejected"],
            **extra,
        ),
        offset_basis=basis,
        offset_cov=cov,
        normal_rz=normal_rz,
    )


def _max_margin(side, br0, br1, bc0, bc1, H, W):
    """The margin (px) beyond which the window of ``_window_and_contour`` cannot grow on ``side``."""
    return {"top": br0, "bottom": H - br1, "left": bc0, "right": W - bc1}[side]


def _edge_level(flat, noise, smooth=2.0):
    """Iso-level just below the flattened background (= 1): 4 noise sigma of the
    ``smooth``-px Gaussian-smoothed image, at least 2 %, so that it follows the
    OUTER surface (lighter coating included)."""
    return 1.0 - max(4.0 * noise / (2.0 * np.sqrt(np.pi) * smooth), 0.02)


def _check_apex_found(apex_img, shape, x, z, hpx, path, min_points=10):
    """The silhouette must have an apex inside the image and points on both flanks near it: a blunt
    tip wider than the field (its flanks leave the image sides) gives a mirror line, and so an apex,
    anywhere (held-out wave image 1033: row -4e9)."""
    H, W = shape
    inside = bool(np.all(np.isfinite(apex_img)) and -0.5 <= apex_img[0] <= H - 0.5 and -0.5 <= apex_img[1] <= W - 0.5)
    near = z <= 0.5 * hpx
    n_left, n_right = int(np.sum(near & (x < 0))), int(np.sum(near & (x > 0)))
    if inside and min(n_left, n_right) >= min_points:
        return
    where = f"row {apex_img[0]:.4g}, col {apex_img[1]:.4g}" if np.all(np.isfinite(apex_img)) else "nowhere"
    raise NoTipError(
        path,
        f"no apex found inside the image: the silhouette's mirror line puts it at {where} px, with "
        f"{n_left} left and {n_right} right flank points near it; the tip may be wider than the field "
        "of view (its flanks leave the image sides), its apex cut by the border, or the edge may have "
        "left the tip (a faint thick coating): image a larger field, or check tem.orientation",
    )


def _sides_hit(cont, shape, r1, c0, c1, H, W):
    """The window sides (bottom, left, right) that contour ``cont`` runs into where the window (rows to
    ``r1``, columns ``c0``..``c1`` of an H x W image) could still grow there."""
    return dict(
        bottom=r1 < H and (cont[:, 0] >= shape[0] - 1.5).any(),
        left=c0 > 0 and (cont[:, 1] <= 0.5).any(),
        right=c1 < W and (cont[:, 1] >= shape[1] - 1.5).any(),
    )


def _at_border(cont, frame, hpx, r0, c0, H, W):
    """True where the apex region of ``cont`` (window px of the window at ``r0``, ``c0`` in an H x W
    image) touches the image border (window edges inside the image are fine)."""
    x, z = frame.to_tip(cont)
    near = z < 0.5 * hpx
    rows, cols = cont[near, 0] + r0, cont[near, 1] + c0
    return bool(rows.size) and (
        rows.max() >= H - 1.5 or cols.min() <= 0.5 or cols.max() >= W - 1.5 or rows.min() <= 0.5
    )


def _check_border(cont, shape, frame, hpx, path, r0, c0, H, W):
    """Apex region must not touch the image border (window edges inside the image are fine)."""
    if _at_border(cont, frame, hpx, r0, c0, H, W):
        raise ApexAtBorderError(path, "apex touches the image border")


def _flanks(x, z):
    left, right = x < 0, x >= 0
    out = []
    for m in (left, right):
        o = np.argsort(z[m])
        out.append((z[m][o], np.abs(x[m][o])))
    return out


def _crossings(a, b, level):
    """Values of ``a`` where the polyline (a_i, b_i) crosses b = level."""
    d = b - level
    i = np.nonzero((d[:-1] <= 0) != (d[1:] <= 0))[0]
    w = d[i] / (d[i] - d[i + 1])
    return a[i] + w * (a[i + 1] - a[i])


def _extent(x, z, levels, max_gap=4.0):
    """Left-most and right-most silhouette x at each height (NaN where not crossed twice,
    or where the crossing falls in a gap > ``max_gap`` px between kept edge points)."""
    seg = np.hypot(np.diff(x), np.diff(z)) <= max_gap
    out = np.full((len(levels), 2), np.nan)
    for k, lv in enumerate(levels):
        d = z - lv
        i = np.nonzero(((d[:-1] <= 0) != (d[1:] <= 0)) & seg)[0]
        if i.size >= 2:
            w = d[i] / (d[i] - d[i + 1])
            c = x[i] + w * (x[i + 1] - x[i])
            out[k] = c.min(), c.max()
    return out


MAX_AXIS_DEV = np.radians(1.5)  # rad: the mirror axis at most this far from the coarse axis


def _mirror_residuals(p, tgt, nrm, tree, sel):
    """Normal distances of the reflected points to the silhouette, and their
    Jacobian w.r.t. (a, t) with the nearest silhouette points held (point-to-line
    Gauss-Newton)."""
    a, t = p
    # reflect about the line x = a + t z (direction d = (t, 1) / |.|)
    h = np.hypot(t, 1.0)
    d = np.array([t, 1.0]) / h
    dd = np.array([1.0, -t]) / h**3  # d(d)/dt
    q = tgt[sel] - [a, 0.0]
    qd = q @ d
    refl = 2 * qd[:, None] * d - q + [a, 0.0]
    _, j = tree.query(refl)
    ok = (j > 0) & (j < len(tgt) - 1)
    nj = nrm[j]
    r = np.where(ok, np.einsum("ij,ij->i", refl - tgt[j], nj), np.nan)
    d_a = np.array([2.0, 0.0]) - 2.0 * d[0] * d  # d(refl)/da
    d_t = 2.0 * ((q @ dd)[:, None] * d + qd[:, None] * dd)  # d(refl)/dt
    return r, np.column_stack([nj @ d_a, np.einsum("ij,ij->i", d_t, nj)])


def _mirror_line(tgt, nrm, tree, sel, x, z, hpx):
    """(a, t) of the mirror line x = a + t z of the silhouette ``tgt`` (tip frame, px) by
    Gauss-Newton on ``_mirror_residuals`` (``_symmetry_frame``)."""
    # start: the axis through the mean midpoint of cuts 0.3-1 x hpx up (the coarse
    # apex of a blunt tip can sit anywhere on its flat bottom)
    ext = _extent(x, z, np.linspace(0.3 * hpx, hpx, 20) + z.min())
    ok = np.isfinite(ext[:, 0])
    p = np.array([float(ext[ok].mean()) if ok.any() else 0.0, 0.0])
    for it in range(9):
        r, J = _mirror_residuals(p, tgt, nrm, tree, sel)
        good = np.isfinite(r) & np.isfinite(J).all(1)
        if good.sum() < 10:
            break
        if it >= 4:  # outliers (contamination, a notch) only once the axis is close
            mad = 1.4826 * np.median(np.abs(r[good])) + 1e-9
            good &= np.abs(r) <= max(4 * mad, 0.5)
        Jg = J[good]
        try:
            step = np.linalg.solve(Jg.T @ Jg, -(Jg.T @ r[good]))
        except np.linalg.LinAlgError:
            break
        p += step
        if it >= 4 and abs(step[1]) < 1e-5 and abs(step[0]) < 1e-2:
            break
    return p


def _symmetry_frame(pts, frame, hpx, max_dev=MAX_AXIS_DEV):
    """Axis = mirror line of the silhouette: the line about which the reflected edge
    points (up to ``profile_height`` above the lowest point) fall onto the silhouette,
    by Gauss-Newton on their normal distances (at most ``max_dev`` from the starting,
    coarse long-range axis).  Every point counts along its normal, so the flat bottom
    of a blunt tip pins the tilt (cut midpoints have almost no lever arm there).
    Apex = lowest crossing of the silhouette with the axis."""
    from scipy.spatial import cKDTree

    pts = np.asarray(pts, float)
    a0 = frame.angle
    for _ in range(2):
        x, z = frame.to_tip(pts)
        tgt = np.column_stack([x, z])
        nrm, _ = curve_normals(tgt, smooth=2.0)
        tree = cKDTree(tgt)
        sel = np.nonzero(z - z.min() <= hpx)[0]
        p = _mirror_line(tgt, nrm, tree, sel, x, z, hpx)
        off, t = p
        ang = float(np.clip(frame.angle + np.arctan(t), a0 - max_dev, a0 + max_dev))
        frame = TipFrame(frame.to_image(off, 0.0), ang)
        if abs(np.arctan(t)) < 1e-4 and abs(off) < 1e-2:
            break
    x, z = frame.to_tip(pts)
    zc = _crossings(z, x, 0.0)
    z0 = float(zc.min()) if zc.size else float(z.min())
    return TipFrame(frame.to_image(0.0, z0), frame.angle)


def _asymmetry(x, z, hpx):
    (zl, rl), (zr, rr) = _flanks(x, z)
    if zl.size < 3 or zr.size < 3:
        return float("nan"), float("nan")
    zz = np.linspace(0.05 * hpx, min(hpx, zl.max(), zr.max()), 50)
    d = np.interp(zz, zr, rr) - np.interp(zz, zl, rl)
    return float(d.mean()), float(np.sqrt((d**2).mean()))
