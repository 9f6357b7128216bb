"""Detection of circle grids: blobs, OpenCV's grid finder, sub-pixel ellipse centres.

Used by every circle target (:mod:`cutterpose.calibration.circle_grids`) and by the project's
plate (:func:`detect_plate`, ordered by its triangular mark).

Pipeline:
    1. ``cv2.SimpleBlobDetector`` for dark blobs (light marks: the image is inverted first), in
       two passes: a wide one, then one tuned to the median size of the largest blobs (area
       1/5 to 5x, minimum distance 0.6 diameters, so one circle never gives two blobs); OpenCV's
       default detector is the fallback, and an illumination-flattened copy of the image (the
       grey level divided by its large-scale mean) the last resort against vignetting.
    2. ``cv2.findCirclesGrid`` (symmetric or asymmetric, plain and clustering) on a copy of at
       most 1600 px; scrambled grids (second differences along rows/columns above 0.25 of the
       spacing) are rejected.
    3. Every centre refined at full resolution by ``cv2.fitEllipse`` on sub-pixel crossings of
       the mid grey level around the circle's own dark component (written here because OpenCV's
       blob centres are centroids of thresholded regions, biased by blur and light gradients).

References:
    OpenCV calib3d ``findCirclesGrid``; features2d ``SimpleBlobDetector``.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from ..errors import FeatureError, ImageError
from .plate import CirclePlate

__all__ = ["PlateDetection", "detect_plate", "to_gray_u8", "find_circle_grid",
           "refine_circle_centres", "grid_half_windows", "sample_gray"]


def to_gray_u8(image) -> np.ndarray:
    """A (H, W) uint8 view of a grey or BGR image; ImageError for anything else."""
    import cv2

    gray = np.asarray(image)
    if gray.ndim == 3 and gray.shape[2] in (3, 4):
        gray = cv2.cvtColor(gray, cv2.COLOR_BGR2GRAY if gray.shape[2] == 3 else
                            cv2.COLOR_BGRA2GRAY)
    if gray.ndim != 2 or gray.size == 0:
        raise ImageError(f"expected a grey image, got shape {gray.shape}")
    if gray.dtype != np.uint8:
        gray = np.clip(np.nan_to_num(gray), 0, 255).astype(np.uint8)
    return np.ascontiguousarray(gray)


def _blob_detector(image_shape, extent_spacings: float, d_over_s: float,
                   size_px: float | None = None, relaxed: bool = False):
    """Dark-blob detector; with ``size_px`` (a typical circle diameter) tuned to that size.

    ``extent_spacings`` is the grid's largest extent in spacings (largest circles: the grid
    spans the image); ``d_over_s`` the circle diameter over the spacing. ``relaxed`` (with
    ``size_px``): finer thresholds and looser shape filters, for blurred circles that touch
    their neighbours at some thresholds and circles cut by the image border.
    """
    import cv2

    h, w = image_shape
    p = cv2.SimpleBlobDetector_Params()
    p.filterByColor = True
    p.blobColor = 0  # dark circles
    p.minThreshold, p.maxThreshold, p.thresholdStep = 30, 230, 20
    p.minRepeatability = 2
    p.filterByArea = True
    if size_px is None:
        # largest circle: the whole grid spans the image; smallest: ~4 px across
        d_max = max(w, h) / max(extent_spacings, 1.0) * d_over_s
        p.minArea, p.maxArea = 12.0, float(max(np.pi / 4 * d_max**2, 50.0))
        p.minDistBetweenBlobs = 3.0
    else:
        # perspective changes circle areas across one plate by far less than 5x
        a = np.pi / 4 * size_px**2
        p.minArea, p.maxArea = float(max(a / 5, 8.0)), float(a * 5)
        # one blob per circle: the centres of one circle found at several thresholds merge
        p.minDistBetweenBlobs = float(0.6 * size_px)
    p.filterByCircularity = True
    p.minCircularity = 0.7  # ellipses down to an axis ratio of ~0.4; rejects the triangle
    p.filterByInertia = True
    p.minInertiaRatio = 0.15
    p.filterByConvexity = True
    p.minConvexity = 0.85
    if relaxed and size_px is not None:
        p.minThreshold, p.maxThreshold, p.thresholdStep = 20, 235, 10
        a = np.pi / 4 * size_px**2
        p.minArea, p.maxArea = float(max(a / 6, 6.0)), float(a * 6)
        p.minDistBetweenBlobs = float(0.5 * size_px)
        p.minCircularity, p.minInertiaRatio, p.minConvexity = 0.5, 0.05, 0.7
    return cv2.SimpleBlobDetector_create(p)


def _grid_consistent(grid: np.ndarray) -> bool:
    """Reject scrambled grids: along rows and columns the second differences of a projected
    grid are small against the spacing (perspective and distortion bend it only slowly)."""
    if grid.shape[0] < 2 or grid.shape[1] < 2:
        return True
    step = np.median(np.concatenate([np.linalg.norm(np.diff(grid, axis=0), axis=-1).ravel(),
                                     np.linalg.norm(np.diff(grid, axis=1), axis=-1).ravel()]))
    d2 = [np.zeros(1)]
    if grid.shape[0] >= 3:
        d2.append(np.linalg.norm(grid[2:] - 2 * grid[1:-1] + grid[:-2], axis=-1).ravel())
    if grid.shape[1] >= 3:
        d2.append(np.linalg.norm(grid[:, 2:] - 2 * grid[:, 1:-1] + grid[:, :-2], axis=-1).ravel())
    return bool(step > 0 and np.concatenate(d2).max() < 0.25 * step)


def _asym_consistent(grid: np.ndarray) -> bool:
    """An asymmetric grid's even and odd rows are each a regular grid."""
    return _grid_consistent(grid[0::2]) and _grid_consistent(grid[1::2])


