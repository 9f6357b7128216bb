"""From one image to a checked pose: :func:`measure`.

The measurement reads

    features -> method.estimate -> method.budget -> verdict

Image processing (:mod:`cutterpose.image.features`, paper section 2.1) finds the holder's
features (the pocket outline, the edge lines, the corners); the pose method
(:class:`~cutterpose.solvers.method.PoseMethod`, by name from :mod:`cutterpose.methods`) turns
them into a pose (:meth:`~cutterpose.solvers.method.PoseMethod.estimate`) and says how far off
it may be (:meth:`~cutterpose.solvers.method.PoseMethod.budget`: noise, edge model, edge break
... propagated to the position of a grasp point and to the rotation); the verdict
(:func:`cutterpose.verdict.verdict`, then the method's own
:meth:`~cutterpose.solvers.method.PoseMethod.review`) refuses, with the reason, a pose that
should not be used: residuals, working range, ambiguity, std, and 3-sigma figures above the
tolerance (1 mm, 0.3 deg). The camera-frame 6 x 6 covariance is
``Measurement.covariance_cam`` (order :data:`cutterpose.budget.COVARIANCE_CAM_ORDER`).

The default method is ``dm+b`` (:mod:`cutterpose.solvers.edge_band`): the pocket outline's pose
for the start on the field chain (no corners needed; the corners' ``dm+`` pose when the band
finds nothing from there, and on the paper's chain), then the band across every broken pocket
edge fitted with the edge model (:mod:`cutterpose.image.edge_band`), so that the pose is that of
the design edge on field holders. ``dm+r`` (:mod:`cutterpose.solvers.radius_budget`) fits one
radius from the corners alone. The corner methods (``dm``, ``dm+``, PnP) see the broken edge,
not the design edge, and their budget carries the break (:mod:`cutterpose.solvers.corners`).

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

from .errors import CutterposeError, FeatureError, ImageError, InputError
from .frames import load_frame
from .geometry.camera import Camera, default_camera
from .geometry.holder import Holder, default_holder
from .geometry.pose import Pose, wrap_deg
from .image import FeatureParams, Features, detect_features
from .methods import get_method
from .solvers.corners import (
    ambiguity_ratio,
    edge_break_effect,
    edge_wear_effect,
    fit_offset,
    order_for_model,
    pose_std,
    worst_line_residual,
)
from .solvers.edge_band import band_budget, band_verdict, outline_start
from .solvers.estimate import PoseEstimate
from .solvers.method import MethodContext, PoseMethod
from .verdict import (
    DOF_NAMES,
    EDGE_SHAPE_FITS,
    EDGE_SHAPES,
    NOMINAL_DISTANCE_MM,
    UNKNOWN_EDGE_BREAK_MM,
    Quality,
    QualityLimits,
    verdict,
)

__all__ = ["QualityLimits", "Quality", "Measurement", "measure", "measure_features", "judge",
           "order_for_model", "pose_std", "demo", "DOF_NAMES", "edge_wear_effect",
           "band_budget", "band_verdict", "edge_break_effect", "UNKNOWN_EDGE_BREAK_MM",
           "fit_offset", "NOMINAL_DISTANCE_MM", "station_center_dof", "station_params",
           "ambiguity_ratio", "worst_line_residual", "outline_start", "corner_residual_px",
           "EDGE_SHAPES", "EDGE_SHAPE_FITS", "PoseEstimate"]


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
        return None if self.estimate is None else self.estimate.band

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


def corner_residual_px(features: Features, camera: Camera, holder: Holder,
                       limits: QualityLimits | None = None) -> float:
    """RMS residual (ideal px) of ``dm+``'s pose fitted to the detected corners: how far the
    innermost rise the corners follow lies off the rigid model (NaN without a pose). The
    tracker holds its tracked edges to it."""
    if not np.isfinite(np.asarray(features.corners_px, float)).all(axis=1).any():
        return math.nan
    est = get_method("dm+").estimate(features, camera, holder,
                                     MethodContext(limits or QualityLimits()))
    return float(est.residual_px) if est else math.nan


def judge(method: PoseMethod, estimate: PoseEstimate, features: Features, camera: Camera,
          holder: Holder, limits: QualityLimits) -> Quality:
    """The verdict on ``method``'s ``estimate``: its budget
    (:meth:`~cutterpose.solvers.method.PoseMethod.budget`), the common verdict
    (:func:`cutterpose.verdict.verdict`, with the ambiguity of its candidates and the edges'
    possible wear as a note), then the method's own checks
    (:meth:`~cutterpose.solvers.method.PoseMethod.review`)."""
    budget, bias, offset_px = None, None, math.nan
    if estimate:
        budget = method.budget(estimate, features, camera, holder, limits)
        bias, offset_px = edge_wear_effect(estimate.pose, features, camera, holder)
    amb = ambiguity_ratio(estimate, features.corners_ideal_px, camera, holder,
                          order=features.order)
    q = verdict(estimate, budget, limits, amb, bias, offset_px)
    return method.review(q, estimate, features, camera, holder, limits)


def measure_features(features: Features, camera: Camera, holder: Holder,
                     method: str | PoseMethod = "dm+b", limits: QualityLimits | None = None,
                     edge_look=None, *, outline_failed: str | None = None) -> Measurement:
    """Pose, std and verdict from already detected features (one image, several methods):
    features -> ``method.estimate`` -> ``method.budget`` -> verdict (:func:`judge`).
    ``edge_look``: the edge look calibrated in the cell
    (:class:`cutterpose.calibration.edge_look.EdgeLookCalibration`; the methods that fit the
    edge's look use it). ``outline_failed``: the reason a refinement from the method's own
    start already failed on this image
    (:meth:`~cutterpose.solvers.method.RefinementMethod.estimate`): it starts from the
    corners' pose directly."""
    limits = limits or QualityLimits()
    meth = get_method(method)
    timings = dict(features.timings_ms)
    t0 = time.perf_counter()
    try:
        est = meth.estimate(features, camera, holder,
                            MethodContext(limits, edge_look, outline_failed))
    except CutterposeError as e:
        est = PoseEstimate.failure(meth.name, f"{type(e).__name__}: {e}")
    timings["solve"] = (time.perf_counter() - t0) * 1e3
    t0 = time.perf_counter()
    q = judge(meth, est, features, camera, holder, limits)
    timings["quality"] = (time.perf_counter() - t0) * 1e3
    std = q.budget.std_dof if q.budget is not None else np.full(6, np.nan)
    return Measurement(meth.name, est.pose if est else None, std, q,
                       features.visible_corners_px, features, est, timings)


def measure(image, camera: Camera | None = None, holder: Holder | None = None,
            method: str = "dm+b", params: FeatureParams | None = None,
            limits: QualityLimits | None = None, grasp_point_mm=None, *, handeye=None,
            T_base_flange=None, robot_accuracy=None, grasp_tolerance=None, edge_look=None,
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
    handeye, T_base_flange, robot_accuracy, grasp_tolerance : the robot path
        (:func:`cutterpose.robot.locate`; ``grasp_tolerance`` its ``tolerance``).
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
    meth = get_method(method)  # unknown names fail before any work
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
    m = _measure_frame(image, camera, holder, meth, params, limits, edge_look, corners)
    if load_ms:
        m.timings_ms = {"load": load_ms} | m.timings_ms
    m.timings_ms["total"] = (time.perf_counter() - t0) * 1e3
    return _with_robot(m, camera, holder, handeye, T_base_flange, robot_accuracy,
                       grasp_tolerance)


def _measure_frame(image: np.ndarray, camera: Camera, holder: Holder, meth: PoseMethod,
                   params, limits, edge_look, corners: bool | None) -> Measurement:
    """Features -> :func:`measure_features`; a method that found nothing without the corners
    (``dm+b`` from the outline's pose) gets them and starts again from their pose."""
    # a method that needs no corners (dm+b starts from the outline): the line fits are skipped
    # on the field chain (a third of the image stage)
    if corners is None:
        corners = meth.needs_corners
    try:
        feats = detect_features(image, camera, holder, params, corners=corners)
    except FeatureError as e:
        return Measurement(meth.name, None, np.full(6, np.nan), Quality(False, str(e)))
    m = measure_features(feats, camera, holder, meth, limits, edge_look)
    if (m.pose is None and feats.segmentation == "outline" and m.estimate is not None
            and not m.estimate):
        # the first attempt's time stays in the total
        try:
            feats = detect_features(image, camera, holder, params, corners=True)
        except FeatureError:
            pass
        else:
            m = measure_features(feats, camera, holder, meth, limits, edge_look,
                                 outline_failed=m.estimate.reason)
    return m


def _with_robot(m: Measurement, camera, holder, handeye, T_base_flange, robot_accuracy,
                grasp_tolerance=None):
    """Attach the base-frame answer when both a hand-eye file and a flange pose are given."""
    if handeye is None and T_base_flange is None:
        return m
    if handeye is None or T_base_flange is None:
        raise InputError("the base frame needs both a hand-eye file and a flange pose")
    from .robot.locate import locate

    m.robot = locate(m, handeye, T_base_flange, robot_accuracy, camera=camera, holder=holder,
                     tolerance=grasp_tolerance)
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
