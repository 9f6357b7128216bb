"""Parameters and results of the image stage (paper section 2.1): :class:`FeatureParams`
(the paper's values as defaults), :class:`Segment`, :class:`Features`.

Convention:
    Pixels as in :mod:`cutterpose.geometry.camera`; ``*_px`` observed (distorted) pixels of the full
    image, ``*_ideal_px`` the same points undistorted. Lines are homogeneous ``(a, b, c)`` with
    ``a u + b v + c = 0`` and ``(a, b)`` a unit normal, in ideal pixels.
"""

from __future__ import annotations

from dataclasses import dataclass, field, replace

import numpy as np

from ..geometry.camera import Camera

PAPER_FOCAL_PX = 0.00854103 / 3.45e-6


@dataclass(frozen=True)
class FeatureParams:
    """Parameters of the image processing.

    Two chains (``chain``): ``"field"`` (the default; issue 10) finds the pocket's outline on
    gradient orientations and its 20 lines by a model-guided, robust edge search, needing no
    dark pocket or dark surround; ``"paper"`` (:meth:`paper`) is section 2.1 as before:
    grey-level template, threshold 70..255, longest inside contour, curvature segmentation
    (the threshold and segmentation fields below are the paper's values), with the gradient
    refinement and fallbacks beyond the paper (``refine``, ``threshold_fallback``,
    ``model_fallback``; set them to ``False`` / ``"none"`` for the chain exactly as published).

    Pixel lengths are for the paper's 12 Mpx camera (f ~ 2475 px at 600 mm); use
    :meth:`scaled` for a camera with another resolution.
    """

    chain: str = "field"                  #: "field" (gradient outline, robust lines) or "paper"

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
    # --- field chain (issue 10) ---
    #: in-plane turns of the outline template (deg; the working range is +-10 deg)
    roi_gammas_deg: tuple = (-12.0, -9.0, -6.0, -3.0, 0.0, 3.0, 6.0, 9.0, 12.0)
    roi_depths_mm: tuple = (600.0,)     #: outline templates at these depths (approach: more)
    roi_line_px: int = 3                  #: width of the template's outline (reduced px)
    roi_min_edge_score: float = 0.3       #: outline orientation match below this: no holder
    #: half widths (px) of the successive model-guided searches along the outline's normals
    search_gates_px: tuple = (40.0, 14.0, 6.0)
    search_step_px: float = 10.0          #: spacing of the search profiles along each edge
    corner_trim_px: float = 10.0          #: profiles kept this far from the predicted corners
    min_line_support: float = 0.3         #: a line is seen if inliers cover this much of it
    min_outline_support: float = 0.6      #: the outline fit must rest on edges along this much
    max_line_shift_px: float = 2.5        #: a seen line stays this close to the outline fit
    #: ... plus this much outwards (a rounded or chamfered edge images outside the design edge
    #: by up to its width, unevenly round the contour, which the outline fit averages)
    max_outward_shift_px: float = 4.0
    #: which rise across a broken (rounded, chamfered) edge is the edge: 0 = the strongest;
    #: f > 0 = the innermost (pocket-side) rise reaching f of the strongest (edges.py)
    edge_innermost: float = 0.3

    @classmethod
    def paper(cls, **changes) -> FeatureParams:
        """The threshold chain of section 2.1 (``chain="paper"``), its values as defaults."""
        return cls(**({"chain": "paper"} | changes))

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
                       min_segment_px=self.min_segment_px * factor,
                       search_gates_px=tuple(max(3.0, g * factor)
                                             for g in self.search_gates_px),
                       search_step_px=max(2.0, self.search_step_px * factor),
                       corner_trim_px=max(4.0, self.corner_trim_px * factor),
                       max_outward_shift_px=self.max_outward_shift_px * factor)


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
    segmentation : "contour" (the paper's segmentation gave the 20 segments), "model" (the
        fallback: lines from the holder model fitted to the contour, then refined), "field"
        (the field chain's robust line fits) or "outline" (the field chain stopped at the
        pocket outline, ``detect_features(..., corners=False)``: no corners or lines seen).
    edge_darkening : (N,) per line, how much darker the face is just outside the edge than
        farther out, as a fraction of the edge contrast (:func:`edge_wear`; ~0 for a clean
        edge, 0.3-0.4 for a worn one). None without refinement.
    edge_offset_px : (N,) per line, how far (px) the edge estimate may lie outside the true edge
        because of that darkening (:func:`edge_wear`).
    inward_ideal : (N, 2) unit normals of the lines towards the pocket (ideal px).
    visible : (N,) bool, the corners that were seen (both their lines seen); the others are NaN
        in ``corners_px`` / ``corners_ideal_px``. All True on the paper's chain.
    order : "contour" (corners in contour order: unknown start and direction; paper chain) or
        "holder" (``corners_px[i]`` is the image of ``holder.json`` corner ``i``; field chain).
    lines_visible : (N,) bool, the lines that were seen (``lines_ideal`` NaN for the others).
    H_ideal_holder : (3, 3) homography holder plane (mm) -> ideal px of the outline fit (field
        chain), else None.
    image : the grey image the features come from (a reference, not a copy): ``dm+b`` samples
        the band across the edges in it.
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
    visible: np.ndarray | None = None
    order: str = "contour"
    lines_visible: np.ndarray | None = None
    H_ideal_holder: np.ndarray | None = None
    image: np.ndarray | None = field(default=None, repr=False)

    def __post_init__(self):
        if self.visible is None:
            self.visible = np.isfinite(np.asarray(self.corners_px, float)).all(axis=1)
        if self.lines_visible is None:
            self.lines_visible = np.isfinite(np.asarray(self.lines_ideal, float)).all(axis=1)

    @property
    def visible_corners_px(self) -> np.ndarray:
        """(n, 2) the seen corners only, observed px (in ``order``, the others left out)."""
        return np.asarray(self.corners_px, float)[self.visible]


def signed_area(p: np.ndarray) -> float:
    x, y = p[:, 0], p[:, 1]
    return 0.5 * float(np.dot(x, np.roll(y, -1)) - np.dot(np.roll(x, -1), y))


def where_px(p) -> str:
    return f"({p[0]:.0f}, {p[1]:.0f})"
