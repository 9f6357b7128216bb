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
grey-level gradient (:mod:`cutterpose.edges`, which also measures edge wear). When the paper's
segmentation fails, the model's outline fitted to the contour gives the 20 lines instead
(:mod:`cutterpose.contour_model`).

Convention:
    Pixels as in :mod:`cutterpose.camera`: (u, v) with (0, 0) the centre of the top-left pixel,
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
from dataclasses import dataclass, field, replace
from pathlib import Path

import cv2
import numpy as np
from scipy.ndimage import gaussian_filter1d

from .camera import Camera
from .edges import edge_wear, fit_line, intersect_consecutive, line_from, refine_lines
from .errors import FeatureError, ImageError
from .holder import Holder
from .pose import Pose

__all__ = ["FeatureParams", "Features", "Segment", "load_image", "check_image", "find_roi",
           "detect_features", "segment_contour"]


#: focal length of the paper's camera in pixels (Table 1: f / s_y)
PAPER_FOCAL_PX = 0.00854103 / 3.45e-6


@dataclass(frozen=True)
class FeatureParams:
    """Parameters of the image processing; the defaults are the paper's (section 2.1).

    Pixel lengths are for the paper's 12 Mpx camera (f ~ 2475 px at 600 mm); use
    :meth:`scaled` for a camera with another resolution.
    """

    median_ksize: int = 7                 #: median mask (paper: 7 x 7)
    roi_downscale: int = 8                #: template matching on an image reduced this much
    roi_band_mm: float = 25.0             #: face band around the pocket in the ROI template
    roi_min_score: float = 0.35           #: normalised correlation below this: no holder
    roi_margin_frac: float = 0.12         #: ROI margin, fraction of the pocket's size ...
    roi_margin_px: int = 48               #: ... plus this many pixels
    threshold_low: int = 70               #: global threshold range (paper: 70 .. 255)
    threshold_high: int = 255
    threshold_fallback: str = "otsu"      #: "otsu" retries with Otsu's level when 70 fails; "none"
    smooth_contour_px: float = 2.0        #: Gaussian smoothing of the contour before the curvature
    bend_deg: float = 25.0                #: turning over min_primitive_px that breaks a primitive
    min_primitive_px: float = 6.0         #: shortest line or arc (paper: 6 px)
    line_tol_px: float = 2.5              #: max distance of a line primitive's points to its line
    min_segment_px: float = 50.0          #: shorter lines are dropped (paper: 50 px)
    merge_angle_deg: float = 8.0          #: collinear merging: direction difference ...
    merge_dist_px: float = 2.0            #: ... and RMS distance to their common line
    min_corner_angle_deg: float = 30.0    #: consecutive lines must meet at least this steeply
    refine: bool = True                   #: gradient refinement of the lines (beyond the paper)
    refine_half_width_px: float = 6.0     #: profile half length along the normal
    refine_step_px: float = 1.0           #: spacing of the profiles along the line
    refine_trim_px: float = 4.0           #: kept away from the ends of the straight run
    refine_sigma_px: float = 0.8          #: smoothing of the profiles along the normal
    refine_passes: int = 2                #: re-centre the profiles on the refined line
    border_margin_px: float = 3.0         #: a contour this close to the image border is cut
    max_corner_gap_px: float = 15.0       #: a corner farther than this from the contour is hidden
    max_family_spread_deg: float = 12.0   #: alternate lines (one holder direction) stay parallel
    min_edge_support: float = 0.25        #: model fallback: share of an edge its gradient covers
    model_fallback: str = "homography"    #: "none": no model-guided lines when segmentation fails
    band_only: bool = True                #: filter/threshold only tiles the edge passes through
    tile_px: int = 64                     #: tile size of the band (a multiple of roi_downscale)

    @classmethod
    def for_camera(cls, camera: Camera, **changes) -> FeatureParams:
        """The paper's values scaled to a camera's focal length (the paper's camera has
        f = 8.54 mm / 3.45 um = 2476 px); unchanged within 10 % of it."""
        factor = camera.focal_px / PAPER_FOCAL_PX
        p = cls(**changes)
        return p if abs(factor - 1) < 0.1 else p.scaled(factor)

    def scaled(self, factor: float) -> FeatureParams:
        """The same parameters for an image ``factor`` times the paper's resolution."""
        k = max(1, int(round(self.median_ksize * factor)) | 1)
        return replace(self, median_ksize=k if k >= 3 else 3,
                       roi_downscale=max(1, int(round(self.roi_downscale * factor))),
                       roi_margin_px=int(round(self.roi_margin_px * factor)),
                       min_segment_px=self.min_segment_px * factor)


