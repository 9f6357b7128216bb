"""The pocket's inside contour and its segmentation into the characteristic segments
(paper section 2.1, steps 4-5): longest closed inside contour, curvature segmentation into
lines and arcs, length filter, collinear merging, the initial line fits.

Convention:
    Contour points in ideal pixels (undistorted through the camera model), lines homogeneous,
    as in :mod:`cutterpose.image.params`.
"""

from __future__ import annotations

import cv2
import numpy as np
from scipy.ndimage import gaussian_filter1d

from ..errors import FeatureError
from .lines import fit_line, line_from
from .params import FeatureParams, Segment, signed_area, where_px


def inside_contour(binary: np.ndarray) -> np.ndarray | None:
    """The longest closed inside contour (a hole of the white region), (M, 2) int pixels."""
    contours, hierarchy = cv2.findContours(binary, cv2.RETR_CCOMP, cv2.CHAIN_APPROX_NONE)
    if hierarchy is None:
        return None
    holes = [c for c, h in zip(contours, hierarchy[0]) if h[3] >= 0 and len(c) >= 8]
    if not holes:
        return None
    best = max(holes, key=lambda c: cv2.arcLength(c, True))
    return best[:, 0, :]


def _fit_circle_maxdev(p: np.ndarray) -> float:
    """Max distance of the points to their algebraic (Kasa) circle; inf if degenerate."""
    A = np.column_stack([2 * p, np.ones(len(p))])
    b = (p ** 2).sum(axis=1)
    try:
        sol, *_ = np.linalg.lstsq(A, b, rcond=None)
    except np.linalg.LinAlgError:
        return np.inf
    cx, cy, k = sol
    r2 = k + cx * cx + cy * cy
    if r2 <= 0:
        return np.inf
    return float(np.abs(np.hypot(p[:, 0] - cx, p[:, 1] - cy) - np.sqrt(r2)).max())


def _split(p: np.ndarray, offset: int, params: FeatureParams, out: list) -> None:
    """Recursively split a run of contour points into lines and arcs (Ramer-Douglas-Peucker
    with a circle test)."""
    n = len(p)
    length = float(np.linalg.norm(np.diff(p, axis=0), axis=1).sum()) if n > 1 else 0.0
    if length < params.min_primitive_px or n < 3:
        return
    c, d, nrm = fit_line(p)
    dev = np.abs((p - c) @ nrm)
    if dev.max() <= params.line_tol_px:
        out.append(Segment("line", offset, offset + n, p, length))
        return
    if n >= 5 and _fit_circle_maxdev(p) <= params.line_tol_px:
        out.append(Segment("arc", offset, offset + n, p, length))
        return
    # split at the point farthest from the chord
    chord = p[-1] - p[0]
    cl = np.linalg.norm(chord)
    if cl > 1e-9:
        cn = np.array([-chord[1], chord[0]]) / cl
        k = int(np.argmax(np.abs((p - p[0]) @ cn)))
    else:
        k = int(np.argmax(np.linalg.norm(p - p[0], axis=1)))
    k = min(max(k, 1), n - 2)
    _split(p[: k + 1], offset, params, out)
    _split(p[k:], offset + k, params, out)


