"""Linear hand-eye solvers: the starts of the refinement in :mod:`cutterpose.calibration.handeye`.

Every method OpenCV offers (``cv2.calibrateHandEye``: Tsai, Park, Horaud, Andreff, Daniilidis;
``cv2.calibrateRobotWorldHandEye``: Shah, Li) and numpy versions of Tsai, Park and Shah (for
OpenCV builds without those bindings). Each takes the flange poses ``A_i = T_base_flange_i`` and
the target poses ``B_i = T_cam_plate_i`` and returns ``(X, Y) = (T_flange_cam, T_base_plate)``
with ``A_i X B_i = Y``.

References:
    R. Tsai, R. Lenz, IEEE Trans. Robotics and Automation 5(3), 1989.
    F. Park, B. Martin, "Robot sensor calibration: solving AX = XB on the Euclidean group",
    IEEE Trans. Robotics and Automation 10(5), 1994.
    M. Shah, J. Mechanisms and Robotics 5(3), 2013.
    OpenCV ``calibrateHandEye``, ``calibrateRobotWorldHandEye`` documentation.
"""

from __future__ import annotations

import numpy as np
from scipy.spatial.transform import Rotation

from ..errors import InputError
from ..geometry.pose import Pose, geodesic_deg, nearest_rotation

__all__ = ["OPENCV_METHODS", "NUMPY_METHODS", "MIN_PAIR_ROTATION_DEG", "stack_poses",
           "rigid_mean", "relative_motions", "translation_ax_xb", "numpy_start", "opencv_start"]

#: OpenCV's solvers, name -> (function, flag)
OPENCV_METHODS = {
    "tsai": ("calibrateHandEye", "CALIB_HAND_EYE_TSAI"),
    "park": ("calibrateHandEye", "CALIB_HAND_EYE_PARK"),
    "horaud": ("calibrateHandEye", "CALIB_HAND_EYE_HORAUD"),
    "andreff": ("calibrateHandEye", "CALIB_HAND_EYE_ANDREFF"),
    "daniilidis": ("calibrateHandEye", "CALIB_HAND_EYE_DANIILIDIS"),
    "shah": ("calibrateRobotWorldHandEye", "CALIB_ROBOT_WORLD_HAND_EYE_SHAH"),
    "li": ("calibrateRobotWorldHandEye", "CALIB_ROBOT_WORLD_HAND_EYE_LI"),
}
#: the same ideas in numpy, always run (OpenCV 5.0.0.93's bindings lacked the above)
NUMPY_METHODS = ("tsai", "park", "shah")
MIN_PAIR_ROTATION_DEG = 2.0


def stack_poses(poses) -> tuple[np.ndarray, np.ndarray]:
    return np.stack([p.R for p in poses]), np.stack([p.t_mm for p in poses])



def rigid_mean(poses: list[Pose], to_frame: str, from_frame: str) -> Pose:
    R, t = stack_poses(poses)
    return Pose(Rotation.from_matrix(R).mean().as_matrix(), t.mean(axis=0), to_frame, from_frame)


def relative_motions(A: list[Pose], B: list[Pose]):
    """Relative motions of all station pairs: ``M_A X = X M_B`` with ``M_A = A_j^-1 A_i``,
    ``M_B = B_j B_i^-1`` (from ``A_i X B_i = A_j X B_j``)."""
    RA, tA = stack_poses(A)
    RB, tB = stack_poses(B)
    i, j = np.triu_indices(len(A), 1)
    RMA = np.einsum("nki,nkj->nij", RA[j], RA[i])
    tMA = np.einsum("nki,nk->ni", RA[j], tA[i] - tA[j])
    RMB = np.einsum("nij,nkj->nik", RB[j], RB[i])
    tMB = tB[j] - np.einsum("nij,nj->ni", RMB, tB[i])
    keep = geodesic_deg(RMA, np.eye(3)) > MIN_PAIR_ROTATION_DEG
    return RMA[keep], tMA[keep], RMB[keep], tMB[keep]


def translation_ax_xb(RMA, tMA, RMB, tMB, RX) -> np.ndarray:
    """``(R_MA - I) t_X = R_X t_MB - t_MA``, stacked, least squares."""
    M = (RMA - np.eye(3)).reshape(-1, 3)
    rhs = (tMB @ RX.T - tMA).ravel()
    return np.linalg.lstsq(M, rhs, rcond=None)[0]


