"""Poses, the Euler-angle convention of the protocol, and the protocol's error figures.

Convention:
    A pose is the holder frame expressed in the camera frame::

        x_cam = R_cam_holder @ x_holder + t_cam_holder_mm

    ``R_cam_holder = Rz(gamma) @ Ry(beta) @ Rx(alpha)`` with alpha, beta, gamma in degrees
    (intrinsic Z-Y'-X'' angles, scipy's ``"ZYX"`` order with the angles given as
    ``[gamma, beta, alpha]``). Translations are in millimetres. Camera frame: x right, y down,
    z along the optical axis. The nominal pose is ``R = I``, ``t = (0, 0, 600)`` mm.

    Frames are named in variable names as ``R_<to>_<from>``; :class:`Pose` carries the names and
    refuses to compose poses whose frames do not chain.

References:
    ``shared/spec/PROTOCOL.md`` (section "Pose" and "Error figures").
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
from scipy.spatial.transform import Rotation

from ..errors import InputError

#: Gross-failure thresholds of the protocol.
FAIL_ROT_DEG = 2.0
FAIL_TRANS_MM = 10.0

NOMINAL_T_MM = np.array([0.0, 0.0, 600.0])


def rotation_from_euler_deg(alpha_deg, beta_deg, gamma_deg) -> np.ndarray:
    """``Rz(gamma) @ Ry(beta) @ Rx(alpha)``; vectorised over the angles' common shape.

    Returns an array of shape ``(..., 3, 3)``.
    """
    a, b, g = np.broadcast_arrays(
        np.asarray(alpha_deg, float), np.asarray(beta_deg, float), np.asarray(gamma_deg, float)
    )
    # the product written out (the same matrix as scipy's intrinsic "ZYX" to rounding): the
    # pose fits evaluate it in every residual call, where scipy's Rotation costs 10x more
    ca, sa = np.cos(np.radians(a)), np.sin(np.radians(a))
    cb, sb = np.cos(np.radians(b)), np.sin(np.radians(b))
    cg, sg = np.cos(np.radians(g)), np.sin(np.radians(g))
    R = np.empty(a.shape + (3, 3))
    R[..., 0, 0] = cg * cb
    R[..., 0, 1] = cg * sb * sa - sg * ca
    R[..., 0, 2] = cg * sb * ca + sg * sa
    R[..., 1, 0] = sg * cb
    R[..., 1, 1] = sg * sb * sa + cg * ca
    R[..., 1, 2] = sg * sb * ca - cg * sa
    R[..., 2, 0] = -sb
    R[..., 2, 1] = cb * sa
    R[..., 2, 2] = cb * ca
    return R


def euler_deg_from_rotation(R) -> np.ndarray:
    """Inverse of :func:`rotation_from_euler_deg`: ``(..., 3)`` array of (alpha, beta, gamma) deg.

    ``beta = asin(-R_20)``, ``alpha = atan2(R_21, R_22)``, ``gamma = atan2(R_10, R_00)`` (the
    same angles as scipy's intrinsic ``"ZYX"`` to ~1e-12 deg, 8x faster: every pose's ``dof``
    goes through it). Near ``beta = +-90 deg`` (gimbal lock) alpha and gamma are not unique;
    scipy then sets one of them to zero (those rows go through scipy). The protocol's ranges
    (|beta| <= 60 deg) stay far from it.
    """
    R = np.asarray(R, float)
    shape = R.shape[:-2]
    M = R.reshape(-1, 3, 3)
    s = -M[:, 2, 0]
    out = np.empty((len(M), 3))
    out[:, 0] = np.degrees(np.arctan2(M[:, 2, 1], M[:, 2, 2]))
    out[:, 1] = np.degrees(np.arcsin(np.clip(s, -1.0, 1.0)))
    out[:, 2] = np.degrees(np.arctan2(M[:, 1, 0], M[:, 0, 0]))
    lock = np.abs(s) > 1.0 - 1e-9
    if lock.any():
        out[lock] = Rotation.from_matrix(M[lock]).as_euler("ZYX", degrees=True)[:, ::-1]
    return out.reshape(*shape, 3)


def pose_from_plane_homography(H, K):
    """``(R, t)`` of a plane homography ``H ~ K [r1 r2 t]`` (plane ``Z = 0`` -> ideal pixels;
    ``t`` in the plane's units), or None when degenerate.

    Zhang (2000), section 3.1: ``[r1 r2 t] = lambda K^-1 H`` with ``lambda`` from the mean norm
    of the first two columns, its sign putting the plane in front (``t_z > 0``), ``r3 = r1 x
    r2``, the rotation made orthonormal (:func:`nearest_rotation`).
    """
    M = np.linalg.solve(np.asarray(K, float), np.asarray(H, float))
    norm = np.linalg.norm(M[:, 0]) + np.linalg.norm(M[:, 1])
    if not np.isfinite(norm) or norm <= 0:
        return None
    lam = 2.0 / norm
    if M[2, 2] * lam < 0:
        lam = -lam
    r1, r2, t = M[:, 0] * lam, M[:, 1] * lam, M[:, 2] * lam
    R = nearest_rotation(np.column_stack([r1, r2, np.cross(r1, r2)]))
    return (R, t) if np.all(np.isfinite(R)) and np.all(np.isfinite(t)) and t[2] > 0 else None


def nearest_rotation(M) -> np.ndarray:
    """The rotation closest to ``M`` in Frobenius norm (orthogonal polar factor, det = +1)."""
    M = np.asarray(M, float)
    U, _, Vt = np.linalg.svd(M)
    d = np.sign(np.linalg.det(U @ Vt))
    D = np.ones(M.shape[:-2] + (3,))
    D[..., 2] = d
    return (U * D[..., None, :]) @ Vt


def wrap_deg(angle_deg):
    """Wrap angles to (-180, 180] degrees."""
    a = np.mod(np.asarray(angle_deg, float) + 180.0, 360.0) - 180.0
    return np.where(a == -180.0, 180.0, a)


def geodesic_deg(R_a, R_b) -> np.ndarray:
    """Rotation angle of ``R_a^T R_b`` in degrees (the protocol's geodesic error)."""
    R_a = np.asarray(R_a, float)
    R_b = np.asarray(R_b, float)
    tr = np.einsum("...ji,...ji->...", R_a, R_b)
    # arccos loses half the digits near 0; the arctan2 form of the same angle does not.
    rel = np.swapaxes(R_a, -1, -2) @ R_b
    axis = np.stack(
        [rel[..., 2, 1] - rel[..., 1, 2], rel[..., 0, 2] - rel[..., 2, 0],
         rel[..., 1, 0] - rel[..., 0, 1]],
        axis=-1,
    )
    return np.degrees(np.arctan2(0.5 * np.linalg.norm(axis, axis=-1), 0.5 * (tr - 1.0)))


@dataclass(frozen=True)
class Pose:
    """A rigid transform ``x_<to> = R @ x_<from> + t`` with named frames.

    Parameters
    ----------
    R : (3, 3) rotation matrix.
    t_mm : (3,) translation in millimetres.
    to_frame, from_frame : frame names; the default is the holder in the camera frame.

    Examples
    --------
    >>> T = Pose.from_euler(2.0, -1.0, 0.5, 3.0, -4.0, 600.0)   # deg, deg, deg, mm, mm, mm
    >>> T.name, T.inverse().name
    ('T_cam_holder', 'T_holder_cam')
    >>> [round(float(v), 9) for v in T.dof]
    [2.0, -1.0, 0.5, 3.0, -4.0, 600.0]
    >>> T.apply([[0.0, 0.0, 0.0]])                  # the holder's origin in the camera frame
    array([[  3.,  -4., 600.]])
    >>> T.inverse().apply(T.apply([[10.0, 20.0, 0.0]])).round(9) + 0.0
    array([[10., 20.,  0.]])
    """

    R: np.ndarray
    t_mm: np.ndarray
    to_frame: str = "cam"
    from_frame: str = "holder"

    def __post_init__(self):
        R = np.asarray(self.R, float)
        t = np.asarray(self.t_mm, float).reshape(-1)
        if R.shape != (3, 3) or t.shape != (3,):
            raise InputError(f"a pose needs R of shape (3, 3) and t of shape (3,), got "
                             f"{R.shape} and {t.shape}")
        if not (np.all(np.isfinite(R)) and np.all(np.isfinite(t))):
            raise InputError("a pose must be finite (R or t holds NaN or inf)")
        if abs(np.linalg.det(R) - 1.0) > 1e-6 or np.abs(R.T @ R - np.eye(3)).max() > 1e-6:
            raise InputError("R is not a rotation matrix (R^T R != I or det R != 1)")
        object.__setattr__(self, "R", R)
        object.__setattr__(self, "t_mm", t)

    @classmethod
    def from_euler(cls, alpha_deg, beta_deg, gamma_deg, X_mm, Y_mm, Z_mm, **frames) -> Pose:
        """Pose from the protocol's six DOFs."""
        return cls(rotation_from_euler_deg(alpha_deg, beta_deg, gamma_deg),
                   np.array([X_mm, Y_mm, Z_mm], float), **frames)

    @classmethod
    def nominal(cls) -> Pose:
        """The protocol's nominal pose: ``R = I``, ``t = (0, 0, 600)`` mm."""
        return cls(np.eye(3), NOMINAL_T_MM.copy())

    @classmethod
    def from_matrix(cls, T, to_frame: str = "cam", from_frame: str = "holder") -> Pose:
        """Pose from a 4x4 homogeneous matrix ``T_<to>_<from>`` (last row ``0 0 0 1``)."""
        T = np.asarray(T, float)
        if T.shape != (4, 4):
            raise InputError(f"a 4x4 transform is needed, got shape {T.shape}")
        if np.abs(T[3] - [0.0, 0.0, 0.0, 1.0]).max() > 1e-9:
            raise InputError(f"the last row of a 4x4 transform must be 0 0 0 1, got "
                             f"{T[3].tolist()}")
        return cls(T[:3, :3], T[:3, 3], to_frame, from_frame)

    @property
    def matrix(self) -> np.ndarray:
        """The 4x4 homogeneous matrix ``T_<to>_<from>`` (mm)."""
        T = np.eye(4)
        T[:3, :3] = self.R
        T[:3, 3] = self.t_mm
        return T

    @property
    def name(self) -> str:
        """``T_<to>_<from>``."""
        return f"T_{self.to_frame}_{self.from_frame}"

    def with_frames(self, to_frame: str, from_frame: str) -> Pose:
        """The same transform under other frame names (e.g. a pose read from a file)."""
        return Pose(self.R, self.t_mm, to_frame, from_frame)

    @property
    def euler_deg(self) -> np.ndarray:
        """(alpha, beta, gamma) in degrees."""
        return euler_deg_from_rotation(self.R)

    @property
    def dof(self) -> np.ndarray:
        """The six DOFs (alpha, beta, gamma [deg], X, Y, Z [mm])."""
        return np.concatenate([self.euler_deg, self.t_mm])

    def apply(self, points_mm) -> np.ndarray:
        """Transform ``(..., 3)`` points from ``from_frame`` into ``to_frame``."""
        return np.asarray(points_mm, float) @ self.R.T + self.t_mm

    def inverse(self) -> Pose:
        return Pose(self.R.T, -self.R.T @ self.t_mm, self.from_frame, self.to_frame)

    def __matmul__(self, other: Pose) -> Pose:
        if not isinstance(other, Pose):
            return NotImplemented
        if self.from_frame != other.to_frame:
            raise InputError(
                f"cannot compose T_{self.to_frame}_{self.from_frame} with "
                f"T_{other.to_frame}_{other.from_frame}: frames '{self.from_frame}' and "
                f"'{other.to_frame}' differ")
        return Pose(self.R @ other.R, self.R @ other.t_mm + self.t_mm,
                    self.to_frame, other.from_frame)

    def to_dict(self) -> dict:
        a, b, g = self.euler_deg
        return {
            f"R_{self.to_frame}_{self.from_frame}": self.R.tolist(),
            f"t_{self.to_frame}_{self.from_frame}_mm": self.t_mm.tolist(),
            "alpha_deg": float(a), "beta_deg": float(b), "gamma_deg": float(g),
            "X_mm": float(self.t_mm[0]), "Y_mm": float(self.t_mm[1]),
            "Z_mm": float(self.t_mm[2]),
        }


@dataclass
class PoseErrors:
    """Protocol error figures of estimates against the truth, vectorised over trials.

    Attributes
    ----------
    dof : (T, 6) estimate - truth per DOF: alpha, beta, gamma wrapped to (-180, 180] deg;
        X, Y, Z in mm.
    rot_deg : (T,) geodesic rotation error.
    trans_mm : (T,) translation error norm.
    failed : (T,) gross failure (rot > 2 deg or trans > 10 mm, or no estimate: NaN input).
    """

    dof: np.ndarray
    rot_deg: np.ndarray
    trans_mm: np.ndarray
    failed: np.ndarray = field(default=None)


def pose_errors(R_true, t_true_mm, R_est, t_est_mm) -> PoseErrors:
    """Error figures of the protocol; inputs ``(T, 3, 3)``/``(T, 3)`` or single poses.

    A NaN estimate (a method that gave nothing) yields NaN errors and ``failed = True``.
    """
    R_true = np.asarray(R_true, float).reshape(-1, 3, 3)
    R_est = np.asarray(R_est, float).reshape(-1, 3, 3)
    t_true = np.asarray(t_true_mm, float).reshape(-1, 3)
    t_est = np.asarray(t_est_mm, float).reshape(-1, 3)
    valid = np.all(np.isfinite(R_est), axis=(1, 2)) & np.all(np.isfinite(t_est), axis=1)
    T = len(R_true)
    dof = np.full((T, 6), np.nan)
    rot = np.full(T, np.nan)
    if valid.any():
        e_true = euler_deg_from_rotation(R_true[valid])
        e_est = euler_deg_from_rotation(R_est[valid])
        dof[valid, :3] = wrap_deg(e_est - e_true)
        rot[valid] = geodesic_deg(R_true[valid], R_est[valid])
    dof[:, 3:] = t_est - t_true
    trans = np.linalg.norm(t_est - t_true, axis=1)
    with np.errstate(invalid="ignore"):
        failed = ~valid | ~(rot <= FAIL_ROT_DEG) | ~(trans <= FAIL_TRANS_MM)
    return PoseErrors(dof=dof, rot_deg=rot, trans_mm=trans, failed=failed)


def pixel_jacobian(R_cam_holder, t_cam_holder_mm, points_holder_mm, K) -> np.ndarray:
    """Analytic Jacobian of the projected pixels w.r.t. (alpha, beta, gamma [deg], X, Y, Z [mm]).

    The pixels are the ideal (undistorted) ones of the pinhole ``K``: every camera model's
    pose computation works on them. Used for the Cramer-Rao bound of the protocol and for the
    per-DOF std of a measurement. Returns ``(T, 2N, 6)``, rows ordered
    ``u_1, v_1, u_2, v_2, ...``; vectorised over T poses.
    """
    R = np.asarray(R_cam_holder, float).reshape(-1, 3, 3)
    t = np.asarray(t_cam_holder_mm, float).reshape(-1, 3)
    P = np.asarray(points_holder_mm, float)
    T, N = len(R), len(P)
    # R = Rz(gamma) Ry(beta) Rx(alpha): dR/dalpha = R [e_x]x, dR/dbeta = [Rz(gamma) e_y]x R,
    # dR/dgamma = [e_z]x R, so the points' derivatives are cross products (no angle matrices)
    Rt = R.transpose(0, 2, 1)
    RP = P @ Rt                                                   # (T, N, 3)
    X = RP + t[:, None, :]
    ex_P = np.zeros_like(P)
    ex_P[:, 1], ex_P[:, 2] = -P[:, 2], P[:, 1]                    # e_x x P
    dX = np.empty((T, N, 3, 3))                                   # [..., xyz, angle]
    dX[..., 0] = ex_P @ Rt
    g = np.arctan2(R[:, 1, 0], R[:, 0, 0])
    cg, sg = np.cos(g)[:, None], np.sin(g)[:, None]               # Rz e_y = (-sg, cg, 0)
    dX[..., 0, 1] = cg * RP[..., 2]
    dX[..., 1, 1] = sg * RP[..., 2]
    dX[..., 2, 1] = -sg * RP[..., 1] - cg * RP[..., 0]
    dX[..., 0, 2] = -RP[..., 1]                                   # e_z x RP
    dX[..., 1, 2] = RP[..., 0]
    dX[..., 2, 2] = 0.0
    dX *= np.pi / 180.0
    fx, s, fy = K[0, 0], K[0, 1], K[1, 1]
    iz = 1.0 / X[..., 2]
    x, y = X[..., 0] * iz, X[..., 1] * iz
    # du/dX = (fx, s, -(fx x + s y)) / z, dv/dX = (0, fy, -fy y) / z (x, y normalised)
    du = np.stack([fx * iz, s * iz, -(fx * x + s * y) * iz], axis=-1)
    dv = np.stack([np.zeros_like(iz), fy * iz, -fy * y * iz], axis=-1)
    J = np.empty((T, N, 2, 6))
    J[..., 0, :3] = (du[..., None, :] @ dX)[..., 0, :]
    J[..., 1, :3] = (dv[..., None, :] @ dX)[..., 0, :]
    J[..., 0, 3:] = du
    J[..., 1, 3:] = dv
    return J.reshape(T, -1, 6)