def segment_contour(points_ideal_px: np.ndarray, params: FeatureParams) -> list[Segment]:
    """Segment a closed contour into lines and circular arcs (paper section 2.1).

    The turning angle of the (lightly smoothed) contour over ``min_primitive_px`` marks bends
    where ``|turn| > bend_deg``; the runs between bends are split recursively into primitives of
    at least ``min_primitive_px`` that either stay within ``line_tol_px`` of a line or of a circle.

    Parameters
    ----------
    points_ideal_px : (M, 2) closed contour, about one point per pixel, ideal pixels.

    Returns
    -------
    Primitives in contour order; indices refer to the contour rotated so that it starts on a bend.
    """
    p = np.asarray(points_ideal_px, float)
    m = len(p)
    sm = gaussian_filter1d(p, params.smooth_contour_px, axis=0, mode="wrap") \
        if params.smooth_contour_px > 0 else p
    w = max(1, int(round(params.min_primitive_px / 2)))
    fwd = np.roll(sm, -w, axis=0) - sm
    bwd = sm - np.roll(sm, w, axis=0)
    turn = np.degrees(np.arctan2(bwd[:, 0] * fwd[:, 1] - bwd[:, 1] * fwd[:, 0],
                                 (bwd * fwd).sum(axis=1)))
    bend = np.abs(turn) > params.bend_deg
    if bend.all():
        return []
    if bend.any():
        # start the cyclic walk on a bend so that no run wraps around the end
        start = int(np.argmax(bend))
    else:
        start = 0
    order = (np.arange(m) + start) % m
    b = bend[order]
    pts = p[order]
    out: list[Segment] = []
    i = 0
    while i < m:
        if b[i]:
            i += 1
            continue
        j = i
        while j < m and not b[j]:
            j += 1
        run: list[Segment] = []
        _split(pts[i:j], (i + start), params, run)
        out += _join_arcs(run, params)
        i = j
    return out


def _join_arcs(run: list[Segment], params: FeatureParams) -> list[Segment]:
    """Merge consecutive pieces of one run into a circular arc where their union stays within
    ``line_tol_px`` of a circle but not of a line (recursive splitting cuts arcs into chords)."""
    out: list[Segment] = []
    k = 0
    while k < len(run):
        j = k + 1
        best = None
        while j < len(run) and run[j].start == run[j - 1].stop - 1:
            pts = np.vstack([r.points_ideal_px for r in run[k: j + 1]])
            c, _, n = fit_line(pts)
            if np.abs((pts - c) @ n).max() <= params.line_tol_px \
                    or _fit_circle_maxdev(pts) > params.line_tol_px:
                break
            best = j
            j += 1
        if best is None:
            out.append(run[k])
            k += 1
        else:
            pts = np.vstack([r.points_ideal_px for r in run[k: best + 1]])
            out.append(Segment("arc", run[k].start, run[best].stop, pts,
                               sum(r.length_px for r in run[k: best + 1])))
            k = best + 1
    return out


def _merge_collinear(segs: list[Segment], params: FeatureParams) -> list[Segment]:
    """Merge neighbouring lines (cyclically) that lie on one line."""
    segs = list(segs)
    cos_tol = np.cos(np.radians(params.merge_angle_deg))
    changed = True
    while changed and len(segs) > 1:
        changed = False
        for k in range(len(segs)):
            a, b = segs[k], segs[(k + 1) % len(segs)]
            ca, da, na = fit_line(a.points_ideal_px)
            cb, db, nb = fit_line(b.points_ideal_px)
            if abs(da @ db) < cos_tol:
                continue
            # collinear: one line fits both within the line tolerance (RMS)
            both = np.vstack([a.points_ideal_px, b.points_ideal_px])
            c, _, n = fit_line(both)
            if np.sqrt(np.mean(((both - c) @ n) ** 2)) > params.merge_dist_px:
                continue
            merged = Segment("line", a.start, b.stop, both,
                             a.length_px + b.length_px)
            if k + 1 < len(segs):
                segs[k: k + 2] = [merged]
            else:  # b is segs[0]
                segs = [merged] + segs[1:-1]
            changed = True
            break
    return segs


def threshold_levels(small_sub: np.ndarray, params: FeatureParams) -> list[int]:
    """Grey levels to try: the paper's ``threshold_low`` first; with ``threshold_fallback =
    "otsu"`` then Otsu's level of the (reduced) ROI and the level halfway between the dark
    class's median and Otsu's level (for dark stains on the face)."""
    levels = [int(params.threshold_low)]
    if params.threshold_fallback == "otsu":
        otsu, _ = cv2.threshold(small_sub, 0, 255, cv2.THRESH_BINARY + cv2.THRESH_OTSU)
        dark = small_sub[small_sub < otsu]
        extra = [int(otsu)]
        if dark.size:
            extra.append(int(round(0.5 * (float(np.median(dark)) + otsu))))
        for lv in extra:
            if all(abs(lv - x) >= 5 for x in levels) and 0 < lv < params.threshold_high:
                levels.append(lv)
    return levels


