"""From one image to a checked pose: :func:`measure`.

Image processing (:mod:`cutterpose.image.features`, paper section 2.1) gives the 20 corners in
contour order; a pose method (:mod:`cutterpose.methods`) turns them into a pose; the residuals
give the pose's per-DOF standard deviations and a quality verdict that refuses, with the reason,
a pose that should not be used.

Correspondences for the PnP methods ("contour order"): the contour gives the corners in order up
to a cyclic shift and a direction. The direction is fixed by the sign of the polygon's area
(the holder is always seen from its front, so the image polygon turns the same way as the model
projected at the nominal pose), the shift by comparing the corner-to-corner vectors, normalised
by the perimeter, with those of the model at the nominal pose: within the working range
(+-10 deg, holder X axis along the image rows) this separates the holder's 180 deg symmetric
assignments, and the edge lengths separate the others. The correspondence-free methods
(``initial``, ``dm``, ``dm+``) get the contour order as it is.

Per-DOF standard deviation (Gauss-Newton covariance at the estimate): with ``r`` the 40 residuals
(detected minus projected ideal pixels, corners matched by the best cyclic assignment) and ``J``
their Jacobian with respect to ``(alpha, beta, gamma, X, Y, Z)``,

    s^2 = |r|^2 / (40 - 6),        Cov = s^2 (J^T J)^-1,        std = sqrt(diag Cov).

The default method is ``dm+b`` (:mod:`cutterpose.solvers.edge_band`): the pocket outline's pose
for the start on the field chain (no corners needed; the corners' ``dm+`` pose when the band
finds nothing from there, and on the paper's chain), then the band across every broken pocket
edge fitted with the edge model
(:mod:`cutterpose.image.edge_band`), so that the pose is that of the design edge on field
holders. ``dm+r`` (:mod:`cutterpose.solvers.edge_radius`) fits one radius from the corners
alone. The verdict is an error budget (:mod:`cutterpose.budget`): noise, edge model and model
floor for ``dm+b``; noise, radius, edge model and edge variation for ``dm+r`` (the std above,
the edge-wear shift and the edge break they cannot measure for the other methods),
propagated to the position of a grasp point and to the rotation; a pose is refused when its
3-sigma figures exceed the tolerance (1 mm, 0.3 deg), with the reason. The camera-frame 6 x 6
covariance is ``Measurement.covariance_cam`` (order :data:`cutterpose.budget.COVARIANCE_CAM_ORDER`).

Convention:
    Pose as in :mod:`cutterpose.geometry.pose` (holder in camera frame, mm, Z-Y-X Euler angles in
    deg).
    Pixels: ``corners_px`` are observed (distorted) image pixels; residuals are in ideal pixels.
"""

from __future__ import annotations

import json
import math
import numbers
import time
from dataclasses import dataclass, field, replace
from pathlib import Path

import numpy as np

from .budget import ErrorBudget, Tolerance, budget_from_dof_cov, budget_from_fit
from .errors import CutterposeError, FeatureError, ImageError, InputError
from .frames import load_frame
from .geometry.camera import Camera, default_camera
from .geometry.holder import Holder, default_holder
from .geometry.pose import (
    Pose,
    pixel_jacobian,
    pose_from_plane_homography,
    rotation_from_euler_deg,
    wrap_deg,
)
from .geometry.working_range import MotionRange
from .image import FeatureParams, Features, detect_features
from .methods import get_method
from .solvers.estimate import PoseEstimate

__all__ = ["QualityLimits", "Quality", "Measurement", "measure", "measure_features",
           "order_for_model", "pose_std", "demo", "DOF_NAMES", "edge_wear_effect",
           "band_budget", "band_verdict", "edge_break_effect", "UNKNOWN_EDGE_BREAK_MM",
           "fit_offset", "NOMINAL_DISTANCE_MM", "station_center_dof", "station_params"]

#: the paper's measuring station: the camera 600 mm from the holder's top face
NOMINAL_DISTANCE_MM = 600.0


#: the pocket edge's break shapes a holder's drawing may give (QualityLimits.edge_shape)
EDGE_SHAPES = ("round", "chamfer", "unknown")
#: the shapes the band / radius fit tries for each of them
EDGE_SHAPE_FITS = {"unknown": ("round", "chamfer"), "round": ("round",), "chamfer": ("chamfer",)}
#: the pocket edge's largest break (mm) the corner methods' verdict assumes when the holder's is
#: not given (``QualityLimits.edge_break_mm = None``): a new holder's machined edge break is
#: 0.5-1.5 mm (issue 10), and a worn one's more (the darkening indicator's ``wear`` part)
UNKNOWN_EDGE_BREAK_MM = 1.5

DOF_NAMES = ("alpha_deg", "beta_deg", "gamma_deg", "X_mm", "Y_mm", "Z_mm")