@dataclass
class Segment:
    """A primitive of the segmented contour.

    Attributes
    ----------
    kind : "line" or "arc".
    start, stop : indices into the contour (cyclic; ``stop`` may exceed its length).
    points_ideal_px : (n, 2) its contour points, ideal pixels.
    length_px : arc length in ideal pixels.
    """

    kind: str
    start: int
    stop: int
    points_ideal_px: np.ndarray
    length_px: float


@dataclass
class Features:
    """What the image processing found.

    Attributes
    ----------
    corners_px, corners_ideal_px : (N, 2) corners in contour order (start and direction as the
        contour tracer left them), observed and ideal pixels.
    lines_ideal : (N, 3) characteristic lines; corner k is the intersection of lines k and k+1.
    lines_threshold_ideal : (N, 3) the same lines fitted to the thresholded contour only.
    segments : the characteristic segments (merged lines), contour order.
    primitives : every line and arc of the segmentation (before the length filter).
    contour_px : (M, 2) the inside contour, observed pixels.
    edge_points_px : per line, the gradient edge points used by the refinement (observed px).
    roi : (u0, v0, u1, v1) the region of interest, full-image pixels (u1, v1 exclusive).
    roi_score : template matching score.
    threshold : the grey level used.
    timings_ms : wall time per stage.
    segmentation : "contour" (the paper's segmentation gave the 20 segments) or "model" (the
        fallback: lines from the holder model fitted to the contour, then refined).
    edge_darkening : (N,) per line, how much darker the face is just outside the edge than
        farther out, as a fraction of the edge contrast (:func:`edge_wear`; ~0 for a clean
        edge, 0.3-0.4 for a worn one). None without refinement.
    edge_offset_px : (N,) per line, how far (px) the edge estimate may lie outside the true edge
        because of that darkening (:func:`edge_wear`).
    inward_ideal : (N, 2) unit normals of the lines towards the pocket (ideal px).
    """

    corners_px: np.ndarray
    corners_ideal_px: np.ndarray
    lines_ideal: np.ndarray
    lines_threshold_ideal: np.ndarray
    segments: list
    primitives: list
    contour_px: np.ndarray
    edge_points_px: list
    roi: tuple
    roi_score: float
    threshold: int
    refined: bool
    timings_ms: dict = field(default_factory=dict)
    segmentation: str = "contour"
    edge_darkening: np.ndarray | None = None
    edge_offset_px: np.ndarray | None = None
    inward_ideal: np.ndarray | None = None


# ------------------------------------------------------------------------------------------
# input
def load_image(path) -> np.ndarray:
    """Read an image file as 8-bit grey.

    Colour images are converted to grey, 16-bit images scaled to 8 bits.

    Raises
    ------
    ImageError
        Missing file, a directory, not an image, or a truncated/corrupt image.
    """
    path = Path(path)
    if not path.exists():
        raise ImageError(f"{path}: image file not found")
    if not path.is_file():
        raise ImageError(f"{path}: not a file")
    data = np.fromfile(str(path), dtype=np.uint8)
    if data.size == 0:
        raise ImageError(f"{path}: empty file, not an image")
    img = cv2.imdecode(data, cv2.IMREAD_UNCHANGED)
    if img is None:
        raise ImageError(f"{path}: not a readable image (unknown format, truncated or corrupt)")
    if _png_truncated(data):
        raise ImageError(f"{path}: truncated PNG (no IEND chunk)")
    return as_grey_u8(img, str(path))


