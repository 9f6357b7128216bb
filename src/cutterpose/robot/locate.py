"""The holder and the grasp frame in the robot's base frame, with their 6x6 covariance.

    T_base_holder = T_base_flange @ T_flange_cam @ T_cam_holder
    T_base_grasp  = T_base_holder @ T_holder_grasp

Three independent error sources are propagated to first order
(:class:`cutterpose.robot.frames.PoseCov`): the robot's accuracy on ``T_base_flange``
(:class:`RobotAccuracy`), the hand-eye covariance of ``T_flange_cam`` (``handeye.json``), and
the measurement's covariance of ``T_cam_holder``. ``T_holder_grasp`` is exact (a design value).

Measurement covariance: the measurement reports per-DOF standard deviations (``std_dof``,
which may include systematic terms such as the edge-wear bias, :mod:`cutterpose.pipeline`).
Their correlations come from the geometry: with ``J`` the Jacobian of the 20 corners' ideal
pixels with respect to the DOFs at the measured pose, ``C0 = (J^T J)^-1`` has the shape of
the Gauss-Newton covariance; its correlation matrix is scaled to the reported std,
``Cov = diag(std) corr(C0) diag(std)``. (A measurement that carries its own full covariance
as ``cov_dof`` is used as it is.) The correlations matter: depth and tilt errors are strongly
coupled for a narrow-angle camera, and the grasp frame's error depends on them.

Convention:
    PROTOCOL.md "Robot cell"; covariances as in :mod:`cutterpose.robot.frames` (mm, rad, parent
    axes) and in ROS form in the JSON. Robot accuracy: independent Gaussian errors of
    ``position_mm`` per base axis and ``angle_deg`` about each base axis (1 sigma).
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from ..calibration.handeye import HandEye, load_handeye
from ..errors import InputError
from ..geometry.camera import Camera, default_camera
from ..geometry.holder import Holder, default_holder
from ..geometry.pose import Pose, pixel_jacobian
from .frames import PoseCov, cov_from_dof, cov_from_own_axes
from .grasp import GraspTolerance, GraspVerdict, grasp_frame, judge, refusal_hint
from .poses import load_flange_pose

__all__ = ["RobotAccuracy", "RobotResult", "locate", "measurement_covariance"]


@dataclass(frozen=True)
class RobotAccuracy:
    """The robot's error on the flange pose it reports, 1 sigma per axis.

    The default, 0.05 mm and 0.01 deg, is the repeatability class of 6-axis industrial robots
    of 100-300 kg payload (ISO 9283 RP +-0.05..0.08 mm); the grasp happens near where the
    picture was taken, so repeatability, not absolute accuracy, is what matters. Give your
    robot's figure.
    """

    position_mm: float = 0.05
    angle_deg: float = 0.01

    def __post_init__(self):
        if not (self.position_mm >= 0 and self.angle_deg >= 0
                and math.isfinite(self.position_mm) and math.isfinite(self.angle_deg)):
            raise InputError(f"robot accuracy must be finite and >= 0, got "
                             f"{self.position_mm} mm, {self.angle_deg} deg")

    @property
    def covariance(self) -> np.ndarray:
        r = math.radians(self.angle_deg)
        return np.diag([self.position_mm ** 2] * 3 + [r * r] * 3)


def measurement_covariance(measurement, camera: Camera, holder: Holder) -> np.ndarray | None:
    """6x6 covariance of the measured DOFs (alpha, beta, gamma [deg], X, Y, Z [mm]) (module
    doc); None without a pose or a finite std."""
    cov = getattr(measurement, "cov_dof", None)
    if cov is not None:
        return np.asarray(cov, float)
    pose, std = measurement.pose, np.asarray(measurement.std_dof, float)
    if pose is None or not np.all(np.isfinite(std)):
        return None
    J = pixel_jacobian(pose.R, pose.t_mm, holder.points_holder_mm, camera.K)[0]
    try:
        C0 = np.linalg.inv(J.T @ J)
    except np.linalg.LinAlgError:
        return None
    d = np.sqrt(np.diag(C0))
    corr = C0 / np.outer(d, d)
    return corr * np.outer(std, std)


@dataclass
class RobotResult:
    """The base-frame answer (:func:`locate`).

    Attributes
    ----------
    T_base_flange, T_base_cam : the flange pose given and the camera it implies.
    T_cam_holder, T_base_holder, T_base_grasp : None when the measurement has no pose.
    grasp : the verdict.
    robot_accuracy : what was assumed for the robot.
    """

    T_base_flange: PoseCov
    T_flange_cam: PoseCov
    T_base_cam: PoseCov
    T_cam_holder: PoseCov | None
    T_base_holder: PoseCov | None
    T_base_grasp: PoseCov | None
    grasp: GraspVerdict
    robot_accuracy: RobotAccuracy

    def to_dict(self) -> dict:
        """The fields of the measurement JSON (PROTOCOL.md "Robot cell"): ``T_base_holder``
        and ``T_base_grasp`` as 4x4 (mm), ``grasp``, and every pose in ROS form under
        ``poses_ros``."""
        def m(pc):
            return None if pc is None else pc.pose.matrix.tolist()

        poses = {"base_flange": self.T_base_flange, "flange_cam": self.T_flange_cam,
                 "base_cam": self.T_base_cam, "cam_holder": self.T_cam_holder,
                 "base_holder": self.T_base_holder, "base_grasp": self.T_base_grasp}
        return {"T_base_flange": m(self.T_base_flange), "T_flange_cam": m(self.T_flange_cam),
                "T_base_holder": m(self.T_base_holder), "T_base_grasp": m(self.T_base_grasp),
                "grasp": self.grasp.to_dict(),
                "poses_ros": {k: None if v is None else v.to_ros_dict()
                              for k, v in poses.items()},
                "frames": {"base": "robot base", "flange": "tool flange", "cam": "camera",
                           "holder": "disc cutter holder", "grasp": "gripper TCP at grasp"},
                "robot_accuracy": {"position_mm": self.robot_accuracy.position_mm,
                                   "angle_deg": self.robot_accuracy.angle_deg}}


def locate(measurement, handeye: HandEye | str | Path, T_base_flange: Pose | str,
           robot_accuracy: RobotAccuracy | None = None, *, camera: Camera | None = None,
           holder: Holder | None = None, tolerance: GraspTolerance | None = None
           ) -> RobotResult:
    """The holder and the grasp frame in the base frame, with covariance and verdict.

    Parameters
    ----------
    measurement : a :class:`cutterpose.pipeline.Measurement` (its ``pose``, ``std_dof``,
        ``ok`` and ``quality.reason`` are used).
    handeye : a :class:`HandEye` or the path of ``handeye.json``.
    T_base_flange : the flange pose at the picture (a ``Pose`` with frames base/flange, a
        one-row pose file, or an inline ``x_mm,y_mm,z_mm,qx,qy,qz,qw``).
    robot_accuracy : the robot's error (default :class:`RobotAccuracy`).
    camera, holder : those of the measurement (defaults as in ``measure``: Table 1, bundled).
    tolerance : the grasp tolerance (default 1 mm and 1 mm at the cutter's rim).

    Raises
    ------
    InputError
        Poses whose frames do not chain (e.g. a ``T_flange_base`` given as flange pose).
    HandEyeFileError
        A malformed hand-eye file.
    """
    camera = camera or default_camera("table1")
    holder = holder or default_holder()
    acc = robot_accuracy or RobotAccuracy()
    he = handeye if isinstance(handeye, HandEye) else load_handeye(handeye)
    A = T_base_flange if isinstance(T_base_flange, Pose) else load_flange_pose(T_base_flange)
    if (A.to_frame, A.from_frame) != ("base", "flange"):
        raise InputError(f"the flange pose must be T_base_flange, got {A.name}")
    pc_A = PoseCov(A, acc.covariance)
    pc_X = PoseCov(he.T_flange_cam, cov_from_own_axes(he.T_flange_cam, he.covariance))
    pc_bc = pc_A @ pc_X
    R_cam_base = pc_bc.pose.R.T
    if measurement.pose is None:
        reason = getattr(measurement.quality, "reason", "") or "no pose"
        v = GraspVerdict("retake", f"measurement refused: {reason}", refusal_hint(reason),
                         tolerance=tolerance or GraspTolerance())
        return RobotResult(pc_A, pc_X, pc_bc, None, None, None, v, acc)
    pose = measurement.pose.with_frames("cam", "holder")
    C_own = getattr(measurement, "covariance_cam", None)
    if C_own is not None and np.all(np.isfinite(C_own)):
        # the measurement's error budget (noise, edge radius, edge model), about the holder's
        # own axes: the full covariance, correlations included
        C_m = cov_from_own_axes(pose, np.asarray(C_own, float))
    else:
        cov_dof = measurement_covariance(measurement, camera, holder)
        C_m = cov_from_dof(pose, cov_dof) if cov_dof is not None else np.full((6, 6), np.nan)
    finite = np.all(np.isfinite(C_m))
    pc_m = PoseCov(pose, C_m if finite else np.zeros((6, 6)))
    pc_bh = pc_bc @ pc_m
    pc_bg = pc_bh @ PoseCov.exact(grasp_frame(holder))
    # each source alone, for the shares (the propagation is linear, they add up)
    Z = np.zeros((6, 6))
    T_hg = PoseCov.exact(grasp_frame(holder))
    parts = {
        "measurement": (PoseCov.exact(A) @ PoseCov.exact(he.T_flange_cam) @ pc_m @ T_hg).cov,
        "hand-eye": (PoseCov.exact(A) @ pc_X @ PoseCov(pose, Z) @ T_hg).cov,
        "robot": (pc_A @ PoseCov.exact(he.T_flange_cam) @ PoseCov(pose, Z) @ T_hg).cov,
    }
    if not finite:
        v = GraspVerdict("retake", "the measurement has no finite uncertainty",
                         refusal_hint("uncertain"), tolerance=tolerance or GraspTolerance())
    else:
        v = judge(pc_bg.cov, parts, R_cam_base, tolerance)
    if not measurement.ok:  # a refused measurement is never grasp
        reason = getattr(measurement.quality, "reason", "") or "refused"
        v = GraspVerdict("retake", f"measurement refused: {reason}", refusal_hint(reason),
                         v.position_3sigma_mm, v.angle_3sigma_deg, v.tolerance, v.shares)
    return RobotResult(pc_A, pc_X, pc_bc, pc_m, pc_bh, pc_bg, v, acc)
