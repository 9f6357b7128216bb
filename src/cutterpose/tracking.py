"""Tracking the holder while the robot approaches it: one pose per frame, fast.

The first frame (and any frame where tracking fails) is measured in full
(:func:`cutterpose.pipeline.measure`: region search, threshold, contour segmentation, dm+).
From the second frame on, the previous poses predict where every edge of the holder's inner
contour lies, and the region search, threshold and contour segmentation are skipped:

1. **prediction** (constant velocity on SE(3)): with ``T_k = (R_k, t_k)`` the pose of the holder
   in the camera frame at frame ``k``, the camera's motion over one frame is
   ``D = T_k T_{k-1}^{-1}`` (its body velocity, in the camera frame); the prediction is
   ``T_pred = D T_k``; without two consecutive tracked poses, ``T_pred = T_k``;
2. **edges**: the 20 model edges projected with ``T_pred`` (ideal pixels) are the initial lines
   of the sub-pixel gradient refinement :func:`cutterpose.image.edges.refine_lines` (profiles
   across each line within +-``band_half_width_px``, each edge's band read from its own crop of
   the frame); the corners are the intersections of consecutive lines, in model order;
3. **pose**: Levenberg-Marquardt on the 20 corners' ideal-pixel reprojection error started at
   ``T_pred`` (:func:`cutterpose.solvers.pnp.refine.refine_pose`), no coarse search; the std per
   DOF is the Gauss-Newton covariance ``s^2 (J^T J)^-1`` of :mod:`cutterpose.pipeline`;
4. **checks**: each edge must be found along at least ``min_support`` of its length, the corner
   residuals must stay small (``max_rms_px``, ``max_corner_residual_px``). A frame that fails
   them (a jump, an occluder, lost edges) falls back to the full measurement and says why.

**Temporal filter** (optional, ``filter=True``): an alpha-beta filter, the steady-state Kalman
filter of a constant-velocity model, on SE(3): state ``T`` and a per-frame twist ``xi``;
predict ``T- = Exp(xi) T``; innovation ``nu = Log(Z T-^{-1})`` for the measured pose ``Z``;
update ``T = Exp(alpha nu) T-``, ``xi = xi + beta nu``. It is reported *beside* the raw pose,
never instead of it, and it is reset to the raw pose (velocity zero) after a fall-back or when
the innovation exceeds the gate, so that it never hides a jump.

Convention:
    Poses ``T_cam_holder`` as in :mod:`cutterpose.geometry.pose` (``x_cam = R x_holder + t``,
    mm, deg). Twists ``xi = (omega [rad], rho [mm])`` with ``Exp(xi) = (Exp(omega),
    V(omega) rho)``. Pixels: ``*_px`` observed, ``*_ideal_px`` undistorted (ideal pinhole ``K``).
    Line ``j`` of the model runs from corner ``j - 1`` to corner ``j`` (``holder.json`` order),
    so that corner ``j`` is the intersection of lines ``j`` and ``j + 1`` as in
    :func:`cutterpose.image.edges.intersect_consecutive`.

References:
    T. Drummond, R. Cipolla, "Real-time visual tracking of complex structures", PAMI 24(7),
    2002 (edge search along normals of the projected model); T. Barfoot, *State Estimation for
    Robotics*, 2017, sec. 7.1 (SE(3) exponential map, ``V = J_l``); P. Kalata, "The tracking
    index", IEEE TAES 20(2), 1984 (alpha-beta filter); Benedict & Bordner (1962) for
    ``beta = alpha^2 / (2 - alpha)``.
"""

from __future__ import annotations

import math
import time
from dataclasses import dataclass, field, replace

import numpy as np
from scipy.ndimage import gaussian_filter1d
from scipy.spatial.transform import Rotation

