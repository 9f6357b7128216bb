"""Eye-in-hand calibration: the camera on the flange, a calibration target fixed in the cell.

The robot moves the camera through stations ``i``; at each the controller reports
``T_base_flange_i`` and the camera sees the target, ``T_cam_plate_i`` (``plate`` names the
target's frame, whatever the target: the 7x7 plate, a circle grid, a chessboard; see
:class:`~cutterpose.calibration.handeye_problem.TargetModel`). With the unknowns
``X = T_flange_cam`` and ``Y = T_base_plate``, every station satisfies

    T_base_flange_i @ X @ T_cam_plate_i = Y        (the AX = XB / AX = YB problem).

Pipeline:
    1. Per station: target detection, ``T_cam_plate_i`` by PnP (IPPE + Levenberg-Marquardt
       on the ideal pixels), the perspective bias of circle centres predicted at that pose and
       removed, PnP again. The pooled PnP residual gives the pixel noise ``sigma_px``. A target
       whose point order is symmetric (a plain grid turned by 180 deg reads the same) gets each
       station's order from the robot motion before anything else
       (:mod:`cutterpose.calibration.handeye_symmetry`: the rotation angle and screw pitch of
       every station pair's motion must agree between robot and camera).
    2. Starts: every method OpenCV offers -- ``cv2.calibrateHandEye`` (Tsai, Park, Horaud,
       Andreff, Daniilidis; ``Y`` then as the rotation mean of the per-station ``A X B``) and
       ``cv2.calibrateRobotWorldHandEye`` (Shah, Li). The start with the lowest robust cost
       of step 3 is refined.
    3. One joint refinement (``scipy.optimize.least_squares``) of ``X`` and ``Y`` (12
       parameters) on the plate's reprojection error over all images, camera intrinsics
       fixed. Station ``i``'s 2N residuals are whitened with the covariance
       ``sigma_px^2 I + G_i C_robot G_i^T`` (``G_i`` the pixels' Jacobian with respect to the
       flange pose, ``C_robot`` the robot's stated repeatability): the robot's error moves all
       of a station's circles together and is the larger of the two. Robust loss (soft L1) for
       a first pass; stations whose whitened chi-square exceeds both the 99.9 % quantile and
       five times the median are distrusted and left out; then a plain least-squares pass.
       This is the maximum-likelihood estimate under plate and robot noise with the robot's
       per-station errors integrated out in closed form (exact to first order in them).
       ``refinement="bundle"`` then solves the same problem as a bundle adjustment with those
       errors as explicit unknowns under their prior (:func:`bundle_adjust_handeye`); the two
       agree to ~1e-4 mm in the simulated cell, and the estimate reaches the Cramer-Rao bound
       (``benchmarks/handeye_floor.py``, docs/RESULTS.md section 8).
    4. Covariance ``s^2 (J^T J)^-1`` of the 12 parameters (whitened Jacobian, ``s^2`` the
       reduced chi-square, never below 1), per-station residuals in px and as the station's
       plate pose in the base frame against ``Y`` (mm, deg), the spread of those poses against
       what the robot's stated error and the pixel noise explain (:func:`plate_spread`), and
       a one-line verdict.

Degenerate input is refused with a typed error before any solving: fewer than 3 stations,
stations that do not rotate (the rotation between every pair below 2 deg), or rotations all
about one axis (then the translation of ``X`` along that axis is unobservable; Tsai & Lenz
1989, section IV).

Convention:
    Frames and ``T_a_b`` as in PROTOCOL.md ("Robot cell"): mm, ``x_a = T_a_b x_b``.
    Covariance of a transform in the hand-eye file (PROTOCOL.md): order x, y, z [mm], rotation
    x, y, z [rad] about the frame's *own* axes, ``R = R_hat Exp(dphi)``, ``t = t_hat + dt``.
    Internally the refinement perturbs rotations on the left (``Exp(dphi) R_hat``, parent axes;
    :mod:`cutterpose.robot.frames`) and converts on output.
    Robot repeatability: the reported flange pose is the true one moved by independent Gaussian
    errors of ``repeatability_mm`` per axis and turned by ``repeatability_deg`` per axis
    (about the base axes).

References:
    R. Tsai, R. Lenz, "A new technique for fully autonomous and efficient 3D robotics
    hand/eye calibration", IEEE Trans. Robotics and Automation 5(3), 1989.
    M. Shah, "Solving the robot-world/hand-eye calibration problem using the Kronecker
    product", J. Mechanisms and Robotics 5(3), 2013.
    K. Koide, E. Menegatti, "General hand-eye calibration based on reprojection error
    minimization", IEEE RA-L 4(2), 2019 (joint refinement on the reprojection error).
    OpenCV ``calibrateHandEye``, ``calibrateRobotWorldHandEye`` documentation.
"""