def numpy_start(name: str, A: list[Pose], B: list[Pose]) -> tuple[Pose, Pose]:
    """Park-Martin, Tsai-Lenz and Shah, for OpenCV builds without the hand-eye bindings
    (opencv-python 5.0.0.93 lacks ``calibrateHandEye``: opencv/opencv#29565).

    Park & Martin (1994): ``log R_MA = R_X log R_MB``, so ``R_X`` is the rotation nearest to
    ``sum a_k b_k^T``. Tsai & Lenz (1989): with ``P = 2 sin(theta/2) n`` of each motion,
    ``[P_A + P_B]x g = P_B - P_A`` for the Gibbs vector ``g = tan(theta_X/2) n_X``. Shah (2013):
    ``A_i X = Y C_i`` (``C_i = B_i^-1``) gives ``[I (x) R_A, -(R_C^T (x) I)] [vec R_X; vec R_Y]
    = 0``; the null vector, scaled to ``det = 1`` and projected on rotations, then the
    translations by linear least squares.
    """
    if name == "shah":
        RA, tA = stack_poses(A)
        C = [b.inverse() for b in B]
        RC, tC = stack_poses(C)
        I3 = np.eye(3)
        K = np.concatenate([np.concatenate([np.kron(I3, Ra), -np.kron(Rc.T, I3)], axis=1)
                            for Ra, Rc in zip(RA, RC)])
        v = np.linalg.svd(K)[2][-1]
        RX0, RY0 = v[:9].reshape(3, 3).T, v[9:].reshape(3, 3).T  # column-major vec
        d = np.cbrt(np.linalg.det(RX0))
        RX, RY = nearest_rotation(RX0 / d), nearest_rotation(RY0 / d)
        M = np.concatenate([np.concatenate([Ra, -I3], axis=1) for Ra in RA])
        rhs = np.concatenate([RY @ tc - ta for ta, tc in zip(tA, tC)])
        t = np.linalg.lstsq(M, rhs, rcond=None)[0]
        return Pose(RX, t[:3], "flange", "cam"), Pose(RY, t[3:], "base", "plate")
    RMA, tMA, RMB, tMB = relative_motions(A, B)
    a = Rotation.from_matrix(RMA).as_rotvec()
    b = Rotation.from_matrix(RMB).as_rotvec()
    if name == "park":
        RX = nearest_rotation(a.T @ b)
    elif name == "tsai":
        def mrp(r):
            th = np.linalg.norm(r, axis=1, keepdims=True)
            return 2.0 * np.sin(th / 2.0) * r / np.maximum(th, 1e-300)

        pa, pb = mrp(a), mrp(b)
        S = np.stack([_skew(v) for v in pa + pb])
        g = np.linalg.lstsq(S.reshape(-1, 3), (pb - pa).ravel(), rcond=None)[0]
        ng = np.linalg.norm(g)
        RX = Rotation.from_rotvec(2.0 * np.arctan(ng) * g / max(ng, 1e-300)).as_matrix()
    else:
        raise InputError(f"no numpy version of hand-eye method {name!r}")
    X = Pose(RX, translation_ax_xb(RMA, tMA, RMB, tMB, RX), "flange", "cam")
    return X, rigid_mean([a_ @ X @ b_ for a_, b_ in zip(A, B)], "base", "plate")


def _skew(v) -> np.ndarray:
    x, y, z = v
    return np.array([[0.0, -z, y], [z, 0.0, -x], [-y, x, 0.0]])


def opencv_start(name: str, A: list[Pose], B: list[Pose]) -> tuple[Pose, Pose]:
    """``(T_flange_cam, T_base_plate)`` from one OpenCV solver; ``A = T_base_flange``,
    ``B = T_cam_plate``."""
    import cv2

    fn, flag = OPENCV_METHODS[name]
    if not hasattr(cv2, fn):
        raise InputError(f"this OpenCV ({cv2.__version__}) has no cv2.{fn}")
    if fn == "calibrateHandEye":
        R, t = cv2.calibrateHandEye([a.R for a in A], [_col(a) for a in A], [b.R for b in B],
                                    [_col(b) for b in B], method=getattr(cv2, flag))
        X = Pose(np.asarray(R), np.ravel(t), "flange", "cam")
        Y = rigid_mean([a @ X @ b for a, b in zip(A, B)], "base", "plate")
        return X, Y
    # robot-world: world = plate; "base2gripper" = T_flange_base; outputs T_plate_base and
    # T_cam_flange
    Ai = [a.inverse() for a in A]
    Rbw, tbw, Rgc, tgc = cv2.calibrateRobotWorldHandEye(
        [b.R for b in B], [_col(b) for b in B], [a.R for a in Ai], [_col(a) for a in Ai],
        method=getattr(cv2, flag))
    Y = Pose(np.asarray(Rbw), np.ravel(tbw), "plate", "base").inverse()
    X = Pose(np.asarray(Rgc), np.ravel(tgc), "cam", "flange").inverse()
    return X, Y




def _col(p: Pose) -> np.ndarray:
    """A translation as the (3, 1) column OpenCV 5's robot-world solver insists on."""
    return np.asarray(p.t_mm, float).reshape(3, 1)