def _png_truncated(data: np.ndarray) -> bool:
    # libpng may decode a cut PNG partially (the missing rows black) without an error.
    is_png = data.size >= 8 and bytes(data[:8]) == b"\x89PNG\r\n\x1a\n"
    return is_png and b"IEND" not in bytes(data[-32:])


def as_grey_u8(img: np.ndarray, where: str = "image") -> np.ndarray:
    """An image array as contiguous 8-bit grey (colour -> grey, 16 bit / float -> 8 bit)."""
    a = np.asarray(img)
    if a.ndim == 3 and a.shape[2] in (3, 4):
        a = cv2.cvtColor(a, cv2.COLOR_BGR2GRAY if a.shape[2] == 3 else cv2.COLOR_BGRA2GRAY)
    elif a.ndim == 3 and a.shape[2] == 1:
        a = a[:, :, 0]
    if a.ndim != 2:
        raise ImageError(f"{where}: expected a grey or colour image, got an array of shape "
                         f"{a.shape}")
    if a.dtype == np.uint16:
        a = (a >> 8).astype(np.uint8)
    elif a.dtype != np.uint8:
        if not np.issubdtype(a.dtype, np.number) or not np.all(np.isfinite(a)):
            raise ImageError(f"{where}: image holds non-numeric or non-finite values")
        hi = 1.0 if a.max() <= 1.0 else 255.0
        a = np.clip(np.rint(a * (255.0 / hi)), 0, 255).astype(np.uint8)
    return np.ascontiguousarray(a)


def check_image(image: np.ndarray, camera: Camera, small: np.ndarray | None = None) -> None:
    """Refuse images that cannot show the holder: wrong size, black, saturated, uniform.

    Raises
    ------
    ImageError
        With the measured statistic in the message.
    """
    h, w = image.shape[:2]
    if (w, h) != tuple(camera.image_size_px):
        cw, ch = camera.image_size_px
        raise ImageError(f"image is {w} x {h} px but the camera model is for {cw} x {ch} px "
                         "(wrong camera file, or a resized/cropped image)")
    s = small if small is not None else image[::8, ::8]
    p01, p50, p99 = np.percentile(s, [1, 50, 99])
    if p99 < 20:
        raise ImageError(f"image is black (99th percentile grey level {p99:.0f}): no light or "
                         "lens cap on")
    if np.mean(s >= 250) > 0.5:
        raise ImageError(f"image is saturated ({100 * np.mean(s >= 250):.0f} % of pixels at "
                         "255): overexposed")
    if p99 - p01 < 10:
        raise ImageError(f"image is nearly uniform (grey levels {p01:.0f}..{p99:.0f}): "
                         "nothing to measure")


# ------------------------------------------------------------------------------------------
# region of interest
_TEMPLATE_CACHE: dict = {}


def _nominal_outlines_px(camera: Camera, holder: Holder, band_mm: float):
    pose = Pose.nominal()
    pocket = camera.project(pose.apply(holder.points_holder_mm))
    lo = holder.corners_mm.min(axis=0) - band_mm
    hi = holder.corners_mm.max(axis=0) + band_mm
    rect = holder.outer_rectangle_mm
    lo = np.maximum(lo, rect.min(axis=0))
    hi = np.minimum(hi, rect.max(axis=0))
    box_mm = np.array([[lo[0], lo[1]], [hi[0], lo[1]], [hi[0], hi[1]], [lo[0], hi[1]]])
    box = camera.project(pose.apply(np.column_stack([box_mm, np.zeros(4)])))
    return pocket, box