from __future__ import annotations

import json
import math
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
from scipy.spatial.transform import Rotation
from scipy.stats import chi2

from ..errors import DegenerateInputError, FeatureError, HandEyeFileError, InputError
from ..geometry.camera import Camera
from ..geometry.jsonfile import read_json
from ..geometry.pose import Pose, geodesic_deg
from .handeye_bundle import BundleResult, bundle_adjust_handeye
from .handeye_problem import (
    HandEyeProblem,
    TargetModel,
    cov_left_to_own,
    refine_xy,
    solve_pnp,
)
from .handeye_report import plate_spread
from .handeye_starts import (
    MIN_PAIR_ROTATION_DEG,
    NUMPY_METHODS,
    OPENCV_METHODS,
    numpy_start,
    opencv_start,
    stack_poses,
)
from .handeye_symmetry import motion_mismatch, resolve_point_orders
from .plate import CirclePlate

__all__ = ["HandEye", "HandEyeResult", "StationResidual", "calibrate_handeye",
           "handeye_from_images", "load_handeye", "save_handeye", "OPENCV_METHODS",
           "check_station_rotations", "NUMPY_METHODS", "BundleResult",
           "bundle_adjust_handeye", "TargetModel", "plate_spread", "MIN_PAIR_ROTATION_DEG"]

MIN_AXIS_SPREAD_DEG = 3.0
MIN_POINTS_PER_STATION = 6
DUPLICATE_ROTATION_DEG = 1.0


# ------------------------------------------------------------------------------------------
@dataclass
class HandEye:
    """What the measurement needs: ``T_flange_cam`` with its covariance, and ``T_base_plate``.

    ``covariance`` is PROTOCOL's: 6x6 of ``T_flange_cam``, x, y, z [mm], rotation x, y, z [rad]
    about the camera frame's own axes.
    """

    T_flange_cam: Pose
    T_base_plate: Pose
    covariance: np.ndarray

    def to_dict(self) -> dict:
        return {"T_flange_cam": self.T_flange_cam.matrix.tolist(),
                "T_base_plate": self.T_base_plate.matrix.tolist(),
                "covariance": np.asarray(self.covariance).tolist(),
                "covariance_convention": "6x6 of T_flange_cam: x, y, z [mm], rotation x, y, z "
                                         "[rad] about the cam frame's own axes",
                "units": "mm"}


@dataclass
class StationResidual:
    """One station's fit. ``position_mm`` and ``angle_deg``: the plate pose this station alone
    gives in the base frame (``T_base_flange_i X T_cam_plate_i``) against the joint ``Y``."""

    name: str
    rms_px: float
    position_mm: float
    angle_deg: float
    chi2: float
    used: bool = True
    distrust: str = ""
    order: str = "as detected"   #: the point order used (a symmetric target: chosen)
    order_margin: float = math.inf  #: how clearly the motion chose it (inf: no choice)
    motion_deg: float = 0.0      #: robot vs camera motion to the other stations: angle
    motion_mm: float = 0.0       #: ... and translation along the axis (medians; X-free)

    def to_dict(self) -> dict:
        return {"name": self.name, "rms_px": self.rms_px, "position_mm": self.position_mm,
                "angle_deg": self.angle_deg, "chi2": self.chi2, "used": self.used,
                "distrust": self.distrust, "order": self.order,
                "motion_mismatch_deg": self.motion_deg, "motion_mismatch_mm": self.motion_mm,
                "order_margin": self.order_margin if math.isfinite(self.order_margin)
                else None}


