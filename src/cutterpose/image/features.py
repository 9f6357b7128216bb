"""Image processing: the holder's 20 characteristic lines and corners (paper section 2.1).

The paper's chain (Fig. 1), each step configurable through :class:`FeatureParams` whose defaults
are the paper's values:

1. region of interest by grey-level template matching (template built from the model at the
   nominal pose, matched on an image reduced ``roi_downscale`` times);
2. 7 x 7 median filter, applied to the ROI only (the full 12 Mpx frame would cost ~0.2 s);
3. global threshold: grey levels in ``[70, 255]`` are the holder's top face;
4. contours of the binary image; the longest closed *inside* contour (a hole of the face) is the
   pocket's edge;
5. curvature-based segmentation of that contour into straight lines and circular arcs of at least
   ``min_primitive_px`` (6 px); lines shorter than ``min_segment_px`` (50 px) are dropped, the
   remaining collinear neighbours merged: the characteristic segments, 20 for the default holder;
6. each segment's line fitted to its points (total least squares, sub-pixel); the corners are the
   intersections of consecutive lines.

Everything geometric (segmentation, fits, intersections) is done in *ideal* pixels: contour and
edge points are undistorted through the camera model first, so that the holder's straight edges
are straight. The corners are returned both ideal and observed (re-distorted).

Beyond the paper (``refine=True``, the default): a fixed threshold puts the contour where the
blurred edge crosses grey 70, not on the edge itself; the offset depends on blur, lighting and
wear. Each characteristic line is therefore re-fitted to sub-pixel edge points found on the
grey-level gradient (:mod:`cutterpose.image.edges`, which also measures edge wear). When the paper's
segmentation fails, the model's outline fitted to the contour gives the 20 lines instead
(:mod:`cutterpose.image.contour_model`).

Convention:
    Pixels as in :mod:`cutterpose.geometry.camera`: (u, v) with (0, 0) the centre of the top-left
    pixel,
    u along the rows. ``*_px`` are observed (distorted) pixels of the full image, ``*_ideal_px``
    the same points undistorted through the camera model. Lines are homogeneous ``(a, b, c)``
    with ``a u + b v + c = 0`` and ``(a, b)`` a unit normal, in ideal pixels.

References:
    Seed paper, section 2.1 and Fig. 1. Template matching: OpenCV ``matchTemplate``
    (``TM_CCOEFF_NORMED``). Contours: Suzuki & Abe (1985) through ``cv2.findContours``.
    Segmentation in lines and arcs: Ramer-Douglas-Peucker splitting with a curvature test
    (as HALCON's ``segment_contours_xld`` 'lines_circles').
"""

from __future__ import annotations

import time

import numpy as np

from ..errors import FeatureError, InputError
from ..geometry.camera import Camera
from ..geometry.holder import Holder
from .contour import contour_and_segments, initial_lines, threshold_levels
from .contour_model import apply_homography, check_edge_support, model_features, search_outline
from .corners import (
    check_corner_angles,
    check_corners_on_contour,
    check_families,
    corners_from_lines,
)
from .edges import edge_wear, refine_lines, robust_edge_lines
from .lines import intersect_consecutive, line_from
from .params import FeatureParams, Features, Segment, signed_area, where_px
from .preprocessing import as_grey_u8, binarize, check_frame_size, check_image, reduce_image
from .region import find_roi, match_outline

__all__ = ["detect_features"]