from .budget import Tolerance
from .errors import CutterposeError, InputError
from .frames import load_frame
from .geometry.camera import Camera, default_camera
from .geometry.holder import Holder, default_holder
from .geometry.pose import Pose, pixel_jacobian
from .image import FeatureParams, as_grey_u8
from .image.edges import _half_max_centroids, intersect_consecutive
from .pipeline import DOF_NAMES, Measurement, QualityLimits, measure
from .solvers.pnp.refine import refine_pose

__all__ = ["TrackParams", "TrackResult", "Tracker", "PoseFilter", "approach_limits",
           "approach_params", "se3_exp", "se3_log"]


# ------------------------------------------------------------------------------------------
# SE(3)
def _v_matrix(w: np.ndarray) -> np.ndarray:
    """``V(w) = I + (1 - cos a)/a^2 [w]x + (a - sin a)/a^3 [w]x^2`` (the left Jacobian)."""
    a2 = float(w @ w)
    W = np.array([[0.0, -w[2], w[1]], [w[2], 0.0, -w[0]], [-w[1], w[0], 0.0]])
    if a2 < 1e-12:
        return np.eye(3) + 0.5 * W + (W @ W) / 6.0
    a = math.sqrt(a2)
    return np.eye(3) + ((1 - math.cos(a)) / a2) * W + ((a - math.sin(a)) / (a2 * a)) * (W @ W)