@dataclass(frozen=True)
class QualityLimits:
    """When :func:`measure` refuses a pose.

    The working range is the real rig's (paper section 3.2): +-10 deg and +-20 mm around the
    nominal pose, accepted with a tolerance.
    """

    max_rms_px: float = 1.5            #: RMS corner residual (ideal px)
    max_corner_residual_px: float = 4.0
    max_ambiguity_ratio: float = 0.8   #: best / second-best candidate error
    range_center_dof: tuple = (0.0, 0.0, 0.0, 0.0, 0.0, NOMINAL_DISTANCE_MM)
    range_half_width_dof: tuple = (10.0, 10.0, 10.0, 20.0, 20.0, 20.0)
    range_tolerance_dof: tuple = (2.0, 2.0, 2.0, 5.0, 5.0, 5.0)
    max_std_dof: tuple = (0.5, 0.5, 0.5, 2.0, 2.0, 2.0)
    #: unused since the error budget (kept for callers that set it)
    max_edge_bias_dof: tuple = (0.2, 0.2, 0.2, 0.5, 0.5, 0.5)
    #: the error budget's tolerance (3 sigma: 1 mm at the grasp point, 0.3 deg)
    tolerance: Tolerance = Tolerance()
    #: the point (holder frame, mm) whose position the budget checks: the origin, the centre of
    #: the pocket's top plane (a holder file's grasp frame may be given instead)
    grasp_point_mm: tuple = (0.0, 0.0, 0.0)
    #: the pocket edge's break as the holder's drawing gives it: "round" or "chamfer" (only that
    #: shape is fitted), or "unknown" (default: both; ``dm+b`` tells them apart from the band's
    #: profile; ``dm+r``, from the corners alone, cannot, and its budget then carries a
    #: chamfer's unseen depth, refusing nearly every pose: docs/RESULTS.md section 11)
    edge_shape: str = "unknown"
    #: the largest break (mm, fillet radius or chamfer leg) the pocket edge may have, for the
    #: methods that see only the edge's image, not the design edge (``dm``, ``dm+``, PnP): their
    #: budget carries the pose shift of the seen edge lying anywhere between the design edge and
    #: this far outside it (:func:`edge_break_effect`). ``None``: not known, 1.5 mm
    #: (:data:`UNKNOWN_EDGE_BREAK_MM`); ``0``: a sharp edge (a lab holder, the analytic
    #: renderer's default). ``dm+b`` and ``dm+r`` measure the break and ignore it.
    edge_break_mm: float | None = None

    def __post_init__(self):
        if self.edge_shape not in EDGE_SHAPES:
            raise InputError(f"edge_shape must be one of {', '.join(EDGE_SHAPES)}, got "
                             f"{self.edge_shape!r}")
        b = self.edge_break_mm
        if b is not None and (isinstance(b, bool) or not isinstance(b, numbers.Real)
                              or not 0 <= b < math.inf):
            raise InputError(f"edge_break_mm must be a finite number >= 0 or None, got {b!r}")

    @property
    def assumed_edge_break_mm(self) -> float:
        """The break the corner methods' budget carries (:attr:`edge_break_mm` or, not given,
        :data:`UNKNOWN_EDGE_BREAK_MM`)."""
        return UNKNOWN_EDGE_BREAK_MM if self.edge_break_mm is None else float(self.edge_break_mm)


def _distance(distance_mm) -> float:
    z = NOMINAL_DISTANCE_MM if distance_mm is None else distance_mm
    if isinstance(z, bool) or not isinstance(z, numbers.Real) or not (math.isfinite(z) and z > 0):
        raise InputError(f"the station distance must be a positive number of mm, got "
                         f"{distance_mm!r}")
    return float(z)


def station_center_dof(distance_mm: float | None = None) -> tuple:
    """The working range's centre for a measuring station ``distance_mm`` from the holder
    (the holder square to the camera, on its axis): ``(0, 0, 0, 0, 0, distance_mm)``."""
    return (0.0, 0.0, 0.0, 0.0, 0.0, _distance(distance_mm))


def station_params(camera: Camera, chain: str = "field",
                   distance_mm: float | None = None) -> FeatureParams:
    """The image stage's parameters for ``camera`` at a measuring station ``distance_mm`` from
    the holder (None: the paper's 600 mm): the region search's outline templates at that
    depth (``FeatureParams.roi_depths_mm``), the rest scaled to the focal length."""
    if distance_mm is None:
        return FeatureParams.for_camera(camera, chain=chain)
    return FeatureParams.for_camera(camera, chain=chain, roi_depths_mm=(_distance(distance_mm),))


@dataclass
class Quality:
    """The verdict: ``ok`` or the reason for refusing."""

    ok: bool
    reason: str = ""
    rms_px: float = math.nan
    ambiguity_ratio: float = math.nan
    #: (6,) pose shift if every edge moved inwards by its possible wear offset (deg, mm)
    edge_bias_dof: np.ndarray | None = None
    edge_offset_px: float = math.nan   #: median possible outward offset of the edges
    note: str = ""                     #: a warning that does not refuse the pose
    budget: ErrorBudget | None = None  #: the error budget (None without a pose)

    def to_dict(self) -> dict:
        return {"ok": self.ok, "reason": self.reason, "rms_residual_px": _f(self.rms_px),
                "ambiguity_ratio": _f(self.ambiguity_ratio), "note": self.note,
                "edge_offset_px": _f(self.edge_offset_px),
                "edge_bias": None if self.edge_bias_dof is None else
                {k: _f(v) for k, v in zip(DOF_NAMES, self.edge_bias_dof)},
                "budget": None if self.budget is None else self.budget.to_dict()}