def initial_lines(contour_ideal, segs):
    """The paper's lines: total least squares fits to each segment's contour points.

    Contour pixels are the face's boundary pixels, half a pixel outside the threshold boundary:
    the lines are moved 0.5 px towards the pocket. Returns lines, inward normals and the
    straight runs ``(t0, t1, c, d)`` along each line.
    """
    sign = np.sign(signed_area(contour_ideal))
    n = len(segs)
    lines0 = np.zeros((n, 3))
    inward = np.zeros((n, 2))
    spans = []
    for k, s in enumerate(segs):
        c, d, _ = fit_line(s.points_ideal_px)
        trav = s.points_ideal_px[-1] - s.points_ideal_px[0]
        if trav @ d < 0:
            d = -d
        n_in = sign * np.array([-d[1], d[0]])
        inward[k] = n_in
        c = c + 0.5 * n_in
        lines0[k] = line_from(c, n_in)
        tt = (s.points_ideal_px - c) @ d
        spans.append((float(tt.min()), float(tt.max()), c, d))
    return lines0, inward, spans


def contour_and_segments(binary, roi, shape, camera, level, n_expected, params,
                          contours: list | None = None):
    u0, v0, u1, v1 = roi
    c = inside_contour(binary)
    if c is None:
        raise FeatureError(f"no closed inside contour in the ROI {roi} at threshold {level}: "
                           "the pocket is not separated from the surroundings (holder out of "
                           "view, or lighting too different)")
    contour_px = c.astype(float) + [u0, v0]
    h, w = shape
    m = params.border_margin_px
    near = ((contour_px[:, 0] <= m) | (contour_px[:, 1] <= m) | (contour_px[:, 0] >= w - 1 - m)
            | (contour_px[:, 1] >= h - 1 - m))
    if near.any():
        p = contour_px[near].mean(axis=0)
        raise FeatureError(f"the holder is partly out of view: its inside contour touches the "
                           f"image border near {where_px(p)} px")
    contour_ideal = camera.undistort_px(contour_px)
    if contours is not None:
        contours.append((level, contour_px, contour_ideal))
    prims = segment_contour(contour_ideal, params)
    lines = [s for s in prims if s.kind == "line" and s.length_px >= params.min_segment_px]
    segs = _merge_collinear(lines, params)
    if len(segs) != n_expected:
        where = ", ".join(
            f"{where_px(camera.distort_px(s.points_ideal_px.mean(axis=0)))}:{s.length_px:.0f}px"
            for s in segs)
        raise FeatureError(
            f"found {len(segs)} characteristic segments, expected {n_expected} (threshold "
            f"{level}, contour of {len(contour_px)} px, {len(prims)} lines/arcs); segments at "
            f"[{where}]{_gap_hint(segs, contour_px, camera)}")
    return contour_px, contour_ideal, segs, prims


def _gap_hint(segs, contour_px, camera) -> str:
    """Where the contour is not covered by a characteristic segment (the biggest gap)."""
    if not segs:
        return ""
    m = len(contour_px)
    covered = np.zeros(m, bool)
    for s in segs:
        covered[np.arange(s.start, s.stop) % m] = True
    if covered.all():
        return ""
    # longest cyclic run of uncovered points
    unc = ~covered
    best, best_len, i = None, 0, 0
    doubled = np.concatenate([unc, unc])
    while i < m:
        if doubled[i]:
            j = i
            while j < i + m and doubled[j]:
                j += 1
            if j - i > best_len:
                best, best_len = (i, j), j - i
            i = j
        else:
            i += 1
    mid = contour_px[((best[0] + best[1]) // 2) % m]
    return f"; the longest stretch without a segment ({best_len} px) is near {where_px(mid)}"