def detect_features(image: np.ndarray, camera: Camera, holder: Holder,
                    params: FeatureParams | None = None, corners: bool = True) -> Features:
    """Run the image processing on a grey image of the camera's size: the field chain
    (:func:`detect_features_field`, the default) or, with ``params.chain == "paper"``, the
    threshold chain of section 2.1 (module doc). ``corners=False``: the field chain stops at
    the pocket outline (no line fits, no corners: what ``dm+b`` needs); the paper's chain
    ignores it.

    Raises
    ------
    ImageError
        Wrong size, black, saturated or uniform image.
    FeatureError
        No holder, no inside contour, a contour cut by the image border, or not exactly
        ``holder.n_corners`` characteristic segments (the message says how many and where).
    """
    params = params or FeatureParams.for_camera(camera)
    if params.chain == "field":
        return detect_features_field(image, camera, holder, params, corners)
    if params.chain != "paper":
        raise InputError(f"unknown feature chain {params.chain!r}: 'field' or 'paper'")
    timings, lap = _timer()
    image = as_grey_u8(image)
    check_frame_size(image, camera)
    small = reduce_image(image, params.roi_downscale)
    check_image(image, camera, small)
    lap("check")
    roi, score = find_roi(image, camera, holder, params, small)
    u0, v0, u1, v1 = roi
    sub = image[v0:v1, u0:u1]
    s = params.roi_downscale
    small_sub = small[v0 // s: -(-v1 // s), u0 // s: -(-u1 // s)]
    lap("roi")

    contours = []  # (level, contour_px, contour_ideal) for the model-guided fallback
    res, level, errors = _segment_at_levels(image.shape, sub, small_sub, roi, camera,
                                            holder.n_corners, params, contours)
    lap("threshold+contour+segments")
    origin = np.array([u0, v0], float)
    if res is not None:
        contour_px, contour_ideal, segs, prims, lines0, inward, spans = res
        lines = lines0
        edges: list = []
        if params.refine:
            lines, edges = refine_lines(sub, origin, camera, lines0, spans, inward, params)
            lap("refine")
        corners_ideal, corners_px = corners_from_lines(lines, camera)
        try:
            check_corners_on_contour(corners_ideal, corners_px, contour_ideal, params)
            lap("corners")
            dark = off = None
            if params.refine:
                dark, off = edge_wear(sub, origin, camera, lines, spans, inward, params)
                lap("edge wear")
            return Features(corners_px=corners_px, corners_ideal_px=corners_ideal,
                            lines_ideal=lines, lines_threshold_ideal=lines0, segments=segs,
                            primitives=prims, contour_px=contour_px, edge_points_px=edges,
                            roi=roi, roi_score=score, threshold=int(level),
                            refined=params.refine, timings_ms=timings, edge_darkening=dark,
                            edge_offset_px=off, inward_ideal=inward, image=image)
        except FeatureError as e:  # a hidden corner: the model fit may still see its lines
            msg = str(e)
    else:
        msg = (errors[0][1] if len(errors) == 1
               else " | ".join(f"threshold {lv}: {m}" for lv, m in errors))
    return _model_fallback_features(msg, contours, image, sub, roi, score, camera, holder,
                                    params, timings, lap)


def _segment_at_levels(shape, sub, small_sub, roi, camera: Camera, n_expected: int,
                       params: FeatureParams, contours: list):
    """The paper's threshold chain at each threshold level in turn (binarise, inside contour,
    characteristic segments, initial lines, their angle and family checks) until one passes.
    Returns ``(result or None, level, errors)``: ``result = (contour_px, contour_ideal,
    segments, primitives, lines0, inward, spans)``; ``errors`` the ``(level, message)`` of
    each level that failed; ``contours`` collects the contours for the model fallback."""
    errors = []
    for level in threshold_levels(small_sub, params):
        try:
            binary = binarize(sub, small_sub, level, params)
            res = contour_and_segments(binary, roi, shape, camera, level, n_expected,
                                       params, contours)
            segs = res[2]
            lines0, inward, spans = initial_lines(res[1], segs)
            check_corner_angles(lines0, params, segs)
            check_families(lines0, params, segs, camera)
            return (*res, lines0, inward, spans), level, errors
        except FeatureError as e:
            errors.append((level, str(e)))
    return None, None, errors


def _model_fallback_features(msg: str, contours: list, image, sub, roi, score, camera: Camera,
                             holder: Holder, params: FeatureParams, timings: dict, lap):
    """When the paper's segmentation failed (``msg``): the lines from the holder model fitted
    to the contour (:func:`model_features`), refined on the edges, checked for edge support
    and for corners near the model's; :class:`FeatureError` with both reasons otherwise."""
    if params.model_fallback == "none" or not contours or not params.refine:
        raise FeatureError(msg)
    origin = np.array([roi[0], roi[1]], float)
    try:
        level, contour_px, contour_ideal, segs, lines0, inward, spans, _ = \
            model_features(contours, sub, roi, camera, holder, params)
        lap("model fit")
        lines, edges = refine_lines(sub, origin, camera, lines0, spans, inward, params)
        lap("model refine")
        corners_ideal, corners_px = corners_from_lines(lines, camera)
        # corners may be hidden: the lines must instead rest on the edges' gradient, and the
        # corners stay near the fitted model's (a line that jumped to another edge does not)
        check_edge_support(lines, edges, spans, camera, params)
        gap = np.linalg.norm(corners_ideal - intersect_consecutive(lines0), axis=1)
        if gap.max() > params.max_corner_gap_px:
            k = int(np.argmax(gap))
            raise FeatureError(f"corner near {where_px(corners_px[k])} px moved {gap[k]:.0f} px "
                               "from the model fitted to the contour: an edge is not the "
                               "holder's")
    except FeatureError as e:
        raise FeatureError(f"{msg} | model fit: {e}") from None
    lap("corners")
    dark, off = edge_wear(sub, origin, camera, lines, spans, inward, params)
    lap("edge wear")
    return Features(corners_px=corners_px, corners_ideal_px=corners_ideal, lines_ideal=lines,
                    lines_threshold_ideal=lines0, segments=segs, primitives=[],
                    contour_px=contour_px, edge_points_px=edges, roi=roi, roi_score=score,
                    threshold=int(level), refined=True, timings_ms=timings,
                    segmentation="model", edge_darkening=dark, edge_offset_px=off,
                    inward_ideal=inward, image=image)


def _timer():
    timings: dict[str, float] = {}
    t = [time.perf_counter()]

    def lap(name):
        now = time.perf_counter()
        timings[name] = (now - t[0]) * 1e3
        t[0] = now

    return timings, lap


def detect_features_field(image: np.ndarray, camera: Camera, holder: Holder,
                          params: FeatureParams, corners: bool = True) -> Features:
    """The field chain (issue 10): lines and corners from the gradient, robustly, with no dark
    pocket, dark surround or threshold.

    1. the pocket outline matched on the reduced image's gradient orientations
       (:func:`~cutterpose.image.region.match_outline`): a homography plane -> image;
    2. the outline searched along its normals with shrinking gates, the homography re-fitted
       robustly to the dark-to-bright edge points (Tukey IRLS, MAD scale;
       :func:`~cutterpose.image.contour_model.search_outline`);
    3. each of the 20 lines fitted to its sub-pixel gradient edge points by LMedS + Tukey IRLS
       (:func:`~cutterpose.image.edges.robust_edge_lines`); a line with too little inlier
       support is not seen;
    4. corner ``i`` (holder order) = intersection of edges ``i - 1`` and ``i``, seen when both
       lines are seen and it lies within ``max_corner_gap_px`` of the outline fit's corner.

    With ``corners=False`` it stops after step 2 (``segmentation == "outline"``): no corners
    or lines are seen, the outline's homography and lines are there (``dm+b`` starts from
    them and measures the bands itself; the line fits are a third of the chain's time).

    Returns
    -------
    Features with ``order == "holder"``, ``visible`` the seen corners (the others NaN).

    Raises
    ------
    ImageError
        Wrong size, black, saturated or uniform image.
    FeatureError
        No outline match, no edge points, or fewer than 6 corners seen.
    """
    timings, lap = _timer()
    image = as_grey_u8(image)
    check_frame_size(image, camera)
    small = reduce_image(image, params.roi_downscale)
    check_image(image, camera, small)
    lap("check")
    H, score, roi, sub, origin = _pocket_outline(image, small, camera, holder, params, lap)
    model = np.asarray(holder.corners_mm, float)
    pred = apply_homography(H, model)
    n = len(model)
    # lines, spans and normals of the outline fit, for the wear indicator and the overlay
    sign = np.sign(signed_area(pred))
    nxt = np.roll(pred, -1, axis=0)
    d = (nxt - pred) / np.linalg.norm(nxt - pred, axis=1, keepdims=True)
    inward = sign * np.column_stack([-d[:, 1], d[:, 0]])
    lines_fit = np.array([line_from(pred[k], inward[k]) for k in range(n)])
    t = np.linspace(0, 1, 24, endpoint=False)
    dense = (pred[:, None, :] + t[None, :, None] * (nxt - pred)[:, None, :]).reshape(-1, 2)
    if not corners:
        none = np.zeros(n, bool)
        return Features(corners_px=np.full((n, 2), np.nan),
                        corners_ideal_px=np.full((n, 2), np.nan),
                        lines_ideal=np.full((n, 3), np.nan), lines_threshold_ideal=lines_fit,
                        segments=[], primitives=[], contour_px=camera.distort_px(dense),
                        edge_points_px=[], roi=roi, roi_score=score, threshold=-1,
                        refined=False, timings_ms=timings, segmentation="outline",
                        inward_ideal=inward, visible=none, order="holder",
                        lines_visible=none.copy(), H_ideal_holder=H, image=image)
    lines, seen, edges, support, _ = robust_edge_lines(sub, origin, camera, pred, params)
    lap("lines")
    corners_ideal, corners_px, visible = _corners_of_lines(lines, seen, support, pred, camera,
                                                           params)
    lap("corners")
    length = np.linalg.norm(nxt - pred, axis=1)
    # edge_wear keeps 2 refine_trim_px more from each end (about a contour segment's span)
    spans = [(0.5 * params.corner_trim_px, float(length[k]) - 0.5 * params.corner_trim_px,
              pred[k], d[k]) for k in range(n)]
    dark, off = edge_wear(sub, origin, camera, np.where(seen[:, None], lines, lines_fit), spans,
                          inward, params)
    dark[~seen], off[~seen] = np.nan, np.nan
    lap("edge wear")
    # every line's edge points undistorted in one call
    flat = camera.undistort_px(np.concatenate([np.reshape(e, (-1, 2)) for e in edges]))
    cut = np.cumsum([len(e) for e in edges])[:-1]
    segs = [Segment("line", 0, 0, pts, float(length[k]))
            for k, pts in enumerate(np.split(flat, cut))]
    return Features(corners_px=corners_px, corners_ideal_px=corners_ideal, lines_ideal=lines,
                    lines_threshold_ideal=lines_fit, segments=segs, primitives=[],
                    contour_px=camera.distort_px(dense), edge_points_px=edges, roi=roi,
                    roi_score=score, threshold=-1, refined=True, timings_ms=timings,
                    segmentation="field", edge_darkening=dark, edge_offset_px=off,
                    inward_ideal=inward, visible=visible, order="holder", lines_visible=seen,
                    H_ideal_holder=H, image=image)

def _pocket_outline(image: np.ndarray, small: np.ndarray, camera: Camera, holder: Holder,
                    params: FeatureParams, lap):
    """The field chain's pocket outline: the outline templates matched on the reduced image
    (:func:`match_outline`), a region round it, and the outline's homography searched on the
    image's edges there (:func:`search_outline`), checked for support and for lying in view.
    Returns ``(H_ideal_holder, roi_score, roi, sub, origin)`` (``sub``: the region, float32)."""
    H0, score = match_outline(small, camera, holder, params)
    lap("roi")
    model = np.asarray(holder.corners_mm, float)
    h, w = image.shape
    outline = camera.distort_px(apply_homography(H0, model))
    m = max(params.search_gates_px) + 0.1 * float(np.ptp(outline, axis=0).max()) + 16
    u0, v0 = np.maximum(np.floor(outline.min(axis=0) - m), 0).astype(int)
    u1, v1 = np.minimum(np.ceil(outline.max(axis=0) + m) + 1, [w, h]).astype(int)
    if u1 - u0 < 16 or v1 - v0 < 16:
        raise FeatureError("the pocket outline matched outside the image: holder not in view")
    roi = (int(u0), int(v0), int(u1), int(v1))
    sub = image[v0:v1, u0:u1].astype(np.float32)
    origin = np.array([u0, v0], float)
    H, support_all = search_outline(sub, origin, camera, holder, H0, params)
    lap("outline search")
    if support_all < params.min_outline_support:
        raise FeatureError(f"the pocket outline fits the image's edges along only "
                           f"{100 * support_all:.0f} % of its length (< "
                           f"{100 * params.min_outline_support:.0f} %): holder hidden, partly "
                           "out of view, or not in view")
    pred_px = camera.distort_px(apply_homography(H, model))
    near = ~camera.in_image(pred_px, params.border_margin_px)
    if near.any():
        raise FeatureError(f"the holder is partly out of view: its pocket corner near "
                           f"{where_px(pred_px[near][0])} px is outside the image")
    return H, score, roi, sub, origin


def _corners_of_lines(lines: np.ndarray, seen: np.ndarray, support: np.ndarray,
                      pred: np.ndarray, camera: Camera, params: FeatureParams):
    """The corners of the field chain's lines: corner ``i`` where the seen edges ``i - 1`` and
    ``i`` meet, within ``max_corner_gap_px`` of the outline fit's ``pred``; at least 6 of them
    (else :class:`FeatureError` naming the least-supported edge). Returns ``(corners_ideal,
    corners_px, visible)`` (NaN where not visible)."""
    n = len(pred)
    X = intersect_consecutive(np.where(np.isfinite(lines), lines, 0.0))
    corners_ideal = np.roll(X, 1, axis=0)  # corner i: edges i - 1 and i
    visible = seen & np.roll(seen, 1)
    with np.errstate(invalid="ignore"):
        visible &= np.linalg.norm(corners_ideal - pred, axis=1) <= params.max_corner_gap_px
    corners_ideal[~visible] = np.nan
    corners_px = np.full((n, 2), np.nan)
    if visible.any():
        corners_px[visible] = camera.distort_px(corners_ideal[visible])
    if visible.sum() < 6:
        k = int(np.argmin(support))
        mid = camera.distort_px(0.5 * (pred[k] + pred[(k + 1) % n])[None])[0]
        raise FeatureError(f"only {int(visible.sum())} of {n} corners seen (lines seen: "
                           f"{int(seen.sum())}; least-supported edge near {where_px(mid)} px, "
                           f"{100 * support[k]:.0f} % of it): holder hidden or damaged")
    return corners_ideal, corners_px, visible