@dataclass
class HandEyeResult:
    """Result of :func:`calibrate_handeye`.

    Attributes
    ----------
    handeye : the refined transforms and the covariance of ``T_flange_cam``.
    cov_base_plate : 6x6 of ``T_base_plate`` (same convention).
    stations : per-station residuals and distrust.
    starts : OpenCV method name -> its ``(T_flange_cam, T_base_plate)``, or the reason it
        failed (a string).
    start_method : the start that was refined.
    sigma_px : pixel noise from the per-station PnP residuals.
    rms_px : RMS reprojection error of the used stations.
    ok, verdict : the one-line quality verdict.
    """

    handeye: HandEye
    cov_base_plate: np.ndarray
    stations: list[StationResidual]
    starts: dict
    start_method: str
    sigma_px: float
    rms_px: float
    ok: bool
    verdict: str
    repeatability: tuple = (0.0, 0.0)
    notes: list = field(default_factory=list)
    plate_spread: dict = field(default_factory=dict)

    @property
    def T_flange_cam(self) -> Pose:
        return self.handeye.T_flange_cam

    @property
    def T_base_plate(self) -> Pose:
        return self.handeye.T_base_plate

    @property
    def position_3sigma_mm(self) -> float:
        return 3.0 * math.sqrt(max(np.linalg.eigvalsh(self.handeye.covariance[:3, :3])[-1], 0))

    @property
    def angle_3sigma_deg(self) -> float:
        return math.degrees(3.0 * math.sqrt(max(
            np.linalg.eigvalsh(self.handeye.covariance[3:, 3:])[-1], 0)))

    def to_dict(self) -> dict:
        d = self.handeye.to_dict()
        d.update({
            "covariance_base_plate": self.cov_base_plate.tolist(),
            "quality": {"ok": self.ok, "verdict": self.verdict,
                        "position_3sigma_mm": self.position_3sigma_mm,
                        "angle_3sigma_deg": self.angle_3sigma_deg,
                        "rms_px": self.rms_px, "sigma_px": self.sigma_px,
                        "robot_repeatability_mm_deg": list(self.repeatability),
                        "notes": self.notes},
            "plate_spread": self.plate_spread,
            "start_method": self.start_method,
            "stations": [s.to_dict() for s in self.stations],
            "opencv_methods": {k: (v if isinstance(v, str) else
                                   {"T_flange_cam": v[0].matrix.tolist(),
                                    "T_base_plate": v[1].matrix.tolist()})
                               for k, v in self.starts.items()},
        })
        return d


def save_handeye(result: HandEyeResult | HandEye, path) -> Path:
    p = Path(path)
    p.write_text(json.dumps(result.to_dict(), indent=1) + "\n")
    return p


def load_handeye(path) -> HandEye:
    """Read ``handeye.json`` (PROTOCOL.md): ``T_flange_cam``, ``T_base_plate``, ``covariance``.

    Raises
    ------
    HandEyeFileError
        Missing or malformed file or field; the message names it.
    """
    d = read_json(path, HandEyeFileError, "hand-eye file")
    if not isinstance(d, dict):
        raise HandEyeFileError(f"{path}: expected a JSON object")
    poses = {}
    for key, frames in (("T_flange_cam", ("flange", "cam")), ("T_base_plate", ("base", "plate"))):
        if key not in d:
            raise HandEyeFileError(f"{path}: missing field '{key}'")
        try:
            poses[key] = Pose.from_matrix(np.asarray(d[key], float), *frames)
        except (InputError, TypeError, ValueError, OverflowError) as e:
            raise HandEyeFileError(f"{path}: field '{key}': {e}") from None
    try:
        C = np.asarray(d.get("covariance"), float)
    except (TypeError, ValueError, OverflowError):
        C = np.zeros(0)
    if C.shape != (6, 6) or not np.all(np.isfinite(C)):
        raise HandEyeFileError(f"{path}: field 'covariance' must be a finite 6x6 matrix")
    C = 0.5 * (C + C.T)
    if np.linalg.eigvalsh(C).min() < -1e-12 * max(1.0, np.abs(C).max()):
        raise HandEyeFileError(f"{path}: field 'covariance' is not positive semi-definite")
    return HandEye(poses["T_flange_cam"], poses["T_base_plate"], C)