def _flatten_light(gray: np.ndarray) -> np.ndarray:
    """The grey level divided by its large-scale mean (vignetting, uneven light), rescaled."""
    import cv2

    g = gray.astype(np.float32) + 1.0
    sigma = max(gray.shape) / 16.0
    bg = cv2.GaussianBlur(g, (0, 0), sigma)
    r = g / bg
    lo, hi = np.percentile(r, [1, 99])
    return np.clip((r - lo) / max(hi - lo, 1e-6) * 255.0, 0, 255).astype(np.uint8)


def find_circle_grid(gray: np.ndarray, cols: int, rows: int, d_over_s: float, *,
                     asymmetric: bool = False, max_side: int = 1600) -> np.ndarray | None:
    """Rough centres (rows*cols, 2) of a dark-circle grid in ``cv2.findCirclesGrid``'s order
    (pattern size ``(cols, rows)``), at full resolution; None when not found."""
    import cv2

    h, w = gray.shape
    n = cols * rows
    # the grid finder only needs rough centres: work on a copy of at most max_side pixels
    scale = min(1.0, max_side / max(h, w))
    small = gray if scale == 1.0 else cv2.resize(gray, (round(w * scale), round(h * scale)),
                                                 interpolation=cv2.INTER_AREA)
    extent = max(2 * cols - 1 if asymmetric else cols - 1, rows - 1)
    flags0 = cv2.CALIB_CB_ASYMMETRIC_GRID if asymmetric else cv2.CALIB_CB_SYMMETRIC_GRID
    check = _asym_consistent if asymmetric else _grid_consistent
    for img in (small, None):
        if img is None:
            img = _flatten_light(small)
        detectors = []
        kp = _blob_detector(img.shape, extent, d_over_s).detect(img)
        if len(kp) >= max(n // 2, 4):  # a few circles may be merged or cut at this stage
            # the circles dominate the blobs: their median size tunes the second detector
            size = float(np.median(sorted(k.size for k in kp)[-n:]))
            detectors.append(_blob_detector(img.shape, extent, d_over_s, size))
            detectors.append(_blob_detector(img.shape, extent, d_over_s, size, relaxed=True))
        detectors.append(cv2.SimpleBlobDetector_create())  # OpenCV's defaults
        for det in detectors:
            # a textured scene gives thousands of blobs, on which OpenCV's grid search takes
            # seconds per call and finds nothing: such a blob set is not a grid
            if len(det.detect(img)) > max(10 * n, 300):
                continue
            for flags in (flags0, flags0 | cv2.CALIB_CB_CLUSTERING):
                try:
                    found, centres = cv2.findCirclesGrid(img, (cols, rows), flags=flags,
                                                         blobDetector=det)
                except cv2.error:
                    found, centres = False, None
                if found and centres is not None and len(centres) == n:
                    pts = centres.reshape(rows, cols, 2).astype(float)
                    if check(pts):
                        # pixel-centre convention under resizing
                        return ((pts + 0.5) / scale - 0.5).reshape(n, 2)
    return None


def grid_half_windows(points: np.ndarray, cols: int, rows: int, *,
                      asymmetric: bool = False) -> np.ndarray:
    """Half sizes (px) of each circle's refinement window: half the largest distance to a
    grid neighbour (under strong perspective a circle may be longer than the nearest
    spacing; other circles in the window are separate components and are ignored)."""
    grid = np.asarray(points, float).reshape(rows, cols, 2)
    if asymmetric:
        from scipy.spatial import cKDTree

        pts = grid.reshape(-1, 2)
        k = min(5, len(pts))
        d, _ = cKDTree(pts).query(pts, k=k)
        return 0.5 * d[:, 1:].max(axis=1) if k > 1 else np.full(len(pts), 8.0)
    d = np.zeros((rows, cols))
    if rows > 1:
        dr = np.linalg.norm(np.diff(grid, axis=0), axis=-1)
        d[:-1] = np.maximum(d[:-1], dr)
        d[1:] = np.maximum(d[1:], dr)
    if cols > 1:
        dc = np.linalg.norm(np.diff(grid, axis=1), axis=-1)
        d[:, :-1] = np.maximum(d[:, :-1], dc)
        d[:, 1:] = np.maximum(d[:, 1:], dc)
    return 0.5 * d.ravel()


def _edge_points(roi: np.ndarray, thr: float, mask: np.ndarray) -> np.ndarray:
    """Sub-pixel crossings of the level ``thr`` between 4-neighbours touching ``mask``."""
    a = roi.astype(float)
    pts = []
    # horizontal pairs
    l, r = a[:, :-1], a[:, 1:]
    m = ((l - thr) * (r - thr) < 0) & (mask[:, :-1] | mask[:, 1:])
    v, u = np.nonzero(m)
    pts.append(np.stack([u + (thr - l[m]) / (r[m] - l[m]), v.astype(float)], 1))
    # vertical pairs
    t, b = a[:-1, :], a[1:, :]
    m = ((t - thr) * (b - thr) < 0) & (mask[:-1, :] | mask[1:, :])
    v, u = np.nonzero(m)
    pts.append(np.stack([u.astype(float), v + (thr - t[m]) / (b[m] - t[m])], 1))
    return np.concatenate(pts)


def _dark_component(gray: np.ndarray, c: np.ndarray, half: int):
    """The dark component (mid-level threshold) nearest to ``c`` in a window of half size
    ``half`` clipped to the image: (roi, threshold, mask, (u0, v0), touches) or a reason;
    ``touches`` is 'border' or 'window' when the component reaches that edge, else ''."""
    import cv2

    h, w = gray.shape
    cu, cv_ = int(round(c[0])), int(round(c[1]))
    if not (0 <= cu < w and 0 <= cv_ < h):
        return "lies outside the image"
    # the window, clipped to the image: a circle may lie near the border, not across it
    u0, v0 = max(cu - half, 0), max(cv_ - half, 0)
    u1, v1 = min(cu + half + 1, w), min(cv_ + half + 1, h)
    roi = gray[v0:v1, u0:u1].astype(float)
    lo, hi = np.percentile(roi, [2, 98])
    if hi - lo < 10:
        return "has no contrast (blurred or saturated?)"
    thr = 0.5 * (lo + hi)
    dark = (roi < thr).astype(np.uint8)
    _, lab = cv2.connectedComponents(dark, connectivity=8)
    ys, xs = np.nonzero(dark)
    if len(xs) == 0:
        return "not found in its window"
    # the dark component nearest to the rough centre
    j = np.argmin((xs - (c[0] - u0)) ** 2 + (ys - (c[1] - v0)) ** 2)
    blob = lab == lab[ys[j], xs[j]]
    sides = [(blob[0].any(), v0 == 0), (blob[-1].any(), v1 == h),
             (blob[:, 0].any(), u0 == 0), (blob[:, -1].any(), u1 == w)]
    touches = ("border" if any(t and b for t, b in sides) else
               "window" if any(t for t, _ in sides) else "")
    return roi, thr, blob, (u0, v0), touches


def dark_blob_areas(gray: np.ndarray, rough_px: np.ndarray, half_px) -> np.ndarray:
    """Pixel area of the dark component at each rough centre (NaN where none), also for
    circles cut by the image border (e.g. to find the larger origin dot of a grid)."""
    out = np.full(len(rough_px), np.nan)
    for k, (c, hw) in enumerate(zip(np.asarray(rough_px, float),
                                    np.broadcast_to(half_px, len(rough_px)))):
        comp = _dark_component(gray, c, max(int(np.ceil(hw)), 4))
        if not isinstance(comp, str):
            out[k] = float(comp[2].sum())
    return out


def _refine_one(gray: np.ndarray, c: np.ndarray, half_px: float):
    """(centre, axes) of the ellipse fitted to the circle near ``c``, or a reason string."""
    import cv2

    half = max(int(np.ceil(half_px)), 4)
    comp = _dark_component(gray, c, half)
    if not isinstance(comp, str) and comp[4] == "window":
        # a larger circle than its neighbours (an origin dot) or a strongly tilted one
        comp = _dark_component(gray, c, int(np.ceil(1.6 * half)))
    if isinstance(comp, str):
        return comp
    roi, thr, blob, (u0, v0), touches = comp
    if touches == "border":
        return "is cut by the image border"
    if touches == "window":
        return "touches another dark shape (occluded or merged)"
    edge = _edge_points(roi, thr, blob)
    if len(edge) < 8:
        return f"has too few edge points ({len(edge)})"
    mean = edge.mean(axis=0)
    (eu, ev), (a1, a2), _ = cv2.fitEllipse((edge - mean).astype(np.float32))
    return np.array([eu + mean[0] + u0, ev + mean[1] + v0]), np.array([a1, a2])


def refine_circle_centres(gray: np.ndarray, rough_px: np.ndarray, half_px: np.ndarray):
    """Sub-pixel ellipse centres of dark circles near rough centres.

    Returns
    -------
    centres (N, 2), axes (N, 2) (NaN where a circle failed) and ``reasons``: index -> why.
    """
    rough = np.asarray(rough_px, float).reshape(-1, 2)
    centres = np.full((len(rough), 2), np.nan)
    axes = np.full((len(rough), 2), np.nan)
    reasons = {}
    for k, (c, hw) in enumerate(zip(rough, np.broadcast_to(half_px, len(rough)))):
        out = _refine_one(gray, c, float(hw))
        if isinstance(out, str):
            reasons[k] = f"circle {k} {out}"
        else:
            centres[k], axes[k] = out
    return centres, axes, reasons


# ------------------------------------------------------------------------------------------
# the project's plate (caltab): ordered by its triangular mark
@dataclass
class PlateDetection:
    """Circle centres of one plate image, in plate point order.

    Attributes
    ----------
    points_px : (rows*cols, 2) centres of the fitted image ellipses (observed pixels).
    axes_px : (rows*cols, 2) full axes of the fitted ellipses.
    mark_contrast : darkness contrast of the orientation mark against the other corners
        (fraction of the plate's black-white contrast).
    """

    points_px: np.ndarray
    axes_px: np.ndarray
    mark_contrast: float


def sample_gray(gray: np.ndarray, pts: np.ndarray) -> np.ndarray:
    """Bilinear grey values at (n, 2) points (NaN outside)."""
    import cv2

    m = cv2.remap(gray.astype(np.float32), pts[:, :1].astype(np.float32)[None],
                  pts[:, 1:].astype(np.float32)[None], cv2.INTER_LINEAR,
                  borderMode=cv2.BORDER_CONSTANT, borderValue=np.nan)
    return m.ravel()


def _order_by_mark(gray: np.ndarray, grid: np.ndarray, plate: CirclePlate):
    """Rotate/mirror the detected grid so that point 0 sits next to the mark and x, y are
    right-handed (see the plate's Convention). Returns the reordered grid and the contrast."""
    import cv2

    rows, cols, _ = grid.shape
    s = plate.spacing_mm
    # probe positions in grid-index units (j, i) at each corner, from that corner's 3x3 block
    probe_mm = plate.mark_probe_mm()[0]
    a = -(probe_mm[0] / s + 0.5 * (cols - 1))  # outward offset in grid steps (> 0)
    corners = [(0, 0, -1, -1), (0, cols - 1, -1, 1), (rows - 1, cols - 1, 1, 1),
               (rows - 1, 0, 1, -1)]
    offsets = np.array([[0.0, 0.0], [0.04, 0.0], [-0.04, 0.0], [0.0, 0.04], [0.0, -0.04]])
    vals = []
    for i, j, si, sj in corners:
        ii, jj = i - si * np.arange(3), j - sj * np.arange(3)  # the corner's 3x3 block
        I, J = np.meshgrid(ii, jj, indexing="ij")
        src = np.stack([J.ravel(), I.ravel()], 1).astype(np.float32)
        dst = grid[I.ravel(), J.ravel()].astype(np.float32)
        H, _ = cv2.findHomography(src, dst, 0)
        if H is None:
            raise FeatureError("grid corner block is degenerate")
        q = np.array([j + sj * a, i + si * a]) + offsets
        qh = np.c_[q, np.ones(len(q))] @ H.T
        v = sample_gray(gray, qh[:, :2] / qh[:, 2:])
        v = v[np.isfinite(v)]          # all outside the image: NaN, refused below
        vals.append(v.mean() if v.size else np.nan)
    vals = np.array(vals)
    # plate black/white levels: circle centres and the midpoints between circles
    black = np.median(sample_gray(gray, grid.reshape(-1, 2)))
    mid = 0.5 * (grid[1:, 1:] + grid[:-1, :-1]).reshape(-1, 2)
    white = np.median(sample_gray(gray, mid))
    if not np.all(np.isfinite(vals)):
        raise FeatureError("orientation mark outside the image")
    order = np.argsort(vals)
    contrast = float((vals[order[1]] - vals[order[0]]) / max(white - black, 1e-9))
    if white - black < 10 or contrast < 0.35:
        raise FeatureError(f"orientation mark not found (contrast {contrast:.2f})")
    c = int(order[0])
    # bring corner c to index (0, 0): corners are listed clockwise in index space
    g = grid
    for cand in _symmetries(g):
        if cand.shape[:2] != (plate.rows, plate.cols):
            continue
        i, j, _, _ = corners[c]
        if not np.allclose(cand[0, 0], grid[i, j]):
            continue
        ex, ey = cand[0, 1] - cand[0, 0], cand[1, 0] - cand[0, 0]
        if ex[0] * ey[1] - ex[1] * ey[0] > 0:
            return cand, contrast
    # only reachable for non-square grids (a square plate is symmetric about its diagonal)
    raise FeatureError("grid order is mirrored: the image shows the plate's back")


def _symmetries(g: np.ndarray):
    for k in range(4):
        r = np.rot90(g, k, axes=(0, 1))
        yield r
        yield r.transpose(1, 0, 2)


def detect_plate(image: np.ndarray, plate: CirclePlate) -> PlateDetection:
    """Find and order the plate's circle centres in one grey image.

    Raises
    ------
    FeatureError
        Grid not found (wrong grid size, occlusion, strong blur), a circle cut or merged, or
        the orientation mark not found; the message says which.
    """
    gray = to_gray_u8(image)
    d_over_s = plate.diameter_mm / plate.spacing_mm
    rough = find_circle_grid(gray, plate.cols, plate.rows, d_over_s)
    if rough is None:
        raise FeatureError(f"{plate.rows}x{plate.cols} circle grid not found")
    grid, contrast = _order_by_mark(gray, rough.reshape(plate.rows, plate.cols, 2), plate)
    centres, axes, reasons = refine_circle_centres(
        gray, grid.reshape(-1, 2), grid_half_windows(grid, plate.cols, plate.rows))
    if reasons:
        raise FeatureError(next(iter(reasons.values())))
    return PlateDetection(centres, axes, contrast)


# ------------------------------------------------------------------------------------------