def se3_exp(xi: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """``Exp`` of a twist ``(omega [rad], rho [mm])`` -> ``(R, t_mm)``."""
    xi = np.asarray(xi, float)
    w = xi[:3]
    return Rotation.from_rotvec(w).as_matrix(), _v_matrix(w) @ xi[3:]


def se3_log(R: np.ndarray, t_mm: np.ndarray) -> np.ndarray:
    """``Log`` of ``(R, t_mm)`` -> twist ``(omega [rad], rho [mm])``."""
    w = Rotation.from_matrix(R).as_rotvec()
    return np.concatenate([w, np.linalg.solve(_v_matrix(w), np.asarray(t_mm, float))])


def _relative(a: Pose, b: Pose) -> tuple[np.ndarray, np.ndarray]:
    """``a b^{-1}`` as ``(R, t)``."""
    R = a.R @ b.R.T
    return R, a.t_mm - R @ b.t_mm


def _left(R: np.ndarray, t: np.ndarray, pose: Pose) -> Pose:
    """``(R, t) pose``."""
    Rn = R @ pose.R
    # re-orthonormalise: products of many rotations drift by ~1e-16 per step
    u, _, vt = np.linalg.svd(Rn)
    return Pose(u @ vt, R @ pose.t_mm + t)


def _bilinear(img: np.ndarray, u: np.ndarray, v: np.ndarray) -> np.ndarray:
    """Bilinear grey levels of a uint8 image at observed pixels (replicated border)."""
    h, w = img.shape
    u = np.clip(u, 0.0, w - 1.000001)
    v = np.clip(v, 0.0, h - 1.000001)
    u0 = u.astype(np.intp)
    v0 = v.astype(np.intp)
    fu, fv = u - u0, v - v0
    flat = img.reshape(-1)
    i = v0 * w + u0
    p00, p01 = flat[i].astype(np.float32), flat[i + 1].astype(np.float32)
    p10, p11 = flat[i + w].astype(np.float32), flat[i + w + 1].astype(np.float32)
    top = p00 + fu * (p01 - p00)
    return top + fv * ((p10 + fu * (p11 - p10)) - top)


def _fit_lines(pts: np.ndarray, ids: np.ndarray, n: int, iterations: int = 4) -> np.ndarray:
    """Huber-weighted total least squares lines of labelled points, all lines at once.

    The normal of a weighted TLS line is the minor axis of the points' weighted covariance:
    the major axis lies at ``0.5 atan2(2 Sxy, Sxx - Syy)``. Weights: Huber with
    ``k = 1.5 * 1.4826 * MAD`` of each line's residuals (as :mod:`cutterpose.image.edges`).
    Lines without points are NaN.
    """
    x, y = pts[:, 0], pts[:, 1]
    w = np.ones(len(pts))
    bounds = np.searchsorted(ids, np.arange(n + 1))   # ids are sorted by line
    for it in range(iterations + 1):
        W = np.bincount(ids, w, n)
        with np.errstate(invalid="ignore", divide="ignore"):
            cx = np.bincount(ids, w * x, n) / W
            cy = np.bincount(ids, w * y, n) / W
        dx, dy = x - cx[ids], y - cy[ids]
        sxx = np.bincount(ids, w * dx * dx, n)
        syy = np.bincount(ids, w * dy * dy, n)
        sxy = np.bincount(ids, w * dx * dy, n)
        th = 0.5 * np.arctan2(2 * sxy, sxx - syy)
        nx, ny = -np.sin(th), np.cos(th)
        if it == iterations:
            break
        r = np.abs(dx * nx[ids] + dy * ny[ids])
        mad = np.array([np.median(r[bounds[j]:bounds[j + 1]]) if bounds[j + 1] > bounds[j]
                        else 0.0 for j in range(n)])
        k = 1.5 * (1.4826 * mad + 1e-6)
        w = np.where(r <= k[ids], 1.0, k[ids] / np.maximum(r, 1e-12))
    return np.column_stack([nx, ny, -(nx * cx + ny * cy)])


# ------------------------------------------------------------------------------------------
@dataclass(frozen=True)
class TrackParams:
    """Parameters of the tracker (pixel lengths for the paper's 12-Mpx camera; scaled with
    the focal length by :meth:`for_camera`)."""

    band_half_width_px: float = 6.0   #: profiles across the predicted edge, +- this
    cold_band_factor: float = 2.0     #: wider band while the velocity is unknown
    profile_step_px: float = 3.0      #: spacing of the profiles along an edge
    passes: int = 1                   #: refinement passes (re-centred on the refined line)
    end_trim_px: float = 10.0         #: profiles kept this far from the predicted corners
    min_support: float = 0.6          #: share of an edge's profiles that must find the edge
    max_rms_px: float = 0.8           #: RMS corner residual after the pose fit (ideal px)
    max_corner_residual_px: float = 2.5
    filter_alpha: float = 0.5         #: alpha-beta filter gains (beta: Benedict-Bordner)
    filter_beta: float = 0.5 ** 2 / 1.5
    gate_mm: float = 5.0              #: filter reset when the innovation exceeds these
    gate_deg: float = 2.0

    def for_camera(self, camera: Camera) -> TrackParams:
        k = camera.focal_px / (0.00854103 / 3.45e-6)
        if abs(k - 1) < 0.1:
            return self
        return replace(self, band_half_width_px=max(3.0, self.band_half_width_px * k),
                       profile_step_px=max(1.0, self.profile_step_px * k),
                       end_trim_px=max(4.0, self.end_trim_px * k))


def approach_limits() -> QualityLimits:
    """Quality limits of the full measurement during an approach: the working range's angles,
    lateral shifts up to 60 mm, depths from 580 to 940 mm, and an error budget of 10 mm / 3 deg
    (3 sigma): on the way the pose guides the robot and seeds the tracker; the grasp tolerance
    (1 mm, ``Tolerance()``) is the verdict of the measurement at the final stop."""
    return QualityLimits(range_center_dof=(0.0, 0.0, 0.0, 0.0, 0.0, 760.0),
                         range_half_width_dof=(10.0, 10.0, 10.0, 60.0, 60.0, 180.0),
                         tolerance=Tolerance(position_mm=10.0, angle_deg=3.0))


def approach_params(camera: Camera) -> FeatureParams:
    """Image-stage parameters of the full measurement during an approach: the field chain with
    outline templates at 600-900 mm (``roi_depths_mm``; the default matches only the nominal
    600 mm, where a holder at 800-900 mm, 1.3-1.5 times smaller, scores ~0.3 and lands off
    centre)."""
    return FeatureParams.for_camera(camera, roi_depths_mm=(600.0, 675.0, 750.0, 825.0, 900.0))


@dataclass
class TrackResult:
    """One frame's answer.

    Attributes
    ----------
    frame : the frame's index (0-based, in the order given to the tracker).
    mode : ``"track"`` (predicted edges), ``"full"`` (the full measurement: first frame or a
        fall-back) or ``"lost"`` (no pose).
    pose : the raw per-frame pose (None when lost); ``std_dof`` its std per DOF.
    ok : the pose passed the checks (tracking) or the verdict (full).
    fallback_reason : why tracking was not used on this frame ("" when tracked).
    filtered_pose : the temporal filter's pose (None without filter or pose); ``filter_reset``
        the reason it was reset on this frame ("" otherwise).
    rms_px : RMS corner residual; ``edge_support`` the lowest share of an edge found.
    corners_px : (20, 2) corners, model order (tracking) or contour order (full).
    measurement : the full measurement when one was made.
    timings_ms : wall time per stage.
    """

    frame: int
    mode: str
    pose: Pose | None
    std_dof: np.ndarray
    ok: bool
    fallback_reason: str = ""
    filtered_pose: Pose | None = None
    filter_reset: str = ""
    rms_px: float = math.nan
    edge_support: float = math.nan
    corners_px: np.ndarray | None = None
    measurement: Measurement | None = None
    timings_ms: dict = field(default_factory=dict)
    passes: int = 0   #: edge passes (tracking: 2 when the first found the edges off-centre)

    def to_dict(self) -> dict:
        """One JSON object of ``cutterpose track --json-lines``."""
        def f(x):
            return None if x is None or not math.isfinite(float(x)) else float(x)

        return {"frame": self.frame, "mode": self.mode, "ok": self.ok,
                "fallback_reason": self.fallback_reason,
                "pose": None if self.pose is None else self.pose.to_dict(),
                "std": {k: f(v) for k, v in zip(DOF_NAMES, self.std_dof)},
                "filtered_pose": None if self.filtered_pose is None
                else self.filtered_pose.to_dict(),
                "filter_reset": self.filter_reset, "rms_residual_px": f(self.rms_px),
                "edge_support": f(self.edge_support), "passes": self.passes,
                "timings_ms": {k: round(float(v), 3) for k, v in self.timings_ms.items()}}


class PoseFilter:
    """Constant-velocity alpha-beta filter on SE(3) (module doc)."""

    def __init__(self, alpha: float = 0.5, beta: float = 0.5 ** 2 / 1.5, gate_mm: float = 5.0,
                 gate_deg: float = 2.0):
        if not (0 < alpha <= 1 and 0 <= beta < 2):
            raise InputError(f"filter gains need 0 < alpha <= 1, 0 <= beta < 2; got "
                             f"{alpha}, {beta}")
        self.alpha, self.beta = float(alpha), float(beta)
        self.gate_mm, self.gate_deg = float(gate_mm), float(gate_deg)
        self.reset()

    def reset(self, pose: Pose | None = None) -> None:
        self.pose, self.xi = pose, np.zeros(6)
        self._fresh = True   # one pose since the reset: the velocity is not known yet

    def update(self, z: Pose, force_reset: str = "") -> tuple[Pose, str]:
        """Filter the measured pose ``z``; returns the filtered pose and the reset reason."""
        if self.pose is None or force_reset:
            self.reset(z)
            return z, force_reset or "first pose"
        if self._fresh:
            # two-point start: the velocity from the first two poses, the state on the second
            Rn, tn = _relative(z, self.pose)
            self.xi = se3_log(Rn, tn)
            self.pose, self._fresh = z, False
            return z, ""
        Rp, tp = se3_exp(self.xi)
        pred = _left(Rp, tp, self.pose)
        nu = se3_log(*_relative(z, pred))
        # gate on what a jump looks like: the holder's displacement and rotation angle
        rot_deg = math.degrees(float(np.linalg.norm(nu[:3])))
        trans_mm = float(np.linalg.norm(z.t_mm - pred.t_mm))
        if rot_deg > self.gate_deg or trans_mm > self.gate_mm:
            self.reset(z)
            return z, (f"innovation {trans_mm:.1f} mm / {rot_deg:.2f} deg beyond the gate "
                       f"({self.gate_mm} mm / {self.gate_deg} deg)")
        Ru, tu = se3_exp(self.alpha * nu)
        self.pose = _left(Ru, tu, pred)
        self.xi = self.xi + self.beta * nu
        return self.pose, ""


class Tracker:
    """Pose of the holder in a sequence of frames (module doc).

    Parameters
    ----------
    camera, holder : defaults: the Table 1 camera and ``holder.json``.
    method : the full measurement's pose method (first frame and fall-backs).
    params, limits : the full measurement's image parameters and quality limits (default: an
        approach from 940 to 580 mm, :func:`approach_params` and :func:`approach_limits`).
    track : :class:`TrackParams`.
    filter : also report the temporal filter's pose.

    Examples
    --------
    >>> tracker = Tracker(camera, holder, filter=True)          # doctest: +SKIP
    >>> for frame in frames:                                    # doctest: +SKIP
    ...     r = tracker.update(frame)
    ...     print(r.mode, r.pose.dof, r.fallback_reason)
    """

    def __init__(self, camera: Camera | None = None, holder: Holder | None = None,
                 method: str = "dm+", params: FeatureParams | None = None,
                 limits: QualityLimits | None = None, track: TrackParams | None = None,
                 filter: bool = False):
        self.camera = camera or default_camera("table1")
        self.holder = holder or default_holder()
        self.method = method
        self.params = params or approach_params(self.camera)
        self.limits = limits or approach_limits()
        self.tp = (track or TrackParams()).for_camera(self.camera)
        self.K = np.array(self.camera.K, float)
        self._refine_params = FeatureParams.for_camera(
            self.camera, refine_half_width_px=self.tp.band_half_width_px,
            refine_step_px=self.tp.profile_step_px, refine_passes=self.tp.passes,
            refine_trim_px=self.tp.end_trim_px)
        self.filter = PoseFilter(self.tp.filter_alpha, self.tp.filter_beta, self.tp.gate_mm,
                                 self.tp.gate_deg) if filter else None
        self.reset()

    def reset(self) -> None:
        """Forget the past: the next frame is measured in full."""
        self._last: Pose | None = None
        self._prev: Pose | None = None   # the pose before _last, when both were consecutive
        self._n = 0
        if self.filter is not None:
            self.filter.reset()

    # -- one frame ---------------------------------------------------------------------
    def update(self, image) -> TrackResult:
        """Pose in the next frame (array, raw buffer of the camera's size, or a file)."""
        t0 = time.perf_counter()
        img = as_grey_u8(load_frame(image, self.camera))
        k = self._n
        self._n += 1
        timings: dict[str, float] = {}
        reason = "first frame" if k == 0 else "no previous pose"
        if self._last is not None:
            try:
                res = self._track(img, k, timings)
            except CutterposeError as e:
                res = None
                reason = f"{type(e).__name__}: {e}"
            else:
                if isinstance(res, str):
                    reason, res = res, None
            if res is not None:
                self._prev, self._last = self._last, res.pose
                res.timings_ms = timings | {"total": (time.perf_counter() - t0) * 1e3}
                self._filter(res, "")
                return res
        # full measurement
        t1 = time.perf_counter()
        m = measure(img, self.camera, self.holder, self.method, self.params, self.limits)
        timings["full"] = (time.perf_counter() - t1) * 1e3
        self._prev = None   # the velocity is unknown after a fall-back
        if m.ok:
            self._last = m.pose
            res = TrackResult(k, "full", m.pose, m.std_dof, True, reason,
                              rms_px=m.quality.rms_px, corners_px=m.corners_px, measurement=m)
            self._filter(res, f"fall-back: {reason}" if k else "first pose")
        else:
            self._last = None
            res = TrackResult(k, "lost", None, np.full(6, np.nan), False,
                              f"{reason}; full measurement: {m.quality.reason}", measurement=m)
            if self.filter is not None:
                self.filter.reset()
                res.filter_reset = "lost"
        res.timings_ms = timings | {"total": (time.perf_counter() - t0) * 1e3}
        return res

    def _filter(self, res: TrackResult, force: str) -> None:
        if self.filter is not None and res.pose is not None:
            res.filtered_pose, res.filter_reset = self.filter.update(res.pose, force)

    def predict(self) -> Pose | None:
        """The pose predicted for the next frame (constant velocity when known)."""
        if self._last is None:
            return None
        if self._prev is None:
            return self._last
        R, t = _relative(self._last, self._prev)
        return _left(R, t, self._last)

    def _model_lines(self, pose: Pose):
        """The model's lines projected with ``pose`` (ideal px): start points, unit directions,
        lengths, inward normals, corners; None if the holder is behind the camera."""
        X = pose.apply(self.holder.points_holder_mm)
        if np.any(X[:, 2] <= 0):
            return None
        ideal = X[:, :2] / X[:, 2:3] @ self.K[:2, :2].T + self.K[:2, 2]
        a = np.roll(ideal, 1, axis=0)                    # line j: corner j-1 -> corner j
        d = ideal - a
        length = np.linalg.norm(d, axis=1)
        d = d / length[:, None]
        x, y = ideal[:, 0], ideal[:, 1]
        area = 0.5 * (x @ np.roll(y, -1) - np.roll(x, -1) @ y)
        # the pocket lies left of each edge of a polygon with positive (shoelace) area
        inward = np.sign(area) * np.column_stack([-d[:, 1], d[:, 0]])
        return a, d, length, inward, ideal

    def _track(self, img: np.ndarray, k: int, timings: dict) -> TrackResult | str:
        t = time.perf_counter()

        def lap(name):
            nonlocal t
            now = time.perf_counter()
            timings[name] = timings.get(name, 0.0) + (now - t) * 1e3
            t = now

        P = self.holder.points_holder_mm
        pose = self.predict()
        # no velocity yet (second frame, after a fall-back): the frame's motion is not
        # predicted, a wider band covers it
        hw = self.tp.band_half_width_px * (1.0 if self._prev is not None
                                           else self.tp.cold_band_factor)
        for attempt in range(2):
            geo = self._model_lines(pose)
            if geo is None:
                return "the predicted holder is behind the camera"
            a, d, length, inward, corners_pred = geo
            if not np.all(self.camera.in_image(self.camera.distort_px(corners_pred), 2 * hw)):
                return "the predicted holder leaves the image"
            lap("predict")
            lines, support = self._edges(img, a, d, length, inward, hw if attempt == 0
                                         else self.tp.band_half_width_px)
            lap("edges")
            worst = int(np.argmin(support))
            if support[worst] < self.tp.min_support:
                return (f"edge {worst} found along {100 * support[worst]:.0f} % of its length "
                        f"(< {100 * self.tp.min_support:.0f} %): jump, occlusion or lost edge")
            corners_ideal = intersect_consecutive(lines)
            if not np.all(np.isfinite(corners_ideal)):
                return "consecutive tracked edges do not intersect"
            R, tt, _ = refine_pose(pose.R, pose.t_mm, P, corners_ideal, self.K, max_nfev=20)
            try:
                pose = Pose(R, tt)
            except InputError as e:
                return f"the pose fit failed: {e}"
            lap("solve")
            # edges found far from the band's centre were sampled off-centre: once more, with
            # the bands centred on the fitted pose
            moved = float(np.abs(corners_ideal - corners_pred).max())
            if moved <= 0.35 * self.tp.band_half_width_px:
                break
        Xc = pose.apply(P)
        if np.any(Xc[:, 2] <= 0):
            return "the fitted holder is behind the camera"
        proj = Xc[:, :2] / Xc[:, 2:3] @ self.K[:2, :2].T + self.K[:2, 2]
        r = corners_ideal - proj
        dist = np.sqrt((r ** 2).sum(axis=1))
        rms = float(np.sqrt(np.mean(dist ** 2)))
        if rms > self.tp.max_rms_px:
            return (f"corner residual RMS {rms:.2f} px > {self.tp.max_rms_px} px: the tracked "
                    "edges do not fit the holder")
        if dist.max() > self.tp.max_corner_residual_px:
            return (f"corner {int(np.argmax(dist))} is {dist.max():.2f} px off the model "
                    f"(> {self.tp.max_corner_residual_px} px)")
        J = pixel_jacobian(pose.R, pose.t_mm, P, self.K)[0]
        s2 = float((r ** 2).sum()) / max(r.size - 6, 1)
        std = np.sqrt(np.clip(np.diag(s2 * np.linalg.inv(J.T @ J)), 0, None))
        lap("check")
        res = TrackResult(k, "track", pose, std, True, "", rms_px=rms,
                          edge_support=float(support[worst]),
                          corners_px=self.camera.distort_px(corners_ideal))
        res.passes = attempt + 1
        return res

    def _edges(self, img, a, d, length, inward, half_width_px):
        """Sub-pixel edge points in the band of every line at once, and the refitted lines.

        The profiles are those of :func:`cutterpose.image.edges.refine_lines` (0.25 px steps
        across the line from the pocket outwards, smoothed, the edge at the half-maximum
        centroid of the derivative), sampled for all 20 lines in one go: one distortion, one
        bilinear gather from the frame (no crop or float copy of the frame), one centroid
        pass, and Huber-IRLS total least squares vectorised over the lines.

        Returns
        -------
        lines : (N, 3) refitted lines (ideal px); support : (N,) share of each line's profiles
        that found the edge.
        """
        tp = self.tp
        n = len(a)
        offs = np.arange(-half_width_px, half_width_px + 1e-9, 0.25)
        # a profile nearer a corner than the band's half width crosses the neighbouring edge
        trim = max(tp.end_trim_px, half_width_px + 4.0)
        counts = np.maximum(((length - 2 * trim) // tp.profile_step_px).astype(int) + 1, 0)
        ids = np.repeat(np.arange(n), counts)
        first = np.concatenate([[0], np.cumsum(counts)[:-1]])
        ts = trim + (np.arange(ids.size) - first[ids]) * tp.profile_step_px
        base = a[ids] + ts[:, None] * d[ids]
        n_out = -inward[ids]
        q = base[:, None, :] + offs[None, :, None] * n_out[:, None, :]
        obs = self.camera.distort_px(q.reshape(-1, 2))
        prof = _bilinear(img, obs[:, 0], obs[:, 1]).reshape(len(base), len(offs))
        prof = gaussian_filter1d(prof, self._refine_params.refine_sigma_px / 0.25, axis=1)
        o, rows = _half_max_centroids(np.diff(prof, axis=1), offs[0] + 0.125, 0.25)
        pts = base[rows] + o[:, None] * n_out[rows]
        lid = ids[rows]
        support = np.bincount(lid, minlength=n) / np.maximum(counts, 1)
        lines = _fit_lines(pts, lid, n)
        return lines, np.where(counts > 0, support, 0.0)

    def track(self, frames) -> list[TrackResult]:
        """:meth:`update` over an iterable of frames."""
        return [self.update(f) for f in frames]
