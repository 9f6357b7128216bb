"""The error budget (issue 10, item 4): how far off the pose may be, from what, and whether
that is within the robot's tolerance.

A budget is a set of named contributions, each a (6, 6) covariance of the pose's DOFs, summed.
Each pose method makes its own (:meth:`cutterpose.solvers.method.PoseMethod.budget`, beside the
method): the corner methods' (``dm``, ``dm+``, PnP: :mod:`cutterpose.solvers.corner_budget`),
``dm+r``'s (:mod:`cutterpose.solvers.radius_budget`), ``dm+b``'s
(:mod:`cutterpose.solvers.edge_band`). This module holds what they share and imports none of
them.

The 6 x 6 pose covariance is then given in the camera frame as ``covariance_cam`` in the order
``(x, y, z [mm], rx, ry, rz [rad])``: the translation ``t_cam_holder`` and a small rotation about
the holder frame's own axes, ``R_true = R_est exp([w]x)`` (the order of the hand-eye file's
covariance, PROTOCOL.md, Robot cell). At a grasp point ``p`` (holder frame; default the origin,
the centre of the pocket's top plane) the position ``R p + t`` has covariance
``A C A^T`` with ``A = [I, -R [p]x]``. The verdict takes the worst direction:
``position_3sigma_mm = 3 sqrt(lambda_max)`` of that 3 x 3 block and ``angle_3sigma_deg`` the same
of the rotation block, and refuses above the tolerance: 1 mm (the robot's, seed paper 2.3) and
0.3 deg (a rotation error of ``theta`` moves the pocket's ends, 200 mm from the origin, by
``200 theta``: 0.3 deg is 1 mm there, the same tolerance carried to the farthest point the
gripper's seats reach).

Convention:
    DOF covariances in (alpha, beta, gamma [deg], X, Y, Z [mm], r [mm]);
    ``covariance_cam`` as above. 3-sigma figures are of the worst direction.

References:
    Kay, *Fundamentals of Statistical Signal Processing I* (1993), ch. 3; Hartley & Zisserman,
    *Multiple View Geometry*, 2nd ed., 5.2 (forward propagation of covariance).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np

from .geometry.pose import rotation_from_euler_deg

__all__ = ["ErrorBudget", "Tolerance", "budget_from_dof_cov", "dof_to_cam_jacobian",
           "COVARIANCE_CAM_ORDER"]

COVARIANCE_CAM_ORDER = ("x_mm", "y_mm", "z_mm", "rx_rad", "ry_rad", "rz_rad")


@dataclass(frozen=True)
class Tolerance:
    """When the budget refuses: 3-sigma position at the grasp point and rotation."""

    position_mm: float = 1.0
    angle_deg: float = 0.3
    k_sigma: float = 3.0


@dataclass
class ErrorBudget:
    """The budget of one measurement (module doc).

    Attributes
    ----------
    parts : name -> (6, 6) DOF covariance of each contribution (deg, mm).
    dof_cov : (6, 6) their sum; covariance_cam : (6, 6) the same in ``COVARIANCE_CAM_ORDER``.
    grasp_point_mm : (3,) holder-frame point the position figure is for.
    position_3sigma_mm, angle_3sigma_deg : worst-direction 3-sigma figures.
    radius_mm, radius_std_mm : the edge radius and its std (NaN without the edge model).
    residuals_px : (n, 2) the residual vectors of the method's fit (ideal px: the corners', or
        the band's along the edge normals) that the verdict judges.
    """

    parts: dict
    dof_cov: np.ndarray
    covariance_cam: np.ndarray
    grasp_point_mm: np.ndarray
    position_3sigma_mm: float
    angle_3sigma_deg: float
    radius_mm: float = math.nan
    radius_std_mm: float = math.nan
    per_part_3sigma: dict = field(default_factory=dict)
    residuals_px: np.ndarray = field(default_factory=lambda: np.zeros((0, 2)))

    @property
    def std_dof(self) -> np.ndarray:
        return np.sqrt(np.clip(np.diag(self.dof_cov), 0, None))

    def exceeds(self, tol: Tolerance) -> str:
        """The reason for refusing, or '' when within the tolerance."""
        k = tol.k_sigma
        worst = max(self.per_part_3sigma.items(), key=lambda kv: kv[1][0] / tol.position_mm
                    + kv[1][1] / tol.angle_deg, default=("?", (0, 0)))[0]
        if not (self.position_3sigma_mm <= tol.position_mm):
            return (f"error budget: position at the grasp point uncertain by "
                    f"{self.position_3sigma_mm:.2f} mm ({k:g} sigma) > {tol.position_mm} mm; "
                    f"largest part: {worst}")
        if not (self.angle_3sigma_deg <= tol.angle_deg):
            return (f"error budget: rotation uncertain by {self.angle_3sigma_deg:.3f} deg "
                    f"({k:g} sigma) > {tol.angle_deg} deg; largest part: {worst}")
        return ""

    def to_dict(self) -> dict:
        def f(x):
            return None if not math.isfinite(float(x)) else float(x)

        names = ("alpha_deg", "beta_deg", "gamma_deg", "X_mm", "Y_mm", "Z_mm")
        return {"position_3sigma_mm": f(self.position_3sigma_mm),
                "angle_3sigma_deg": f(self.angle_3sigma_deg),
                "grasp_point_holder_mm": [float(v) for v in self.grasp_point_mm],
                "edge_radius_mm": f(self.radius_mm), "edge_radius_std_mm": f(self.radius_std_mm),
                "std": {n: f(v) for n, v in zip(names, self.std_dof)},
                "parts": {k: {"std": {n: f(v) for n, v in zip(
                    names, np.sqrt(np.clip(np.diag(c), 0, None)))},
                    "position_3sigma_mm": f(self.per_part_3sigma[k][0]),
                    "angle_3sigma_deg": f(self.per_part_3sigma[k][1])}
                    for k, c in self.parts.items()},
                "covariance_cam": {"order": list(COVARIANCE_CAM_ORDER),
                                   "matrix": self.covariance_cam.tolist()}}


def dof_to_cam_jacobian(dof) -> np.ndarray:
    """(6, 6) d (t [mm], w [rad]) / d (alpha, beta, gamma [deg], X, Y, Z [mm]) at ``dof``,
    ``w`` the rotation about the holder's own axes (``R(dof + e) = R exp([w]x)``)."""
    from scipy.spatial.transform import Rotation

    dof = np.asarray(dof, float)
    R = rotation_from_euler_deg(*dof[:3])
    A = np.zeros((6, 6))
    A[:3, 3:] = np.eye(3)
    h = 1e-4
    for k in range(3):
        e = dof[:3].copy()
        e[k] += h
        e2 = dof[:3].copy()
        e2[k] -= h
        w1 = Rotation.from_matrix(R.T @ rotation_from_euler_deg(*e)).as_rotvec()
        w2 = Rotation.from_matrix(R.T @ rotation_from_euler_deg(*e2)).as_rotvec()
        A[3:, k] = (w1 - w2) / (2 * h)
    return A