# ------------------------------------------------------------------------------------------
def check_station_rotations(T_base_flange: list[Pose]) -> np.ndarray:
    """Refuse stations that cannot determine ``X``; return the (n, n) pairwise rotation angles.

    Raises
    ------
    DegenerateInputError
        Fewer than 3 stations; no pair rotated by ``MIN_PAIR_ROTATION_DEG``; all relative
        rotations about one axis (within ``MIN_AXIS_SPREAD_DEG``).
    """
    n = len(T_base_flange)
    if n < 3:
        raise DegenerateInputError(f"hand-eye calibration needs at least 3 stations with a "
                                   f"detected plate, got {n}")
    R, _ = stack_poses(T_base_flange)
    ang = geodesic_deg(R[:, None], R[None, :])
    if ang.max() < MIN_PAIR_ROTATION_DEG:
        raise DegenerateInputError(
            f"the stations do not rotate (largest rotation between two stations "
            f"{ang.max():.2f} deg < {MIN_PAIR_ROTATION_DEG} deg): hand-eye calibration needs "
            "stations turned about at least two different axes")
    i, j = np.nonzero(np.triu(ang >= MIN_PAIR_ROTATION_DEG, 1))
    rel = np.einsum("nji,njk->nik", R[i], R[j])  # R_i^T R_j: the motion in the flange frame
    axes = Rotation.from_matrix(rel).as_rotvec()
    axes /= np.linalg.norm(axes, axis=1, keepdims=True)
    lam = np.linalg.eigvalsh(axes.T @ axes / len(axes))
    if lam[1] / lam[2] < math.sin(math.radians(MIN_AXIS_SPREAD_DEG)) ** 2:
        raise DegenerateInputError(
            "every rotation between the stations is about one axis: the camera's offset along "
            "it cannot be found; add stations turned about a second axis (tilt the camera)")
    return ang


def _robust_cost(r: np.ndarray, f: float = 3.0) -> float:
    z = (r / f) ** 2
    return float(np.sum(2.0 * (np.sqrt(1.0 + z) - 1.0)))


def _plate_poses(camera: Camera, target: TargetModel, A: list[Pose], obs: np.ndarray,
                 ambiguity_deg):
    """Step 1: each station's point order (a symmetric target), ``T_cam_plate`` and the marks'
    centre bias. Returns obs in the target's order, B, bias, order labels and margins."""
    n, P = len(A), target.points_mm
    allowed = target.allowed(ambiguity_deg)
    perms = [np.arange(target.n_points)] + list(target.symmetries)
    # detection j is target point perm[j]: object points P[perm]
    cand = [[solve_pnp(camera, P[p], obs[k]) if allowed[k, q] or q == 0 else None
             for q, p in enumerate(perms)] for k in range(n)]
    cand = [[c if c is not None else row[0] for c in row] for row in cand]
    choice = resolve_point_orders(A, cand, target.symmetries, allowed)
    obs = np.stack([obs[k][np.argsort(perms[lab])] for k, lab in enumerate(choice.labels)])
    B, bias = [], np.zeros_like(obs)
    for k in range(n):
        b0 = cand[k][choice.labels[k]]
        bias[k] = target.bias_px(camera, b0)
        B.append(solve_pnp(camera, P, obs[k] - bias[k]))
    return obs, B, bias, choice


def _starts(A: list[Pose], B: list[Pose], prob: HandEyeProblem):
    """Step 2: every linear method; the one with the lowest robust whitened cost wins."""
    starts: dict = {}
    scored = []
    for name in list(OPENCV_METHODS) + [f"{m}-numpy" for m in NUMPY_METHODS]:
        try:
            X, Y = (numpy_start(name[:-6], A, B) if name.endswith("-numpy")
                    else opencv_start(name, A, B))
        except Exception as e:  # noqa: BLE001 -- cv2.error, a missing binding, a degeneracy
            starts[name] = f"failed: {type(e).__name__}: {str(e).splitlines()[0][:120]}"
            continue
        if not (np.all(np.isfinite(X.matrix)) and np.all(np.isfinite(Y.matrix))):
            starts[name] = "failed: not finite"
            continue
        try:
            prob.set_weights(X, Y)
            cost = _robust_cost(prob.residuals(X, Y))
        except np.linalg.LinAlgError:  # a start so far off that the target is not in view
            starts[name] = "failed: the target projects nowhere near its image"
            continue
        if not np.isfinite(cost):
            starts[name] = "failed: the target projects nowhere near its image"
            continue
        starts[name] = (X, Y)
        scored.append((cost, name))
    if not scored:
        raise DegenerateInputError("no OpenCV hand-eye method gave a start: "
                                   + "; ".join(f"{k} {v}" for k, v in starts.items()))
    return starts, min(scored)[1]


