"""Frame-named transforms with a 6x6 covariance, their composition, and their ROS form.

Convention:
    Frames of the robot cell (PROTOCOL.md, "Robot cell"): ``base``, ``flange``, ``cam``,
    ``plate``, ``holder``, ``grasp``. ``T_a_b`` (a :class:`~cutterpose.geometry.pose.Pose` with
    ``to_frame = a``, ``from_frame = b``) maps ``x_a = R x_b + t``, ``t`` in mm.

    Uncertainty of ``T_a_b``: a perturbation ``d = (dt, dphi)`` (mm, rad) in the axes of the
    parent frame ``a``, applied as ``R = Exp(dphi) R_hat``, ``t = t_hat + dt``; the covariance is
    ``Cov(d)`` (6x6, order x, y, z, rot x, rot y, rot z). This is the order and meaning of ROS's
    ``geometry_msgs/PoseWithCovariance`` (position, then rotations about the fixed X, Y, Z axes
    of ``header.frame_id``), so the ROS form only converts mm to m. The hand-eye file's
    covariance (PROTOCOL.md) turns about the frame's *own* axes, ``R = R_hat Exp(dphi_own)``;
    :func:`cov_from_own_axes` and :func:`cov_to_own_axes` convert.

    First-order propagation (``[p]x`` the cross-product matrix, ``Exp(a) p ~ p - [p]x a``)::

        T_ac = T_ab T_bc:  d_ac = [[I, -[R_ab t_bc]x], [0, I]] d_ab + [[R_ab, 0], [0, R_ab]] d_bc
        T_ba = T_ab^-1:    d_ba = [[-R^T, -R^T [t]x], [0, -R^T]] d_ab

References:
    J. Sola, J. Deray, D. Atchuthan, "A micro Lie theory for state estimation in robotics",
    arXiv:1812.01537, 2018 (section 4 and appendix: Jacobians of composition and inversion).
    ROS ``geometry_msgs/PoseWithCovariance`` message definition; REP 103 (units, frames).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from scipy.spatial.transform import Rotation

from ..errors import InputError
from ..geometry.pose import Pose
from ..geometry.se3 import skew

__all__ = ["FRAMES", "PoseCov", "skew", "cov_from_own_axes", "cov_to_own_axes",
           "cov_from_dof", "euler_rate_matrix", "bound_3sigma"]

FRAMES = ("base", "flange", "cam", "plate", "holder", "grasp")


def _check_cov(cov, where: str = "covariance") -> np.ndarray:
    C = np.asarray(cov, float)
    if C.shape != (6, 6) or not np.all(np.isfinite(C)):
        raise InputError(f"{where} must be a finite 6x6 matrix, got shape {C.shape}")
    C = 0.5 * (C + C.T)
    if np.linalg.eigvalsh(C).min() < -1e-9 * max(1.0, np.abs(C).max()):
        raise InputError(f"{where} is not positive semi-definite")
    return C


def cov_from_own_axes(pose: Pose, cov_own) -> np.ndarray:
    """Covariance with rotations about the parent's axes from one about the frame's own axes
    (``Exp(R phi) R = R Exp(phi)``)."""
    J = np.eye(6)
    J[3:, 3:] = pose.R
    return J @ _check_cov(cov_own) @ J.T


def cov_to_own_axes(pose: Pose, cov) -> np.ndarray:
    """Inverse of :func:`cov_from_own_axes`."""
    J = np.eye(6)
    J[3:, 3:] = pose.R.T
    return J @ _check_cov(cov) @ J.T


def euler_rate_matrix(alpha_deg: float, beta_deg: float, gamma_deg: float) -> np.ndarray:
    """``W`` with ``dphi = W d(alpha, beta, gamma)`` (rad per deg) for ``R = Rz Ry Rx``.

    ``dR R^T`` of ``Rz(g) Ry(b) Rx(a)`` is the rotation about ``e_z`` (gamma), ``Rz e_y``
    (beta) and ``Rz Ry e_x`` (alpha), in the parent frame.
    """
    Rz = Rotation.from_euler("z", gamma_deg, degrees=True).as_matrix()
    Ry = Rotation.from_euler("y", beta_deg, degrees=True).as_matrix()
    W = np.column_stack([Rz @ Ry @ [1.0, 0, 0], Rz @ [0, 1.0, 0], [0, 0, 1.0]])
    return W * (math.pi / 180.0)


def cov_from_dof(pose: Pose, cov_dof) -> np.ndarray:
    """Convention covariance from one over the protocol's DOFs (alpha, beta, gamma [deg],
    X, Y, Z [mm])."""
    C = np.asarray(cov_dof, float)
    J = np.zeros((6, 6))
    J[:3, 3:] = np.eye(3)
    J[3:, :3] = euler_rate_matrix(*pose.euler_deg)
    return J @ C @ J.T


def bound_3sigma(cov3) -> float:
    """``3 sqrt(largest eigenvalue)`` of a 3x3 covariance: the 3-sigma bound along the worst
    direction. The norm of a Gaussian error stays below it with probability >= 97.1 % (equal
    eigenvalues: chi-square, 3 DOF, at 9) up to 99.7 % (one dominant direction)."""
    C = np.asarray(cov3, float)
    if not np.all(np.isfinite(C)):  # no usable uncertainty: unbounded (eigvalsh would raise)
        return math.inf
    return 3.0 * math.sqrt(max(float(np.linalg.eigvalsh(C)[-1]), 0.0))


@dataclass(frozen=True)
class PoseCov:
    """A :class:`Pose` ``T_a_b`` with the 6x6 covariance of its error (module Convention)."""

    pose: Pose
    cov: np.ndarray

    def __post_init__(self):
        object.__setattr__(self, "cov", _check_cov(self.cov, f"covariance of {self.pose.name}"))

    @classmethod
    def exact(cls, pose: Pose) -> PoseCov:
        return cls(pose, np.zeros((6, 6)))

    @property
    def name(self) -> str:
        return self.pose.name

    def __matmul__(self, other: PoseCov) -> PoseCov:
        if not isinstance(other, PoseCov):
            return NotImplemented
        T = self.pose @ other.pose  # refuses frames that do not chain
        R = self.pose.R
        Ja = np.eye(6)
        Ja[:3, 3:] = -skew(R @ other.pose.t_mm)
        Jb = np.zeros((6, 6))
        Jb[:3, :3] = R
        Jb[3:, 3:] = R
        return PoseCov(T, Ja @ self.cov @ Ja.T + Jb @ other.cov @ Jb.T)

    def inverse(self) -> PoseCov:
        R, t = self.pose.R, self.pose.t_mm
        J = np.zeros((6, 6))
        J[:3, :3] = -R.T
        J[:3, 3:] = -R.T @ skew(t)
        J[3:, 3:] = -R.T
        return PoseCov(self.pose.inverse(), J @ self.cov @ J.T)

    @property
    def position_3sigma_mm(self) -> float:
        return bound_3sigma(self.cov[:3, :3])

    @property
    def angle_3sigma_deg(self) -> float:
        return math.degrees(bound_3sigma(self.cov[3:, 3:]))

    def to_ros_dict(self) -> dict:
        """Position (m and mm), quaternion ``xyzw``, row-major 6x6 covariance in ROS order and
        units (m, rad) and in mm/rad, and the frame ids: what fills a
        ``geometry_msgs/PoseWithCovarianceStamped`` without reordering."""
        q = Rotation.from_matrix(self.pose.R).as_quat()
        q = q if q[3] >= 0 else -q
        S = np.diag([1e-3, 1e-3, 1e-3, 1.0, 1.0, 1.0])
        return {"frame_id": self.pose.to_frame, "child_frame_id": self.pose.from_frame,
                "position_m": (self.pose.t_mm * 1e-3).tolist(),
                "position_mm": self.pose.t_mm.tolist(),
                "orientation_xyzw": q.tolist(),
                "covariance_ros": (S @ self.cov @ S).ravel().tolist(),
                "covariance_units": "ROS: m^2, m*rad, rad^2; order x, y, z, rot x, rot y, rot z "
                                    "about the axes of frame_id; row-major 6x6",
                "covariance_mm_rad": self.cov.ravel().tolist(),
                "position_3sigma_mm": self.position_3sigma_mm,
                "angle_3sigma_deg": self.angle_3sigma_deg}