@dataclass
class Measurement:
    """Result of :func:`measure`.

    Attributes
    ----------
    method : the pose method.
    pose : the estimated pose (None when there is none; check ``quality.ok`` before use).
    std_dof : (6,) standard deviations of alpha, beta, gamma [deg], X, Y, Z [mm].
    quality : the verdict.
    corners_px : (n, 2) the detected corners that were seen, observed pixels (None if not found):
        the 20 in contour order (paper chain), or the seen ones in model order (field chain;
        ``features.visible`` says which).
    features : everything the image processing found (None if it failed).
    estimate : the method's raw answer.
    timings_ms : wall time per stage.
    """

    method: str
    pose: Pose | None
    std_dof: np.ndarray
    quality: Quality
    corners_px: np.ndarray | None = None
    features: Features | None = None
    estimate: PoseEstimate | None = None
    timings_ms: dict = field(default_factory=dict)
    #: the base-frame answer (:class:`cutterpose.robot.RobotResult`) when :func:`measure` got a
    #: hand-eye file and a flange pose
    robot: object | None = None

    @property
    def ok(self) -> bool:
        return self.quality.ok

    @property
    def covariance_cam(self) -> np.ndarray | None:
        """(6, 6) covariance of the camera-frame pose, order
        :data:`cutterpose.budget.COVARIANCE_CAM_ORDER` (``x, y, z`` [mm] of ``t_cam_holder``,
        ``rx, ry, rz`` [rad] about the holder's own axes); None without a pose."""
        b = self.quality.budget
        return None if b is None else b.covariance_cam

    @property
    def edge_radius_mm(self) -> float:
        """The estimated radius of the pocket edge's break (``dm+r``, ``dm+b``: the median over
        the edge segments; NaN otherwise)."""
        b = self.quality.budget
        return math.nan if b is None else b.radius_mm

    @property
    def edge_band(self):
        """``dm+b``'s band fit (:class:`~cutterpose.solvers.edge_band.BandPose`), else None."""
        return None if self.estimate is None else self.estimate.info.get("band")

    def pose_lines(self) -> list[str]:
        """The pose with its std and the residual as three short lines (CLI and overlay)."""
        if self.pose is None:
            return []
        a, b, g, x, y, z = self.pose.dof
        s = self.std_dof
        lines = [f"alpha {a:7.3f}  beta {b:7.3f}  gamma {g:7.3f} deg   "
                 f"(std {s[0]:.3f} {s[1]:.3f} {s[2]:.3f})",
                 f"X {x:8.2f}  Y {y:8.2f}  Z {z:8.2f} mm   (std {s[3]:.3f} {s[4]:.3f} {s[5]:.3f})",
                 f"RMS residual {self.quality.rms_px:.3f} px"]
        band = self.edge_band
        if band is not None:
            d = band.to_dict()
            lines.append(f"edge break: {d['shape']}, radius {d['radius_median_mm']:.2f} mm "
                         f"(median of {d['segments_valid']} segments, {d['segments_used']} "
                         "used for the pose); residual along the normals "
                         f"{d['residual_within_edge_px']:.2f} px within an edge, "
                         f"{d['residual_shared_per_edge_px']:.2f} px shared per edge")
            if band.calibration_covers is False:
                lines.append("edge look: calibrated in the cell on other distances, breaks or "
                             "shapes than this one: the budget keeps the generic model floor "
                             "and counts the calibration's correction as uncertain")
        return lines

    def to_dict(self) -> dict:
        """The JSON object of ``cutterpose measure --json``."""
        d = {"method": self.method, "quality": self.quality.to_dict(),
             "pose": self.pose.to_dict() | {"frames": {"to": self.pose.to_frame,
                                                        "from": self.pose.from_frame}}
             if self.pose is not None else None,
             "std": {k: _f(v) for k, v in zip(DOF_NAMES, self.std_dof)},
             "corners_px": None if self.corners_px is None else self.corners_px.tolist(),
             "timings_ms": {k: round(float(v), 3) for k, v in self.timings_ms.items()}}
        if self.features is not None:
            f = self.features
            d["features"] = {"roi_px": list(f.roi), "roi_score": round(f.roi_score, 4),
                             "threshold": f.threshold, "refined": f.refined,
                             "n_segments": len(f.segments), "segmentation": f.segmentation,
                             "order": f.order, "visible": np.asarray(f.visible).tolist()}
        band = self.edge_band
        if band is not None:
            d["edge_band"] = band.to_dict()
        if self.robot is not None:
            d.update(self.robot.to_dict())
        return d


def _f(x):
    return None if x is None or not math.isfinite(float(x)) else float(x)


# ------------------------------------------------------------------------------------------
def order_for_model(corners_px: np.ndarray, camera: Camera, holder: Holder) -> np.ndarray:
    """Reorder corners from contour order (unknown start and direction) to ``holder.json``
    order, from the image alone (module doc).

    Returns
    -------
    (N, 2) the same corners, ``out[i]`` the image of model corner ``i``.
    """
    c = np.asarray(corners_px, float)
    nominal = camera.project(Pose.nominal().apply(holder.points_holder_mm))

    def area(p):
        return np.dot(p[:, 0], np.roll(p[:, 1], -1)) - np.dot(np.roll(p[:, 0], -1), p[:, 1])

    if np.sign(area(c)) != np.sign(area(nominal)):
        c = c[::-1]
    e_det = np.roll(c, -1, axis=0) - c
    e_nom = np.roll(nominal, -1, axis=0) - nominal
    e_det = e_det / np.linalg.norm(e_det, axis=1).sum()
    e_nom = e_nom / np.linalg.norm(e_nom, axis=1).sum()
    n = len(c)
    cost = [np.sum((np.roll(e_det, -k, axis=0) - e_nom) ** 2) for k in range(n)]
    return np.roll(c, -int(np.argmin(cost)), axis=0)


def _match_to_projection(ideal: np.ndarray, proj: np.ndarray,
                         order: str = "contour") -> np.ndarray:
    """Detected ideal corners reordered (cyclic shift and direction) to best fit ``proj``.
    In ``"holder"`` order (field chain: known correspondences, NaN rows for the corners not
    seen) they are returned as they are."""
    if order == "holder":
        return np.asarray(ideal, float)
    best, best_cost = ideal, np.inf
    for seq in (ideal, ideal[::-1]):
        for k in range(len(seq)):
            cand = np.roll(seq, -k, axis=0)
            cost = np.sum((cand - proj) ** 2)
            if cost < best_cost:
                best, best_cost = cand, cost
    return best


def _project_ideal(dof: np.ndarray, camera: Camera, holder: Holder) -> np.ndarray:
    R = rotation_from_euler_deg(*dof[:3])
    X = holder.points_holder_mm @ R.T + dof[3:]
    x = X[:, :2] / X[:, 2:3]
    K = camera.K
    return x @ K[:2, :2].T + K[:2, 2]


def _jacobian(pose: Pose, camera: Camera, holder: Holder) -> np.ndarray:
    """(2N, 6) Jacobian of the ideal pixels w.r.t. the DOFs (analytic, :func:`pixel_jacobian`)."""
    return pixel_jacobian(pose.R, pose.t_mm, holder.points_holder_mm, camera.K)[0]