def _robust_refine(prob: HandEyeProblem, X: Pose, Y: Pose):
    """Step 3: robust pass, distrust, plain pass (twice: a wrongly distrusted station comes
    back), then re-linearised at the solution."""
    n = len(prob.RA)
    prob.set_weights(X, Y)
    used = np.ones(n, bool)
    X, Y, _ = refine_xy(prob, X, Y, used, "soft_l1")
    limit_q = chi2.ppf(0.999, 2 * prob.seen.sum(axis=1))  # per station: its points
    for _ in range(2):
        prob.set_weights(X, Y)
        c2 = np.sum(prob.residuals(X, Y) ** 2, axis=1)
        new_used = c2 <= np.maximum(limit_q, 5.0 * np.median(c2))
        if new_used.sum() < 3:
            new_used = c2 <= np.sort(c2)[2]
        X, Y, res = refine_xy(prob, X, Y, new_used, "linear")
        if np.array_equal(new_used, used):
            break
        used = new_used
    prob.set_weights(X, Y)
    X, Y, res = refine_xy(prob, X, Y, used, "linear")
    return X, Y, res, used, limit_q


def calibrate_handeye(T_base_flange: list[Pose], points_px, camera: Camera,
                      plate=None, *, names: list[str] | None = None,
                      repeatability_mm: float = 0.03, repeatability_deg: float = 0.005,
                      max_position_3sigma_mm: float = 0.3,
                      max_angle_3sigma_deg: float = 0.03,
                      refinement: str = "marginal", ambiguity_deg=None) -> HandEyeResult:
    """Eye-in-hand calibration from flange poses and the target's points (module doc).

    Parameters
    ----------
    T_base_flange : n flange poses (``to_frame='base'``, ``from_frame='flange'``).
    points_px : (n, N, 2) detected points, observed pixels, in the detector's order (for a
        symmetric target each station's order is chosen from the robot motion).
    camera : the calibrated camera (intrinsics fixed).
    plate : the target: a :class:`CirclePlate` (default: the 7x7 plate), a target of
        :mod:`cutterpose.calibration.targets` or a :class:`TargetModel`.
    repeatability_mm, repeatability_deg : the robot's pose error per axis (1 sigma): its
        repeatability, or its accuracy when that is what limits the poses.
    max_position_3sigma_mm, max_angle_3sigma_deg : the verdict's limits on ``T_flange_cam``.
    refinement : ``"marginal"`` (step 3: the robot's errors integrated out analytically, each
        station whitened by ``sigma_px^2 I + G_i C_robot G_i^T``) or ``"bundle"`` (then, on the
        stations kept, :func:`bundle_adjust_handeye` with the robot's errors as explicit
        unknowns under their prior). Both are the maximum-likelihood estimate under target and
        robot noise and agree to ~1e-5 mm in the simulated cell; ``"bundle"`` is ~5x slower.
    ambiguity_deg : per station, the rotation by which its detected order may be off (0: its
        marks fixed it; 180: a plain grid; None: as the target says), from each detection's
        ``rotation_ambiguity_deg``; default None for every station.

    Raises
    ------
    DegenerateInputError
        Fewer than 3 stations, stations without rotation or rotating about one axis only.
    InputError
        Mismatched counts or frames, non-finite points.
    """
    target = TargetModel.of(plate)
    if refinement not in ("marginal", "bundle"):
        raise InputError(f"unknown hand-eye refinement {refinement!r} (marginal or bundle)")
    A = list(T_base_flange)
    for a in A:
        if (a.to_frame, a.from_frame) != ("base", "flange"):
            raise InputError(f"robot poses must be T_base_flange, got {a.name}")
    obs = np.asarray(points_px, float)
    if obs.ndim != 3 or obs.shape[1:] != (target.n_points, 2) or len(obs) != len(A):
        raise InputError(f"points_px must be ({len(A)}, {target.n_points}, 2) for {len(A)} "
                         f"stations, got {obs.shape}")
    if np.any(np.isinf(obs)):
        raise InputError("points_px holds inf (mark a point not seen with NaN)")
    n_seen = np.sum(np.all(np.isfinite(obs), axis=2), axis=1)
    if len(obs) and n_seen.min() < MIN_POINTS_PER_STATION:
        k = int(np.argmin(n_seen))
        raise InputError(f"station {k} shows {n_seen[k]} target points; a station needs at "
                         f"least {MIN_POINTS_PER_STATION}")
    names = list(names) if names is not None else [f"station{k}" for k in range(len(A))]
    ang = check_station_rotations(A)
    n, P = len(A), target.points_mm
    amb = [None] * len(A) if ambiguity_deg is None else list(ambiguity_deg)
    if len(amb) != len(A):
        raise InputError(f"ambiguity_deg: {len(amb)} values for {len(A)} stations")
    obs, B, bias, orders = _plate_poses(camera, target, A, obs, amb)
    orders.names = ["as detected"] + [f"turned {a:g} deg" for a in target.angles_deg]
    pnp_r = np.stack([camera.project(b.apply(P)) for b in B]) - (obs - bias)
    dof = float(np.sum(2 * n_seen - 6))
    sigma_px = max(float(np.sqrt(np.nansum(pnp_r ** 2) / dof)), 1e-3)
    prob = HandEyeProblem(camera, P, A, obs, bias, sigma_px, repeatability_mm,
                          math.radians(repeatability_deg))
    starts, start_method = _starts(A, B, prob)
    X, Y, res, used, limit_q = _robust_refine(prob, *starts[start_method])
    J = res.jac
    s2 = max(float(np.sum(res.fun ** 2)) / max(len(res.fun) - 12, 1), 1.0)
    try:
        cov12 = s2 * np.linalg.inv(J.T @ J)
    except np.linalg.LinAlgError:
        raise DegenerateInputError("hand-eye refinement is singular (stations too alike)") from None
    # parameters (dphi, t) -> (t, dphi) per transform; left -> own axes for the file
    order = [3, 4, 5, 0, 1, 2]
    covX_own = cov_left_to_own(X, cov12[np.ix_(order, order)])
    covY_own = cov_left_to_own(Y, cov12[np.ix_([o + 6 for o in order], [o + 6 for o in order])])
    if refinement == "bundle":
        ba = bundle_adjust_handeye(A, obs, camera, X, Y, plate=target, sigma_px=sigma_px,
                                   repeatability_mm=repeatability_mm,
                                   repeatability_deg=repeatability_deg, bias_px=bias,
                                   loss="linear", used=used)
        X, Y, covX_own, covY_own = (ba.T_flange_cam, ba.T_base_plate, ba.cov_flange_cam,
                                    ba.cov_base_plate)
    stations = _station_figures(prob, A, B, X, Y, names, used, limit_q, ang, orders)
    raw = prob.raw(X, Y)
    used_rms = float(np.sqrt(np.nanmean(np.sum(raw[used] ** 2, axis=2))))
    result = HandEyeResult(HandEye(X, Y, covX_own), covY_own, stations, starts, start_method,
                           sigma_px, used_rms, True, "", (repeatability_mm, repeatability_deg))
    result.plate_spread = plate_spread(prob, A, B, X, Y, used)
    if not np.all(np.isinf(orders.margins)):
        flipped = [s.name for s in stations if s.order != "as detected"]
        result.notes.append(
            f"the target's point order is ambiguous: each station's order chosen from the robot "
            f"motion (screw invariants); {len(flipped)} of {n} read in a turned order"
            + (f" ({', '.join(flipped)})" if flipped else ""))
    result.ok, result.verdict = _verdict(result, ang, max_position_3sigma_mm,
                                         max_angle_3sigma_deg)
    return result