def _template(camera: Camera, holder: Holder, params: FeatureParams):
    key = (repr(camera), holder.corners_mm.tobytes(), holder.outer_length_x_mm,
           holder.outer_width_y_mm, params.roi_downscale, params.roi_band_mm)
    if key in _TEMPLATE_CACHE:
        return _TEMPLATE_CACHE[key]
    pocket, box = _nominal_outlines_px(camera, holder, params.roi_band_mm)
    if not (np.all(np.isfinite(pocket)) and np.all(np.isfinite(box))):
        raise FeatureError("the holder model does not project into this camera at the nominal "
                           "pose")
    s = float(params.roi_downscale)
    origin = np.floor(box.min(axis=0) / s)
    size = np.ceil(box.max(axis=0) / s - origin).astype(int) + 1
    tpl = np.zeros((size[1], size[0]), np.float32)
    shift = 4
    scale = 1 << shift
    # pixel centres: small pixel j covers full pixels [s j - 0.5, s (j + 1) - 0.5)

    def to_small(p):
        return (p + 0.5) / s - 0.5 - origin

    cv2.fillPoly(tpl, [np.rint(to_small(box) * scale).astype(np.int32)], 1.0, cv2.LINE_AA,
                 shift)
    cv2.fillPoly(tpl, [np.rint(to_small(pocket) * scale).astype(np.int32)], 0.0, cv2.LINE_AA,
                 shift)
    out = (tpl, origin.astype(int), pocket)
    _TEMPLATE_CACHE[key] = out
    return out