def edge_wear_effect(pose: Pose, features: Features, camera: Camera, holder: Holder
                     ) -> tuple[np.ndarray, float]:
    """Pose shift (6,) if every line moved inwards by the median of the lines' possible wear
    offsets (``features.edge_offset_px``), linearised at ``pose``; and that offset (px).

    The residuals cannot show this: a uniform offset of the edges is close to a change of scale
    (depth), so the shift is a systematic error the residual-based std misses.
    """
    off = features.edge_offset_px
    if off is None or features.inward_ideal is None or not np.any(np.isfinite(off)):
        return np.zeros(6), 0.0
    # wear acts on the whole outline: the median offset, moved uniformly (one line darkened by
    # an occluder or a stain beside it is not wear, and the corner checks see local defects)
    off = np.full(len(off), float(np.nanmedian(off)))
    from .image.edges import intersect_consecutive

    L = np.array(features.lines_ideal, float)
    # moving the line by off along the inward normal n: c' = c - off (a, b) . n
    L[:, 2] -= off * (L[:, :2] * features.inward_ideal).sum(axis=1)
    moved = intersect_consecutive(L)
    if features.order == "holder":  # corner i: lines i - 1 and i (NaN where not seen)
        moved = np.roll(moved, 1, axis=0)
    elif not np.all(np.isfinite(moved)):
        return np.full(6, np.nan), float(np.median(off))
    dof = pose.dof
    proj = _project_ideal(dof, camera, holder)
    J = _jacobian(pose, camera, holder)
    a = _match_to_projection(np.asarray(features.corners_ideal_px, float), proj, features.order)
    b = _match_to_projection(moved, proj, features.order)
    seen = np.repeat(np.isfinite(a).all(axis=1) & np.isfinite(b).all(axis=1), 2)
    shift = np.linalg.lstsq(J[seen], (b - a).ravel()[seen], rcond=None)[0]
    return np.abs(shift), float(np.median(off))


def edge_break_effect(pose: Pose, camera: Camera, holder: Holder, seen: np.ndarray,
                      offset_mm: float, J: np.ndarray | None = None) -> np.ndarray:
    """Signed pose shift (6,: deg, mm) of a corner method's fit when every pocket edge is seen
    ``offset_mm`` outside the design edge, linearised at ``pose`` over the ``seen`` corners.

    A broken edge (fillet or chamfer of size ``b``) images its intensity step somewhere
    between the design edge and the break's line on the face, ``b`` outside it, depending on
    the light and the view (issue 10): the corners of the seen lines are the design corners
    moved by ``offset (o_(i-1) + o_i)`` (:func:`cutterpose.image.edge_model.model_corners_mm`).
    A uniform offset is nearly a change of scale: at 600 mm, 1 mm moves the depth by ~4.5 mm,
    and at a 10 deg tilt the tilt by ~0.7 deg (``docs/RESULTS.md``, section 11). ``J``: the
    (2N, 6) :func:`_jacobian` at ``pose`` when already computed.
    """
    from .image.edge_model import model_corners_mm

    dof = pose.dof
    seen = np.asarray(seen, bool)
    o_edge = holder.edge_normals
    outward = np.stack([np.roll(o_edge, 1, axis=0), o_edge], axis=1)
    moved = model_corners_mm(holder, np.full((holder.n_corners, 2), float(offset_mm)), outward)
    X = moved @ pose.R.T + pose.t_mm
    b = X[:, :2] / X[:, 2:3] @ camera.K[:2, :2].T + camera.K[:2, 2]
    a = _project_ideal(dof, camera, holder)
    J = _jacobian(pose, camera, holder) if J is None else J
    rows = np.repeat(seen, 2)
    return np.linalg.lstsq(J[rows], (b - a).ravel()[rows], rcond=None)[0]