def _figures(cov_cam: np.ndarray, R: np.ndarray, p: np.ndarray, k: float):
    if not np.all(np.isfinite(cov_cam)):  # a singular fit's part: refuse, not a LinAlgError
        return math.inf, math.inf
    px = np.array([[0, -p[2], p[1]], [p[2], 0, -p[0]], [-p[1], p[0], 0]])
    A = np.hstack([np.eye(3), -R @ px])
    Cp = A @ cov_cam @ A.T
    pos = k * math.sqrt(max(float(np.linalg.eigvalsh(Cp)[-1]), 0.0))
    ang = k * math.degrees(math.sqrt(max(float(np.linalg.eigvalsh(cov_cam[3:, 3:])[-1]), 0.0)))
    return pos, ang


def budget_from_dof_cov(parts: dict, dof, grasp_point_mm=None, tol: Tolerance = Tolerance(),
                        radius_mm: float = math.nan, radius_std_mm: float = math.nan,
                        residuals_px=None) -> ErrorBudget:
    """An :class:`ErrorBudget` from named (6, 6) DOF covariances at the pose ``dof``, with the
    fit's ``residuals_px`` ((n, 2) ideal px) the verdict judges."""
    p = np.zeros(3) if grasp_point_mm is None else np.asarray(grasp_point_mm, float).reshape(3)
    dof = np.asarray(dof, float)
    total = sum(parts.values()) if parts else np.zeros((6, 6))
    A = dof_to_cam_jacobian(dof)
    R = rotation_from_euler_deg(*dof[:3])
    with np.errstate(invalid="ignore"):  # inf * 0 in a non-finite part: NaN, refused below
        cam = A @ total @ A.T
        per = {k: _figures(A @ c @ A.T, R, p, tol.k_sigma) for k, c in parts.items()}
    pos, ang = _figures(cam, R, p, tol.k_sigma)
    r = np.zeros((0, 2)) if residuals_px is None else np.asarray(residuals_px, float)
    return ErrorBudget(parts, total, cam, p, pos, ang, radius_mm, radius_std_mm, per, r)