def reduce_image(image: np.ndarray, factor: int) -> np.ndarray:
    """Area-averaged reduction by an integer factor (the image for the ROI search)."""
    if factor <= 1:
        return image
    h, w = image.shape
    return cv2.resize(image, (w // factor, h // factor), interpolation=cv2.INTER_AREA)


def find_roi(image: np.ndarray, camera: Camera, holder: Holder, params: FeatureParams,
             small: np.ndarray | None = None) -> tuple[tuple[int, int, int, int], float]:
    """Region of interest holding the whole inside contour.

    A template of the holder's top face at the nominal pose (face bright, pocket dark, a band of
    ``roi_band_mm`` around the pocket) is matched on the reduced image by normalised correlation;
    the ROI is the nominal pocket's bounding box moved by the best match, widened by a margin that
    covers the working range's rotation and scale changes.

    Returns
    -------
    roi : (u0, v0, u1, v1) in full-image pixels, clipped to the image.
    score : the best normalised correlation.

    Raises
    ------
    FeatureError
        No position matches the template well (no holder in the image).
    """
    s = params.roi_downscale
    if small is None:
        small = reduce_image(image, s)
    tpl, origin, pocket = _template(camera, holder, params)
    if tpl.shape[0] > small.shape[0] or tpl.shape[1] > small.shape[1]:
        raise FeatureError("the holder template is larger than the image: check the camera model")
    res = cv2.matchTemplate(small.astype(np.float32), tpl, cv2.TM_CCOEFF_NORMED)
    _, score, _, loc = cv2.minMaxLoc(res)
    if not np.isfinite(score) or score < params.roi_min_score:
        raise FeatureError(f"no holder found: the best template match scores {score:.2f} "
                           f"(< {params.roi_min_score}); is the holder in view?")
    shift_px = (np.array(loc) - origin) * s
    lo = pocket.min(axis=0) + shift_px
    hi = pocket.max(axis=0) + shift_px
    margin = params.roi_margin_frac * (hi - lo).max() + params.roi_margin_px
    h, w = image.shape
    # aligned on the reduced image's grid so that ROI tiles map onto whole reduced pixels
    u0, v0 = (np.maximum(np.floor((lo - margin) / s), 0) * s).astype(int)
    u1 = int(min(np.ceil(hi[0] + margin) + 1, w))
    v1 = int(min(np.ceil(hi[1] + margin) + 1, h))
    return (int(u0), int(v0), u1, v1), float(score)


def binarize(sub: np.ndarray, small_sub: np.ndarray, level: int, params: FeatureParams
             ) -> np.ndarray:
    """Median filter and global threshold of the ROI: grey in ``[level, threshold_high]`` -> 255.

    With ``band_only`` the ROI is cut in tiles of ``tile_px``; the reduced image (each pixel the
    mean of ``roi_downscale^2`` pixels) is thresholded first, and only tiles where that coarse
    binary changes within one reduced pixel are median-filtered and thresholded at full
    resolution; the others take the coarse value. The pocket's interior and the face far from
    its edge never reach the 7 x 7 median, which is what makes 12 Mpx frames fast.
    """
    k, lo, hi = params.median_ksize, level, params.threshold_high
    if not params.band_only or params.roi_downscale <= 1:
        med = cv2.medianBlur(sub, k) if k > 1 else sub
        return cv2.inRange(med, lo, hi)
    s = params.roi_downscale
    T = max(s, (params.tile_px // s) * s)
    b = T // s
    H, W = sub.shape
    ny, nx = -(-H // T), -(-W // T)
    # coarse binary padded to whole tiles; a missing border strip counts as mixed
    cb = np.full((ny * b, nx * b), 127, np.uint8)
    cs = small_sub[: ny * b, : nx * b]
    cb[: cs.shape[0], : cs.shape[1]] = np.where((cs >= lo) & (cs <= hi), 255, 0)
    kernel = np.ones((3, 3), np.uint8)
    mixed_small = cv2.dilate(cb, kernel) != cv2.erode(cb, kernel)
    mixed = mixed_small.reshape(ny, b, nx, b).any(axis=(1, 3))
    value = (cb.reshape(ny, b, nx, b).mean(axis=(1, 3)) > 127).astype(np.uint8) * 255
    binary = np.repeat(np.repeat(value, T, axis=0), T, axis=1)[:H, :W].copy()
    r = k // 2
    for i, j in zip(*np.nonzero(mixed)):
        y0, x0 = i * T, j * T
        y1, x1 = min(y0 + T, H), min(x0 + T, W)
        py0, px0 = max(y0 - r, 0), max(x0 - r, 0)
        py1, px1 = min(y1 + r, H), min(x1 + r, W)
        tile = sub[py0:py1, px0:px1]
        med = cv2.medianBlur(tile, k) if k > 1 else tile
        binary[y0:y1, x0:x1] = cv2.inRange(med[y0 - py0: y1 - py0, x0 - px0: x1 - px0], lo, hi)
    return binary


# ------------------------------------------------------------------------------------------
# contour
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


def _signed_area(p: np.ndarray) -> float:
    x, y = p[:, 0], p[:, 1]
    return 0.5 * float(np.dot(x, np.roll(y, -1)) - np.dot(np.roll(x, -1), y))


# ------------------------------------------------------------------------------------------
# segmentation into lines and arcs


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



# ------------------------------------------------------------------------------------------
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
            res = _contour_and_segments(binary, roi, image.shape, camera, level, n_expected,
                                        params, contours)
            segs = res[2]
            lines0, inward, spans = _initial_lines(res[1], segs)
            _check_corner_angles(lines0, params, segs)
            _check_families(lines0, params, segs, camera)
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
        corners_ideal, corners_px = _corners(lines, camera)
        try:
            _check_corners_on_contour(corners_ideal, corners_px, contour_ideal, params)
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
    # the paper's segmentation failed: lines from the model fitted to the contour (imported
    # here: contour_model builds on this module's Segment)
    from .contour_model import check_edge_support, model_features

    try:
        level, contour_px, contour_ideal, segs, lines0, inward, spans, _ = \
            model_features(contours, sub, roi, camera, holder, params)
        lap("model fit")
        lines, edges = refine_lines(sub, origin, camera, lines0, spans, inward, params)
        lap("model refine")
        corners_ideal, corners_px = _corners(lines, camera)
        # corners may be hidden: the lines must instead rest on the edges' gradient, and the
        # corners stay near the fitted model's (a line that jumped to another edge does not)
        check_edge_support(lines, edges, spans, camera, params)
        gap = np.linalg.norm(corners_ideal - intersect_consecutive(lines0), axis=1)
        if gap.max() > params.max_corner_gap_px:
            k = int(np.argmax(gap))
            raise FeatureError(f"corner near {_where(corners_px[k])} px moved {gap[k]:.0f} px "
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


def _corners(lines, camera: Camera):
    """Corners of consecutive lines, ideal and observed pixels."""
    corners_ideal = intersect_consecutive(lines)
    corners_px = camera.distort_px(corners_ideal)
    if not np.all(np.isfinite(corners_px)):
        raise FeatureError("consecutive characteristic lines do not intersect")
    return corners_ideal, corners_px


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


def _initial_lines(contour_ideal, segs):
    """The paper's lines: total least squares fits to each segment's contour points.

    Contour pixels are the face's boundary pixels, half a pixel outside the threshold boundary:
    the lines are moved 0.5 px towards the pocket. Returns lines, inward normals and the
    straight runs ``(t0, t1, c, d)`` along each line.
    """
    sign = np.sign(_signed_area(contour_ideal))
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


def _where(p) -> str:
    return f"({p[0]:.0f}, {p[1]:.0f})"


def _contour_and_segments(binary, roi, shape, camera, level, n_expected, params,
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
                           f"image border near {_where(p)} px")
    contour_ideal = camera.undistort_px(contour_px)
    if contours is not None:
        contours.append((level, contour_px, contour_ideal))
    prims = segment_contour(contour_ideal, params)
    lines = [s for s in prims if s.kind == "line" and s.length_px >= params.min_segment_px]
    segs = _merge_collinear(lines, params)
    if len(segs) != n_expected:
        where = ", ".join(
            f"{_where(camera.distort_px(s.points_ideal_px.mean(axis=0)))}:{s.length_px:.0f}px"
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
    return f"; the longest stretch without a segment ({best_len} px) is near {_where(mid)}"


def _check_corners_on_contour(corners_ideal, corners_px, contour_ideal, params):
    """A corner must lie near the contour: one the contour detours around is occluded (or
    broken off), and the lines meeting there may not be the holder's."""
    d2 = ((corners_ideal[:, None, :] - contour_ideal[None, ::2, :]) ** 2).sum(axis=2)
    gap = np.sqrt(d2.min(axis=1))
    bad = np.nonzero(gap > params.max_corner_gap_px)[0]
    if len(bad):
        where = ", ".join(f"{_where(corners_px[k])} ({gap[k]:.0f} px)" for k in bad)
        raise FeatureError(f"{len(bad)} corner(s) not on the contour, occluded or damaged: "
                           f"at {where} from the nearest contour point "
                           f"(> {params.max_corner_gap_px:g} px)")


def _check_families(lines, params, segs, camera):
    """The holder's edges alternate between its X and Y directions; within the working range
    each family stays nearly parallel in the image (vanishing points far away). A line off its
    family's direction is not a holder edge (an occluder's or a stain's outline)."""
    ang = np.arctan2(lines[:, 1], lines[:, 0])
    for fam in (0, 1):
        idx = np.arange(fam, len(lines), 2)
        z = np.exp(2j * ang[idx])
        mean = np.angle(z.sum()) / 2
        dev = np.degrees(np.abs(np.angle(np.exp(2j * (ang[idx] - mean))) / 2))
        k = int(np.argmax(dev))
        if dev[k] > params.max_family_spread_deg:
            i = int(idx[k])
            p = camera.distort_px(segs[i].points_ideal_px.mean(axis=0))
            raise FeatureError(
                f"segment {i} near {_where(p)} px is {dev[k]:.0f} deg off the direction of its "
                f"family of parallel edges (> {params.max_family_spread_deg:g}): an occluded or "
                "damaged edge, or a pose far outside the working range")


def _check_corner_angles(lines, params, segs):
    n = lines[:, :2]
    cosang = np.abs((n * np.roll(n, -1, axis=0)).sum(axis=1))
    bad = np.nonzero(cosang > np.cos(np.radians(params.min_corner_angle_deg)))[0]
    if len(bad):
        k = int(bad[0])
        raise FeatureError(
            f"characteristic segments {k} and {(k + 1) % len(lines)} are nearly parallel "
            f"(they meet at {np.degrees(np.arccos(min(1.0, cosang[k]))):.0f} deg): a segment is "
            f"missing near {_where(segs[k].points_ideal_px[-1])} ideal px")