def _corner_fit(pose: Pose, corners_ideal_px: np.ndarray, camera: Camera, holder: Holder,
                order: str = "contour") -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The corners against the model at ``pose``: which are seen (N,), the (2N, 6)
    :func:`_jacobian` of all of them, and the seen ones' residuals (n, 2: detected minus
    projected ideal px, model order)."""
    proj = _project_ideal(pose.dof, camera, holder)
    det = _match_to_projection(np.asarray(corners_ideal_px, float), proj, order)
    seen = np.isfinite(det).all(axis=1)
    return seen, _jacobian(pose, camera, holder), (det - proj)[seen]


def _least_squares_step(J_seen: np.ndarray, r: np.ndarray) -> np.ndarray:
    """(6,) Gauss-Newton step ``(J^T J)^-1 J^T r`` (NaN with fewer than 4 corners)."""
    if len(r) < 4:
        return np.full(6, np.nan)
    return np.linalg.lstsq(J_seen, r.ravel(), rcond=None)[0]


def fit_offset(pose: Pose, corners_ideal_px: np.ndarray, camera: Camera, holder: Holder,
               order: str = "contour") -> np.ndarray:
    """(6,) DOF step (deg, mm) from ``pose`` to the least-squares pose of the seen corners: one
    Gauss-Newton step, ``(J^T J)^-1 J^T r`` with ``r`` the residuals (detected minus
    projected ideal px). Near zero for a pose that minimises them (``dm+``, PnP + LM); NaN
    with fewer than 4 corners."""
    seen, J, r = _corner_fit(pose, corners_ideal_px, camera, holder, order)
    return _least_squares_step(J[np.repeat(seen, 2)], r)


def _noise_cov(J_seen: np.ndarray, r: np.ndarray) -> np.ndarray:
    """(6, 6) ``s^2 (J^T J)^-1`` (module doc), NaN when ``J`` is singular."""
    s2 = float(np.sum(r ** 2)) / max(r.size - 6, 1)
    try:
        return s2 * np.linalg.inv(J_seen.T @ J_seen)
    except np.linalg.LinAlgError:
        return np.full((6, 6), np.nan)


def _pose_cov(pose: Pose, corners_ideal_px: np.ndarray, camera: Camera, holder: Holder,
              order: str = "contour") -> tuple[np.ndarray, np.ndarray]:
    """(6, 6) ``s^2 (J^T J)^-1`` over the seen corners (module doc) and the residuals."""
    seen, J, r = _corner_fit(pose, corners_ideal_px, camera, holder, order)
    return _noise_cov(J[np.repeat(seen, 2)], r), r


def pose_std(pose: Pose, corners_ideal_px: np.ndarray, camera: Camera, holder: Holder,
             order: str = "contour") -> tuple[np.ndarray, np.ndarray]:
    """Per-DOF standard deviations from the residuals, ``s^2 (J^T J)^-1`` (module doc).

    ``order="holder"``: corners in model order, NaN rows (not seen) left out.

    Returns
    -------
    std : (6,) deg and mm.
    residuals : (n, 2) detected minus projected ideal pixels, model order (seen corners).
    """
    cov, r = _pose_cov(pose, corners_ideal_px, camera, holder, order)
    return np.sqrt(np.clip(np.diag(cov), 0, None)), r


def _solve(method: str, corners_px: np.ndarray, camera: Camera, holder: Holder,
           limits: QualityLimits, order: str = "contour", H=None) -> PoseEstimate:
    """``corners_px``: all 20 in contour order, or (``order="holder"``, field chain) 20 in model
    order with NaN rows for the corners not seen: PnP methods get the seen ones with their
    model points; the range-searching methods (:class:`~cutterpose.methods.Method`,
    ``searches_range``: ``dm``, ``dm+``, ``dm-paper``) the seen ones, unordered, with the
    rig's working range and, on the field chain, the pose of the outline homography ``H`` as
    their start."""
    m = get_method(method)
    if m.base is not None:
        raise InputError(f"{method} refines {m.base}'s pose with more than the corners: "
                         "use measure_features")
    corners_px = np.asarray(corners_px, float)
    seen = np.isfinite(corners_px).all(axis=1)
    if m.searches_range:
        rng = MotionRange(center_dof=limits.range_center_dof,
                          half_width_dof=limits.range_half_width_dof)
        field = order == "holder"
        start = pose_from_plane_homography(H, camera.K) if field and H is not None else None
        return m.solve(corners_px[seen] if field else corners_px, camera, holder,
                       motion_range=rng, start=start, partial=field and not seen.all(),
                       close_start_rms_px=limits.max_rms_px if field else None)
    if order == "holder" and not seen.all():
        if m.needs_correspondences:
            return m.solve(corners_px[seen], camera, holder.points_holder_mm[seen])
        return PoseEstimate.failure(method, f"needs all {holder.n_corners} corners, "
                                    f"{int(seen.sum())} seen")
    if m.needs_correspondences:
        if order == "holder":
            return m.solve(corners_px, camera, holder)
        return m.solve(order_for_model(corners_px, camera, holder), camera, holder)
    return m.solve(corners_px, camera, holder)


def outline_start(H_ideal_holder, camera: Camera, method: str = "outline"
                  ) -> PoseEstimate | None:
    """The pose of the pocket outline's homography (holder plane -> ideal px; Zhang's
    decomposition, :func:`~cutterpose.geometry.pose.pose_from_plane_homography`) as a start,
    or None when it is degenerate. Its residual is NaN: no corners were fitted."""
    rt = pose_from_plane_homography(H_ideal_holder, camera.K)
    if rt is None:
        return None
    return PoseEstimate(method, rt[0], np.asarray(rt[1], float), info={"from": "outline"})


def corner_residual_px(features: Features, camera: Camera, holder: Holder,
                       limits: QualityLimits | None = None) -> float:
    """RMS residual (ideal px) of ``dm+``'s pose fitted to the detected corners: how far the
    innermost rise the corners follow lies off the rigid model (NaN without a pose). The
    tracker holds its tracked edges to it."""
    if not _has_corners(features):
        return math.nan
    est = _solve("dm+", features.corners_px, camera, holder, limits or QualityLimits(),
                 features.order, features.H_ideal_holder)
    return float(est.residual_px) if est else math.nan


def _refine(method: str, features: Features, camera: Camera, holder: Holder,
            limits: QualityLimits, edge_look=None, outline_failed: str | None = None
            ) -> PoseEstimate:
    """A method that refines its base method's pose with more than the corners
    (``Method.refine``: ``dm+r`` the edge radius, ``dm+b`` the bands in the image). A
    calibrated ``edge_look`` goes to a refinement that takes one (``dm+b``); the others ignore
    it.

    A method that starts from the outline (``Method.start_from_outline``, field chain) falls
    back to the corners' pose when the refinement from the outline gives no pose: the outline's
    homography can be bent by what lies on a worn edge (a held-back worn image: its corners up
    to 21 px off, the band found on 9 of 40 segments). Without corners in ``features`` the
    failure is returned; :func:`measure` then detects them and calls again with
    ``outline_failed`` (the first attempt's reason, so that it is not repeated)."""
    m = get_method(method)
    kw = {}
    if edge_look is not None and m.takes_edge_look:
        kw["edge_look"] = edge_look
    shapes = EDGE_SHAPE_FITS[limits.edge_shape]
    if (outline_failed is None and m.start_from_outline and features.order == "holder"
            and features.H_ideal_holder is not None):
        outline = outline_start(features.H_ideal_holder, camera)
        if outline is not None:
            est = m.refine(outline, features, camera, holder, shapes, **kw)
            if est or not _has_corners(features):
                return est
            outline_failed = est.reason
    start = _solve(m.base, features.corners_px, camera, holder, limits, features.order,
                   features.H_ideal_holder)
    est = m.refine(start, features, camera, holder, shapes, **kw)
    if outline_failed is not None:
        est.info["outline_start_failed"] = outline_failed
    return est


def _has_corners(features: Features) -> bool:
    return bool(np.isfinite(np.asarray(features.corners_px, float)).all(axis=1).any())


def ambiguity_ratio(est: PoseEstimate, corners_ideal_px, camera: Camera, holder: Holder,
                    min_rotation_deg: float = 1.0, order: str = "contour") -> float:
    """RMS residual of the best pose over that of the best *different* candidate (rotation
    at least ``min_rotation_deg`` away; the planar two-fold ambiguity); NaN without one."""
    from .geometry.pose import geodesic_deg

    if not est or not est.candidates:
        return math.nan
    R0 = est.R_cam_holder
    others = [(R, t) for R, t in est.candidates
              if geodesic_deg(R0, np.asarray(R, float)) > min_rotation_deg]
    if not others:
        return math.nan

    def rms(R, t):
        dof = Pose(np.asarray(R, float), np.asarray(t, float).reshape(3)).dof
        proj = _project_ideal(dof, camera, holder)
        det = _match_to_projection(np.asarray(corners_ideal_px, float), proj, order)
        return float(np.sqrt(np.nanmean(np.sum((det - proj) ** 2, axis=1))))

    e0 = rms(R0, est.t_cam_holder_mm)
    e1 = min(rms(R, t) for R, t in others)
    return e0 / e1 if e1 > 0 else 1.0


def _bias_text(bias) -> str:
    return ", ".join(f"{n} {b:.2f} {'deg' if k < 3 else 'mm'}"
                     for k, (n, b) in enumerate(zip(DOF_NAMES, bias)))


def _verdict(est: PoseEstimate, std, r, limits: QualityLimits, amb: float = math.nan,
             bias=None, offset_px: float = math.nan, budget: ErrorBudget | None = None
             ) -> Quality:
    if est is None or not est:
        return Quality(False, f"no pose: {est.reason if est is not None else 'not solved'}",
                       ambiguity_ratio=amb)
    rms = float(np.sqrt(np.mean(np.sum(r ** 2, axis=1))))
    q = Quality(True, "", rms, amb, bias, offset_px, budget=budget)
    if bias is not None and np.all(np.isfinite(bias)) and offset_px > 0.1:
        q.note = (f"edges worn: contour position uncertain by ~{offset_px:.1f} px, pose may be "
                  f"biased by {_bias_text(bias)} (in the error budget)")
    dof = Pose(est.R_cam_holder, est.t_cam_holder_mm).dof
    lo = np.subtract(limits.range_center_dof, limits.range_half_width_dof)
    hi = np.add(limits.range_center_dof, limits.range_half_width_dof)
    tol = np.asarray(limits.range_tolerance_dof)
    out = (dof < lo - tol) | (dof > hi + tol)
    worst = float(np.sqrt(np.sum(r ** 2, axis=1)).max())
    if rms > limits.max_rms_px:
        q.ok, q.reason = False, (f"corner residual RMS {rms:.2f} px > {limits.max_rms_px} px: "
                                 "the corners do not fit the holder model")
    elif worst > limits.max_corner_residual_px:
        q.ok, q.reason = False, (f"a corner is {worst:.2f} px off the model (> "
                                 f"{limits.max_corner_residual_px} px)")
    elif out.any():
        names = [f"{DOF_NAMES[k]}={dof[k]:.1f}" for k in np.nonzero(out)[0]]
        q.ok, q.reason = False, f"pose outside the working range: {', '.join(names)}"
    elif math.isfinite(amb) and amb > limits.max_ambiguity_ratio:
        q.ok, q.reason = False, (f"planar ambiguity: a second pose fits almost as well (ratio "
                                 f"{amb:.2f} > {limits.max_ambiguity_ratio})")
    elif not np.all(np.isfinite(std)) or np.any(std > np.asarray(limits.max_std_dof)):
        q.ok, q.reason = False, f"pose too uncertain: std {np.round(std, 3).tolist()}"
    elif budget is not None and (why := budget.exceeds(limits.tolerance)):
        q.ok, q.reason = False, why
    return q


def band_budget(band, dof, limits: QualityLimits) -> tuple[ErrorBudget, np.ndarray]:
    """``dm+b``'s error budget at ``dof`` (its covariance parts,
    :class:`~cutterpose.solvers.edge_band.BandPose`) and its residuals: (M, 2) vectors (ideal
    px) along the edge normals of the inlier segments (dm+b has no corner residuals)."""
    budget = budget_from_dof_cov(band.cov_parts, dof, limits.grasp_point_mm, limits.tolerance,
                                 band.radius_mm)
    inl = band.weights > 0.5
    return budget, band.residuals_px[inl, None] * band.fit.profiles.normals_ideal[inl]


def band_verdict(est: PoseEstimate, limits: QualityLimits) -> Quality:
    """The verdict on a ``dm+b`` estimate made without image features (the tracker's
    re-anchoring: :func:`~cutterpose.solvers.edge_band.measure_band` from a tracked pose): its
    residuals, working range and error budget, as in :func:`measure_features`."""
    if not est:
        return _verdict(est, np.full(6, np.nan), np.zeros((0, 2)), limits)
    if est.info.get("band") is None:
        return Quality(False, f"{est.method} carries no band fit to judge")
    budget, r = band_budget(est.info["band"], Pose(est.R_cam_holder, est.t_cam_holder_mm).dof,
                            limits)
    return _verdict(est, budget.std_dof, r, limits, budget=budget)


def measure_features(features: Features, camera: Camera, holder: Holder, method: str = "dm+b",
                     limits: QualityLimits | None = None, edge_look=None, *,
                     outline_failed: str | None = None) -> Measurement:
    """Pose, std and verdict from already detected features (one image, several methods).
    ``edge_look``: the edge look calibrated in the cell
    (:class:`cutterpose.calibration.edge_look.EdgeLookCalibration`; ``dm+b`` only).
    ``outline_failed``: the reason a refinement from the outline's pose already failed on
    this image (:func:`_refine`): it starts from the corners' pose directly."""
    limits = limits or QualityLimits()
    timings = dict(features.timings_ms)
    t0 = time.perf_counter()
    try:
        if get_method(method).base is not None:
            est = _refine(method, features, camera, holder, limits, edge_look, outline_failed)
        else:
            est = _solve(method, features.corners_px, camera, holder, limits, features.order,
                         features.H_ideal_holder)
    except CutterposeError as e:
        est = PoseEstimate.failure(method, f"{type(e).__name__}: {e}")
    timings["solve"] = (time.perf_counter() - t0) * 1e3
    t0 = time.perf_counter()
    std = np.full(6, np.nan)
    r = np.zeros((0, 2))
    pose = None
    budget = None
    if est:
        pose = Pose(est.R_cam_holder, est.t_cam_holder_mm)
        bias, offset_px = edge_wear_effect(pose, features, camera, holder)
        fit = est.info.get("radius_fit")
        band = est.info.get("band")
        if band is not None:
            budget, r = band_budget(band, pose.dof, limits)
        elif fit is not None:
            # dm+r: the model corners of the broken edge give the residuals and the budget
            r = fit.residuals_px
            budget = budget_from_fit(fit, camera, holder, limits.grasp_point_mm,
                                     limits.tolerance)
        else:
            seen, J_all, r = _corner_fit(pose, features.corners_ideal_px, camera, holder,
                                         features.order)
            J_seen = J_all[np.repeat(seen, 2)]
            cov = _noise_cov(J_seen, r)
            parts = {"noise": np.where(np.isfinite(cov), cov, np.inf)}
            off_fit = _least_squares_step(J_seen, r)              # fit_offset
            if np.all(np.isfinite(off_fit)):
                # a method that does not minimise the corners' residuals (dm's search, the
                # linear PnP) is off their least-squares pose by more than the noise: that
                # step d is an error of its own (~0 for dm+ and the +lm methods). As 1 sigma
                # of 2/3 d, the 3-sigma figure sqrt(9 s^2 + 4 d^2) is at least |d| + 3 s
                # whenever |d| >= 2 s (s the noise's sigma), and within 10 % of it below
                parts["method"] = (4.0 / 9.0) * np.outer(off_fit, off_fit)
            if bias is not None and np.all(np.isfinite(bias)):
                # a systematic error the residuals do not show
                parts["wear"] = np.diag(bias ** 2)
            brk = limits.assumed_edge_break_mm
            if brk > 0:
                # the seen edge lies 0..brk outside the design edge, the pose bias with it:
                # a 1 sigma of brk / 3 makes the 3-sigma figure that whole range's shift (rank
                # one: the one offset moves every DOF)
                s = edge_break_effect(pose, camera, holder, seen, brk / 3.0, J_all)
                parts["edge break"] = np.outer(s, s)
            budget = budget_from_dof_cov(parts, pose.dof, limits.grasp_point_mm,
                                         limits.tolerance)
        std = budget.std_dof
    else:
        bias, offset_px = None, math.nan
    amb = ambiguity_ratio(est, features.corners_ideal_px, camera, holder,
                          order=features.order)
    q = _verdict(est, std, r, limits, amb, bias, offset_px, budget)
    brk = budget.per_part_3sigma.get("edge break") if budget is not None else None
    tol = limits.tolerance
    if not q.ok and brk is not None and (brk[0] > tol.position_mm or brk[1] > tol.angle_deg):
        # the break alone exceeds the tolerance: say what would make it measurable
        q.reason += (f" ({method} sees the broken edge, not the design edge: a break up to "
                     f"{limits.assumed_edge_break_mm:g} mm; dm+b measures it, or give the "
                     "holder's break, 0 for a sharp edge)")
    if (q.ok and pose is not None and get_method(method).base is None
            and features.order == "holder"):
        # the corners may fit a wrong pose when few are seen (dm/dm+ need no correspondences):
        # every seen edge, with or without its corners, must lie on the model at the pose.
        # A refining method's pose is the design edge's, which the seen (innermost) edges are
        # offset from by the break: its own residuals judge it (dm+r's model corners, dm+b's
        # band points)
        k, off = worst_line_residual(pose, features, camera, holder)
        if off > limits.max_corner_residual_px:
            q.ok, q.reason = False, (f"pocket edge {k} is {off:.1f} px off the model at this "
                                     f"pose (> {limits.max_corner_residual_px} px): the corners "
                                     "fit a wrong pose")
    timings["quality"] = (time.perf_counter() - t0) * 1e3
    return Measurement(method, pose, std, q, features.visible_corners_px, features, est, timings)


def worst_line_residual(pose: Pose, features: Features, camera: Camera, holder: Holder
                        ) -> tuple[int, float]:
    """The seen edge line (field chain, holder order) farthest from the model edge projected at
    ``pose``: its index and the larger distance (ideal px) of the model edge's two ends from
    the line; ``(-1, 0.0)`` without seen lines."""
    L = np.asarray(features.lines_ideal, float)
    seen = np.asarray(features.lines_visible, bool) & np.isfinite(L).all(axis=1)
    if not seen.any():
        return -1, 0.0
    q = _project_ideal(pose.dof, camera, holder)
    a, b = q, np.roll(q, -1, axis=0)                 # edge k runs from corner k to k + 1
    n = L[:, :2] / np.linalg.norm(L[:, :2], axis=1, keepdims=True)
    off = L[:, 2] / np.linalg.norm(L[:, :2], axis=1)
    d = np.maximum(np.abs(np.sum(n * a, axis=1) + off), np.abs(np.sum(n * b, axis=1) + off))
    d = np.where(seen, d, -np.inf)
    k = int(np.argmax(d))
    return k, float(d[k])


def measure(image, camera: Camera | None = None, holder: Holder | None = None,
            method: str = "dm+b", params: FeatureParams | None = None,
            limits: QualityLimits | None = None, grasp_point_mm=None, *, handeye=None,
            T_base_flange=None, robot_accuracy=None, edge_look=None,
            corners: bool | None = None) -> Measurement:
    """Measure the holder's pose in one image (and, given ``handeye`` and ``T_base_flange``,
    in the robot's base frame: :func:`cutterpose.robot.locate`, result in ``.robot``).

    Parameters
    ----------
    image : path of an image file or of a raw Mono8 frame (``.raw`` with its sidecar), a raw
        8-bit frame buffer of the camera's size (bytes, bytearray, memoryview: used in place,
        no decode), or a grey/colour array of the camera's size (:mod:`cutterpose.frames`).
    camera, holder : defaults: the Table 1 camera and ``holder.json``.
    method : a registered pose method (``dm+b`` by default: the design edge located in the
        bands across the broken pocket edge, from ``dm+``'s or the outline's start; the
        paper's method is ``dm`` / ``dm-paper`` with ``FeatureParams.paper()``).
    params : image processing parameters (default: the field chain,
        ``FeatureParams.for_camera(camera)``; ``FeatureParams.paper()`` for section 2.1's).
    limits : when to refuse a pose.
    grasp_point_mm : (3,) holder-frame point whose position the error budget checks (default
        ``limits.grasp_point_mm``, the origin: the centre of the pocket's top plane).
    handeye, T_base_flange, robot_accuracy : see :func:`cutterpose.robot.locate`.
    edge_look : the edge look calibrated in the cell on a reference holder
        (:func:`cutterpose.calibration.edge_look.load_edge_look`): ``dm+b`` fits it instead of
        its generic looks; other methods ignore it.
    corners : detect the corners on the field chain (default: when the method needs them;
        ``dm+b`` starts from the pocket outline and does not, so ``corners_px`` is empty; True
        to have them in the result anyway, at the line fits' cost, ~14 ms).

    Returns
    -------
    Measurement : never marked ok unless the verdict accepts it; a failure of the image
        processing (no holder, cut contour, wrong segment count...) gives ``ok = False`` with
        the reason and no pose.

    Raises
    ------
    ImageError
        The file is missing or not an image; the image has the wrong size, or is black,
        saturated or uniform.
    InputError
        Unknown method; a grasp point that is not 3 finite numbers.
    """
    camera = camera or default_camera("table1")
    holder = holder or default_holder()
    m_def = get_method(method)  # unknown names fail before any work
    if grasp_point_mm is not None:
        p = np.asarray(grasp_point_mm, float).reshape(-1)
        if p.shape != (3,) or not np.all(np.isfinite(p)):
            raise InputError(f"grasp_point_mm must be 3 finite numbers, got {grasp_point_mm!r}")
        limits = replace(limits or QualityLimits(), grasp_point_mm=tuple(p.tolist()))
    t0 = time.perf_counter()
    load_ms = 0.0
    if not isinstance(image, np.ndarray):
        # a file is decoded (or read raw); a raw buffer is only viewed (cutterpose.frames)
        image = load_frame(image, camera)
        load_ms = (time.perf_counter() - t0) * 1e3
    # a method that starts from the outline needs no corners on the field chain: the line fits
    # are skipped (a third of the image stage)
    if corners is None:
        corners = not m_def.start_from_outline
    try:
        feats = detect_features(image, camera, holder, params, corners=corners)
    except FeatureError as e:
        timings = {"load": load_ms} if load_ms else {}
        timings["total"] = (time.perf_counter() - t0) * 1e3
        return _with_robot(Measurement(method, None, np.full(6, np.nan), Quality(False, str(e)),
                                       timings_ms=timings),
                           camera, holder, handeye, T_base_flange, robot_accuracy)
    m = measure_features(feats, camera, holder, method, limits, edge_look)
    if (m.pose is None and feats.segmentation == "outline" and m.estimate is not None
            and not m.estimate):
        # the refinement found nothing from the outline's pose: the corners, and their pose
        # as the start (_refine); the first attempt's time stays in the total
        try:
            feats = detect_features(image, camera, holder, params, corners=True)
        except FeatureError:
            pass
        else:
            m = measure_features(feats, camera, holder, method, limits, edge_look,
                                 outline_failed=m.estimate.reason)
    if load_ms:
        m.timings_ms = {"load": load_ms} | m.timings_ms
    m.timings_ms["total"] = (time.perf_counter() - t0) * 1e3
    return _with_robot(m, camera, holder, handeye, T_base_flange, robot_accuracy)


def _with_robot(m: Measurement, camera, holder, handeye, T_base_flange, robot_accuracy):
    """Attach the base-frame answer when both a hand-eye file and a flange pose are given."""
    if handeye is None and T_base_flange is None:
        return m
    if handeye is None or T_base_flange is None:
        raise InputError("the base frame needs both a hand-eye file and a flange pose")
    from .robot.locate import locate

    m.robot = locate(m, handeye, T_base_flange, robot_accuracy, camera=camera, holder=holder)
    return m


def demo(out_dir, method: str = "dm+b", seed: int = 7, echo=print) -> Measurement:
    """The ``make demo`` example: render a seeded image of the holder (renderer, preset
    "easy", Table 1 camera), measure it, write ``demo.png``, ``demo_overlay.png`` and
    ``demo.json`` (with the true pose) into ``out_dir``, and report through ``echo`` (None:
    silent) the measured pose, its std, the true pose, the error and the time per stage."""
    import cv2

    from .overlay import write_overlay
    from .render.analytic import render_holder

    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    camera, holder = default_camera("table1"), default_holder()
    truth = Pose.from_euler(2.0, -3.0, 4.0, 8.0, -6.0, 612.0)
    r = render_holder(truth, camera, holder, "easy", seed=seed)
    if not cv2.imwrite(str(out / "demo.png"), r.image):
        raise ImageError(f"{out / 'demo.png'}: could not write the image")
    m = measure(out / "demo.png", camera, holder, method)
    write_overlay(r.image, m, camera, holder, out / "demo_overlay.png")
    d = m.to_dict()
    d["truth"] = truth.to_dict()
    (out / "demo.json").write_text(json.dumps(d, indent=1))
    if echo is not None:
        echo(_demo_report(m, truth, out))
    return m


def _demo_report(m: Measurement, truth: Pose, out: Path) -> str:
    names = ("alpha deg", "beta deg", "gamma deg", "X mm", "Y mm", "Z mm")
    lines = [f"demo image {out / 'demo.png'} (rendered, preset easy), method {m.method}: "
             + ("OK" if m.ok else f"REFUSED: {m.quality.reason}")]
    if m.pose is not None:
        est, tru = m.pose.dof, truth.dof
        err = est - tru
        err[:3] = wrap_deg(err[:3])
        lines.append(f"{'':10s} {'measured':>10s} {'std':>8s} {'true':>10s} {'error':>9s}")
        for k, n in enumerate(names):
            lines.append(f"{n:10s} {est[k]:10.4f} {m.std_dof[k]:8.4f} {tru[k]:10.4f} "
                         f"{err[k]:9.4f}")
        band = m.edge_band
        what = "edge-segment" if band is not None else "corner"
        lines.append(f"RMS {what} residual {m.quality.rms_px:.3f} px")
        if band is not None:
            lines.append(m.pose_lines()[-1])
    lines.append("time per stage (ms): " + ", ".join(
        f"{k} {v:.0f}" for k, v in m.timings_ms.items()))
    lines.append(f"wrote {out / 'demo_overlay.png'} and {out / 'demo.json'}")
    return "\n".join(lines)