def _station_figures(prob, A, B, X, Y, names, used, limit_q, ang, orders) -> list:
    """Step 4: per-station residuals, the plate pose each station alone gives, distrust."""
    n = len(A)
    prob.set_weights(X, Y)
    rms = np.sqrt(np.nanmean(np.sum(prob.raw(X, Y) ** 2, axis=2), axis=1))
    c2 = np.sum(prob.residuals(X, Y) ** 2, axis=1)
    m_deg, m_mm = motion_mismatch(A, B)
    stations = []
    for k in range(n):
        Yk = A[k] @ X @ B[k]
        st = StationResidual(names[k], float(rms[k]), float(np.linalg.norm(Yk.t_mm - Y.t_mm)),
                             float(geodesic_deg(Yk.R, Y.R)), float(c2[k]), bool(used[k]))
        st.order = orders.names[orders.labels[k]]
        st.order_margin = float(orders.margins[k])
        st.motion_deg, st.motion_mm = float(m_deg[k]), float(m_mm[k])
        why = []
        if not used[k]:
            why.append(f"outlier (chi-square {c2[k]:.0f}, limit "
                       f"{max(limit_q[k], 5.0 * np.median(c2[used])):.0f}; plate off by "
                       f"{st.position_mm:.2f} mm / {st.angle_deg:.3f} deg)")
        others = np.delete(ang[k], k)
        if others.min() < DUPLICATE_ROTATION_DEG:
            j = int(np.argmin(np.where(np.arange(n) == k, np.inf, ang[k])))
            why.append(f"adds no rotation (within {others.min():.2f} deg of {names[j]})")
        if np.isfinite(st.order_margin) and st.order_margin < 5.0 * max(n - 1, 1):
            why.append(f"point order uncertain (margin {st.order_margin:.1f})")
        st.distrust = "; ".join(why)
        stations.append(st)
    return stations


