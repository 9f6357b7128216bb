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

from ..errors import FeatureError
from ..geometry.camera import Camera
from ..geometry.holder import Holder
from .contour import contour_and_segments, initial_lines, threshold_levels
from .contour_model import check_edge_support, model_features
from .corners import (
    check_corner_angles,
    check_corners_on_contour,
    check_families,
    corners_from_lines,
)
from .edges import edge_wear, intersect_consecutive, refine_lines
from .params import FeatureParams, Features, where_px
from .preprocessing import as_grey_u8, binarize, check_image, reduce_image
from .region import find_roi

__all__ = ["detect_features"]


def detect_features(image: np.ndarray, camera: Camera, holder: Holder,
                    params: FeatureParams | None = None) -> Features:
    """Run the image processing of section 2.1 on a grey image of the camera's size.

    Raises
    ------
    ImageError
        Wrong size, black, saturated or uniform image.
    FeatureError
        No holder, no inside contour, a contour cut by the image border, or not exactly
        ``holder.n_corners`` characteristic segments (the message says how many and where).
    """
    params = params or FeatureParams.for_camera(camera)
    timings: dict[str, float] = {}
    t = time.perf_counter()

    def lap(name):
        nonlocal t
        now = time.perf_counter()
        timings[name] = (now - t) * 1e3
        t = now

    image = as_grey_u8(image)
    small = reduce_image(image, params.roi_downscale)
    check_image(image, camera, small)
    lap("check")
    roi, score = find_roi(image, camera, holder, params, small)
    u0, v0, u1, v1 = roi
    sub = image[v0:v1, u0:u1]
    s = params.roi_downscale
    small_sub = small[v0 // s: -(-v1 // s), u0 // s: -(-u1 // s)]
    lap("roi")

    n_expected = holder.n_corners
    levels = threshold_levels(small_sub, params)
    errors = []
    contours = []  # (level, contour_px, contour_ideal) for the model-guided fallback
    for level in levels:
        try:
            binary = binarize(sub, small_sub, level, params)
            res = contour_and_segments(binary, roi, image.shape, camera, level, n_expected,
                                        params, contours)
            segs = res[2]
            lines0, inward, spans = initial_lines(res[1], segs)
            check_corner_angles(lines0, params, segs)
            check_families(lines0, params, segs, camera)
            break
        except FeatureError as e:
            errors.append((level, str(e)))
    else:
        res = None
    lap("threshold+contour+segments")
    origin = np.array([u0, v0], float)
    if res is not None:
        contour_px, contour_ideal, segs, prims = res
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
                            edge_offset_px=off, inward_ideal=inward)
        except FeatureError as e:  # a hidden corner: the model fit may still see its lines
            msg = str(e)
    else:
        msg = (errors[0][1] if len(errors) == 1
               else " | ".join(f"threshold {lv}: {m}" for lv, m in errors))
    if params.model_fallback == "none" or not contours or not params.refine:
        raise FeatureError(msg)
    # the paper's segmentation failed: lines from the model fitted to the contour
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
                    inward_ideal=inward)