def _verdict(r: HandEyeResult, ang: np.ndarray, max_pos: float, max_ang: float):
    n_used = sum(s.used for s in r.stations)
    n = len(r.stations)
    p3, a3 = r.position_3sigma_mm, r.angle_3sigma_deg
    out = [s.name for s in r.stations if not s.used]
    head = (f"{n_used} of {n} stations, 3-sigma {p3:.3f} mm / {a3:.4f} deg, RMS "
            f"{r.rms_px:.3f} px, largest rotation between stations {ang.max():.0f} deg")
    if out:
        head += f"; left out: {', '.join(out)}"
    if n_used < 6:
        return False, f"poor: only {head} (take 10-30 stations)"
    if p3 > max_pos or a3 > max_ang:
        return False, (f"poor: {head} (limits {max_pos} mm / {max_ang} deg: add stations "
                       "with more rotation, 20-45 deg tilts about different axes)")
    if ang.max() < 30.0:
        return True, f"usable: {head} (little rotation; tilt the camera 20-45 deg)"
    return True, f"good: {head}"


def _detect(target, img: np.ndarray):
    """``(points_px in the target's order, NaN where not seen, rotation ambiguity [deg], '')``
    or ``(None, 0, reason)``: a CirclePlate through :func:`detect_plate`, any other target
    through its ``detect``."""
    from .intrinsics import detect_plate

    if target is None or isinstance(target, CirclePlate):
        try:
            return detect_plate(img, target or CirclePlate()).points_px, 0, ""
        except FeatureError as e:
            return None, 0, str(e)
    det = target.detect(img)
    if not det:
        return None, 0, str(getattr(det, "reason", "") or "target not found")
    n_all = TargetModel.of(target).n_points
    ids = np.asarray(det.ids, int)
    if len(np.unique(ids)) < MIN_POINTS_PER_STATION:
        return None, 0, (f"{len(np.unique(ids))} of {n_all} points: a station needs at least "
                         f"{MIN_POINTS_PER_STATION}")
    pts = np.full((n_all, 2), np.nan)  # a partial view: the points not seen stay NaN
    pts[ids] = det.points_px
    return pts, int(det.rotation_ambiguity_deg), ""


def handeye_from_images(paths, T_base_flange: list[Pose], camera: Camera,
                        plate=None, progress=None, **kwargs) -> HandEyeResult:
    """Detect the target in each image (paired with the robot poses in order; the CLI pairs
    them by station number first, :func:`cutterpose.robot.pose_files.pair_with_images`), drop
    the images without a target (with their poses; ``progress(name, reason)`` reports each),
    and calibrate (:func:`calibrate_handeye`, ``kwargs``)."""
    import cv2

    paths = [Path(p) for p in paths]
    if len(paths) != len(T_base_flange):
        raise InputError(f"{len(paths)} target images but {len(T_base_flange)} robot poses; "
                         "give one pose per image, in the images' sorted order")
    pts, poses, names, amb = [], [], [], []
    for p, a in zip(paths, T_base_flange):
        img = cv2.imread(str(p), cv2.IMREAD_GRAYSCALE) if p.is_file() else None
        reason = "not a readable image" if img is None else ""
        if img is not None:
            found, ambiguity, reason = _detect(plate, img)
            if found is not None:
                pts.append(found)
                poses.append(a)
                names.append(p.name)
                amb.append(ambiguity)
        if progress is not None:
            progress(p.name, reason or None)
    n_pts = TargetModel.of(plate).n_points
    return calibrate_handeye(poses, np.array(pts).reshape(len(pts), n_pts, 2), camera,
                             plate, names=names, ambiguity_deg=amb, **kwargs)
