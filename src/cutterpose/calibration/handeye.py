"""Eye-in-hand calibration: the camera on the flange, the circle plate fixed in the cell.

The robot moves the camera through stations ``i``; at each the controller reports
``T_base_flange_i`` and the camera sees the plate, ``T_cam_plate_i``. With the unknowns
``X = T_flange_cam`` and ``Y = T_base_plate``, every station satisfies

    T_base_flange_i @ X @ T_cam_plate_i = Y        (the AX = XB / AX = YB problem).

Pipeline:
    1. Per station: plate detection (:func:`cutterpose.calibration.intrinsics.detect_plate`),
       ``T_cam_plate_i`` by PnP (IPPE + Levenberg-Marquardt on the ideal pixels), the
       perspective bias of the circle centres predicted at that pose and removed, PnP again.
       The pooled PnP residual gives the pixel noise ``sigma_px``.
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
       plate pose in the base frame against ``Y`` (mm, deg), and a one-line verdict.

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
from scipy.optimize import least_squares
from scipy.spatial.transform import Rotation
from scipy.stats import chi2

from ..errors import DegenerateInputError, FeatureError, HandEyeFileError, InputError
from ..geometry.camera import Camera
from ..geometry.jsonfile import read_json
from ..geometry.pose import Pose, geodesic_deg, nearest_rotation
from .plate import CirclePlate, ellipse_center_bias_px

__all__ = ["HandEye", "HandEyeResult", "StationResidual", "calibrate_handeye",
           "handeye_from_images", "load_handeye", "save_handeye", "OPENCV_METHODS",
           "check_station_rotations", "NUMPY_METHODS", "BundleResult",
           "bundle_adjust_handeye"]

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
#: the same ideas in numpy, always run (OpenCV 5.0.0.93's Python bindings lack the above)
NUMPY_METHODS = ("tsai", "park", "shah")
MIN_PAIR_ROTATION_DEG = 2.0
MIN_AXIS_SPREAD_DEG = 3.0
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

    def to_dict(self) -> dict:
        return {"name": self.name, "rms_px": self.rms_px, "position_mm": self.position_mm,
                "angle_deg": self.angle_deg, "chi2": self.chi2, "used": self.used,
                "distrust": self.distrust}


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
        except (InputError, TypeError, ValueError) as e:
            raise HandEyeFileError(f"{path}: field '{key}': {e}") from None
    try:
        C = np.asarray(d.get("covariance"), float)
    except (TypeError, ValueError):
        C = np.zeros(0)
    if C.shape != (6, 6) or not np.all(np.isfinite(C)):
        raise HandEyeFileError(f"{path}: field 'covariance' must be a finite 6x6 matrix")
    C = 0.5 * (C + C.T)
    if np.linalg.eigvalsh(C).min() < -1e-12 * max(1.0, np.abs(C).max()):
        raise HandEyeFileError(f"{path}: field 'covariance' is not positive semi-definite")
    return HandEye(poses["T_flange_cam"], poses["T_base_plate"], C)


# ------------------------------------------------------------------------------------------
def _stack(poses) -> tuple[np.ndarray, np.ndarray]:
    return np.stack([p.R for p in poses]), np.stack([p.t_mm for p in poses])


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
    R, _ = _stack(T_base_flange)
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


def _pnp(camera: Camera, plate_pts: np.ndarray, obs_px: np.ndarray) -> Pose:
    import cv2

    ideal = camera.undistort_px(obs_px).astype(np.float64)
    obj = plate_pts.astype(np.float64)
    K = camera.K
    ok, rv, tv = cv2.solvePnP(obj, ideal, K, None, flags=cv2.SOLVEPNP_IPPE)
    if not ok:
        raise FeatureError("plate pose not found (PnP failed)")
    rv, tv = cv2.solvePnPRefineLM(obj, ideal, K, None, rv, tv)
    return Pose(Rotation.from_rotvec(rv.ravel()).as_matrix(), tv.ravel(), "cam", "plate")


def _rigid_mean(poses: list[Pose], to_frame: str, from_frame: str) -> Pose:
    R, t = _stack(poses)
    return Pose(Rotation.from_matrix(R).mean().as_matrix(), t.mean(axis=0), to_frame, from_frame)


def _motions(A: list[Pose], B: list[Pose]):
    """Relative motions of all station pairs: ``M_A X = X M_B`` with ``M_A = A_j^-1 A_i``,
    ``M_B = B_j B_i^-1`` (from ``A_i X B_i = A_j X B_j``)."""
    RA, tA = _stack(A)
    RB, tB = _stack(B)
    i, j = np.triu_indices(len(A), 1)
    RMA = np.einsum("nki,nkj->nij", RA[j], RA[i])
    tMA = np.einsum("nki,nk->ni", RA[j], tA[i] - tA[j])
    RMB = np.einsum("nij,nkj->nik", RB[j], RB[i])
    tMB = tB[j] - np.einsum("nij,nj->ni", RMB, tB[i])
    keep = geodesic_deg(RMA, np.eye(3)) > MIN_PAIR_ROTATION_DEG
    return RMA[keep], tMA[keep], RMB[keep], tMB[keep]


def _translation_ax_xb(RMA, tMA, RMB, tMB, RX) -> np.ndarray:
    """``(R_MA - I) t_X = R_X t_MB - t_MA``, stacked, least squares."""
    M = (RMA - np.eye(3)).reshape(-1, 3)
    rhs = (tMB @ RX.T - tMA).ravel()
    return np.linalg.lstsq(M, rhs, rcond=None)[0]


def _numpy_start(name: str, A: list[Pose], B: list[Pose]) -> tuple[Pose, Pose]:
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
        RA, tA = _stack(A)
        C = [b.inverse() for b in B]
        RC, tC = _stack(C)
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
    RMA, tMA, RMB, tMB = _motions(A, B)
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
    X = Pose(RX, _translation_ax_xb(RMA, tMA, RMB, tMB, RX), "flange", "cam")
    return X, _rigid_mean([a_ @ X @ b_ for a_, b_ in zip(A, B)], "base", "plate")


def _skew(v) -> np.ndarray:
    x, y, z = v
    return np.array([[0.0, -z, y], [z, 0.0, -x], [-y, x, 0.0]])


def _opencv_start(name: str, A: list[Pose], B: list[Pose]) -> tuple[Pose, Pose]:
    """``(T_flange_cam, T_base_plate)`` from one OpenCV solver; ``A = T_base_flange``,
    ``B = T_cam_plate``."""
    import cv2

    fn, flag = OPENCV_METHODS[name]
    if not hasattr(cv2, fn):
        raise InputError(f"this OpenCV ({cv2.__version__}) has no cv2.{fn}")
    if fn == "calibrateHandEye":
        R, t = cv2.calibrateHandEye([a.R for a in A], [a.t_mm for a in A], [b.R for b in B],
                                    [b.t_mm for b in B], method=getattr(cv2, flag))
        X = Pose(np.asarray(R), np.ravel(t), "flange", "cam")
        Y = _rigid_mean([a @ X @ b for a, b in zip(A, B)], "base", "plate")
        return X, Y
    # robot-world: world = plate; "base2gripper" = T_flange_base; outputs T_plate_base and
    # T_cam_flange
    Ai = [a.inverse() for a in A]
    Rbw, tbw, Rgc, tgc = cv2.calibrateRobotWorldHandEye(
        [b.R for b in B], [b.t_mm for b in B], [a.R for a in Ai], [a.t_mm for a in Ai],
        method=getattr(cv2, flag))
    Y = Pose(np.asarray(Rbw), np.ravel(tbw), "plate", "base").inverse()
    X = Pose(np.asarray(Rgc), np.ravel(tgc), "cam", "flange").inverse()
    return X, Y


class _Problem:
    """Residuals of the joint refinement, vectorised over stations."""

    def __init__(self, camera: Camera, plate_pts: np.ndarray, A: list[Pose], obs: np.ndarray,
                 bias: np.ndarray, sigma_px: float, rep_mm: float, rep_rad: float):
        self.camera, self.P = camera, plate_pts
        self.RA, self.tA = _stack(A)
        self.obs = obs - bias  # observed centres with the perspective bias removed
        self.sigma_px, self.rep_mm, self.rep_rad = sigma_px, rep_mm, rep_rad
        self.W = None

    def project(self, X: Pose, Y: Pose, RA=None, tA=None) -> np.ndarray:
        """(n, N, 2) pixels of the plate at ``T_cam_plate_i = X^-1 A_i^-1 Y``."""
        RA = self.RA if RA is None else RA
        tA = self.tA if tA is None else tA
        # A_i^-1 Y: R = RA^T RY, t = RA^T (tY - tA)
        R1 = np.einsum("nji,jk->nik", RA, Y.R)
        t1 = np.einsum("nji,nj->ni", RA, Y.t_mm - tA)
        R = np.einsum("ji,njk->nik", X.R, R1)
        t = (t1 - X.t_mm) @ X.R
        pts = np.einsum("nij,mj->nmi", R, self.P) + t[:, None, :]
        return self.camera.project(pts)

    def set_weights(self, X: Pose, Y: Pose) -> None:
        """Whitening of each station from the pixel noise and the robot's repeatability,
        linearised at ``(X, Y)`` (central differences of the flange pose, in base axes)."""
        n, N = len(self.RA), len(self.P)
        G = np.zeros((n, 2 * N, 6))
        for k in range(6):
            d = np.zeros(6)
            h = 1e-3 if k < 3 else 1e-6
            d[k] = h
            cols = []
            for s in (1.0, -1.0):
                Rd = Rotation.from_rotvec(s * d[3:]).as_matrix()
                cols.append(self.project(X, Y, Rd @ self.RA, self.tA + s * d[:3]))
            G[:, :, k] = ((cols[0] - cols[1]) / (2 * h)).reshape(n, -1)
        Cr = np.diag([self.rep_mm ** 2] * 3 + [self.rep_rad ** 2] * 3)
        S = self.sigma_px ** 2 * np.eye(2 * N) + G @ Cr @ G.transpose(0, 2, 1)
        L = np.linalg.cholesky(S)
        self.W = np.linalg.inv(L)  # (n, 2N, 2N): W S W^T = I

    def residuals(self, X: Pose, Y: Pose) -> np.ndarray:
        """(n, 2N) whitened residuals (raw pixels before :meth:`set_weights`)."""
        r = (self.project(X, Y) - self.obs).reshape(len(self.RA), -1)
        return r if self.W is None else np.einsum("nij,nj->ni", self.W, r)


def _compose(X0: Pose, Y0: Pose, x: np.ndarray) -> tuple[Pose, Pose]:
    """Parameters ``(dphi_X, t_X, dphi_Y, t_Y)``, rotations perturbed on the left."""
    X = Pose(Rotation.from_rotvec(x[:3]).as_matrix() @ X0.R, x[3:6], "flange", "cam")
    Y = Pose(Rotation.from_rotvec(x[6:9]).as_matrix() @ Y0.R, x[9:12], "base", "plate")
    return X, Y


def _refine(prob: _Problem, X0: Pose, Y0: Pose, used: np.ndarray, loss: str):
    x0 = np.concatenate([np.zeros(3), X0.t_mm, np.zeros(3), Y0.t_mm])

    def fun(x):
        X, Y = _compose(X0, Y0, x)
        return prob.residuals(X, Y)[used].ravel()

    res = least_squares(fun, x0, loss=loss, f_scale=3.0, method="trf", x_scale="jac",
                        xtol=1e-12, ftol=1e-12, gtol=1e-12, max_nfev=200)
    X, Y = _compose(X0, Y0, res.x)
    return X, Y, res


@dataclass
class BundleResult:
    """Result of :func:`bundle_adjust_handeye`.

    ``cov_flange_cam`` / ``cov_base_plate``: 6x6 (x, y, z [mm], rotation [rad] about the
    frame's own axes, PROTOCOL.md), marginalised over the station corrections.
    ``flange_corrections``: (n, 6) estimated errors of the reported flange poses (translation
    [mm], rotation [rad] about the base axes; ``true = Exp(dphi) R_reported``,
    ``t_reported + dt``). ``cost``: half the sum of squared whitened residuals.
    """

    T_flange_cam: Pose
    T_base_plate: Pose
    cov_flange_cam: np.ndarray
    cov_base_plate: np.ndarray
    flange_corrections: np.ndarray
    cost: float
    nfev: int


def _predicted_bias(camera: Camera, plate: CirclePlate, A: list[Pose], X: Pose,
                    Y: Pose) -> np.ndarray:
    return np.stack([np.nan_to_num(ellipse_center_bias_px(camera, X.inverse() @ a.inverse() @ Y,
                                                          plate)) for a in A])


def _ba_sparsity(n: int, N: int):
    """Which parameters each residual depends on: a station's 2N image rows on the 12 global
    parameters and its own 6 corrections, its 6 prior rows on those 6 only."""
    from scipy.sparse import lil_matrix

    S = lil_matrix((n * (2 * N + 6), 12 + 6 * n), dtype=np.int8)
    for i in range(n):
        rows = slice(i * 2 * N, (i + 1) * 2 * N)
        S[rows, :12] = 1
        S[rows, 12 + 6 * i: 18 + 6 * i] = 1
        S[n * 2 * N + 6 * i: n * 2 * N + 6 * i + 6, 12 + 6 * i: 18 + 6 * i] = 1
    return S.tocsr()


def bundle_adjust_handeye(T_base_flange: list[Pose], points_px, camera: Camera,
                          X0: Pose, Y0: Pose, *, plate: CirclePlate | None = None,
                          sigma_px: float, repeatability_mm: float,
                          repeatability_deg: float, bias_px=None, loss: str = "soft_l1",
                          f_scale: float = 3.0, used=None) -> BundleResult:
    """Maximum-likelihood hand-eye calibration under plate *and* robot noise (bundle
    adjustment).

    Unknowns: ``X = T_flange_cam``, ``Y = T_base_plate`` and, per station, the 6 corrections
    ``d_i = (dt_i, dphi_i)`` of the reported flange pose (``T_base_flange_true = (Exp(dphi_i)
    R_i, t_i + dt_i)``, the noise model of :class:`cutterpose.robot.cell.RobotCell`). Cost:
    ``sum_i rho(|proj(X^-1 A_i(d_i)^-1 Y) - obs_i|^2 / sigma_px^2) + d_i^T C_robot^-1 d_i``,
    ``rho`` the robust loss on the image residuals only (the prior is Gaussian), solved by
    ``scipy.optimize.least_squares`` with the block-sparse Jacobian (``jac_sparsity``: a
    station's rows touch the 12 global parameters and its own 6). The covariance is the
    inverse of the full Gauss-Newton information (12 + 6n), its ``X`` and ``Y`` blocks
    (= the Schur complement over the corrections, i.e. marginalised), scaled by the reduced
    chi-square when that exceeds 1. Triggs et al., "Bundle adjustment -- a modern synthesis"
    (2000), sections 6 and 8 (gauge-free priors and marginalisation); Koide & Menegatti 2019.

    Parameters
    ----------
    T_base_flange : the n reported flange poses.
    points_px : (n, N, 2) observed circle centres.
    X0, Y0 : starts (e.g. a linear method's).
    sigma_px : the plate's detection noise (1 sigma per coordinate).
    repeatability_mm, repeatability_deg : the robot's reporting noise (1 sigma per axis).
    bias_px : (n, N, 2) perspective bias of the centres to remove (default: predicted at the
        plate poses of the start, and again at the solution for a second solve).
    used : boolean mask of the stations to use (default all).

    Returns
    -------
    BundleResult

    Raises
    ------
    InputError
        Non-positive noise levels or an unknown loss.
    DegenerateInputError
        Singular information (stations too alike).
    """
    plate = plate or CirclePlate()
    A = list(T_base_flange)
    obs = np.asarray(points_px, float)
    if bias_px is None:
        # the circle centres' perspective bias, predicted at the start's plate poses, then
        # once more at the solution (a start 1 mm off moves it by ~1e-3 px)
        first = bundle_adjust_handeye(
            A, obs, camera, X0, Y0, plate=plate, sigma_px=sigma_px,
            repeatability_mm=repeatability_mm, repeatability_deg=repeatability_deg,
            bias_px=_predicted_bias(camera, plate, A, X0, Y0), loss=loss, f_scale=f_scale,
            used=used)
        X0, Y0 = first.T_flange_cam, first.T_base_plate
        bias_px = _predicted_bias(camera, plate, A, X0, Y0)
    bias = np.asarray(bias_px, float)
    used = np.ones(len(A), bool) if used is None else np.asarray(used, bool)
    A = [a for a, u in zip(A, used) if u]
    obs, bias = obs[used], bias[used]
    n, N = len(A), plate.n_points
    rep_rad = math.radians(repeatability_deg)
    if sigma_px <= 0 or repeatability_mm <= 0 or rep_rad <= 0:
        raise InputError("bundle adjustment needs positive pixel noise and robot repeatability")
    prob = _Problem(camera, plate.points_mm, A, obs, bias, sigma_px, repeatability_mm, rep_rad)
    prior_sd = np.array([repeatability_mm] * 3 + [rep_rad] * 3)

    def unpack(x):
        X, Y = _compose(X0, Y0, x[:12])
        d = x[12:].reshape(n, 6)
        RA = np.einsum("nij,njk->nik", Rotation.from_rotvec(d[:, 3:]).as_matrix(), prob.RA)
        return X, Y, d, RA, prob.tA + d[:, :3]

    w_img = np.ones(n * 2 * N)  # IRLS weights of the image rows (the prior stays quadratic)

    def fun(x):
        X, Y, d, RA, tA = unpack(x)
        r_img = (prob.project(X, Y, RA, tA) - prob.obs).ravel() / sigma_px
        return np.concatenate([w_img * r_img, (d / prior_sd).ravel()])

    def solve(x):
        return least_squares(fun, x, jac_sparsity=_ba_sparsity(n, N), method="trf",
                             x_scale="jac", xtol=1e-12, ftol=1e-12, gtol=1e-12, max_nfev=100,
                             tr_solver="lsmr", tr_options={"atol": 1e-12, "btol": 1e-12})

    x = np.concatenate([np.zeros(3), X0.t_mm, np.zeros(3), Y0.t_mm, np.zeros(6 * n)])
    nfev = 0
    if loss == "soft_l1":
        # robust loss on the image residuals only: least_squares' ``loss`` would act on the
        # prior rows too and let a station's correction swallow a gross robot error, so the
        # soft-L1 M-estimator is reached by reweighting, rho'(z) = (1 + z)^-1/2, z = (r/f)^2
        for _ in range(4):
            res = solve(x)
            x, nfev = res.x, nfev + res.nfev
            r = res.fun[: n * 2 * N] / w_img
            w_img = (1.0 + (r / f_scale) ** 2) ** -0.25
    elif loss != "linear":
        raise InputError(f"unknown loss {loss!r} (soft_l1 or linear)")
    w_img = np.ones(n * 2 * N)
    res = solve(x)
    nfev += res.nfev
    X, Y, d, _, _ = unpack(res.x)
    J = res.jac.toarray() if hasattr(res.jac, "toarray") else res.jac
    dof = max(len(res.fun) - 12 - 6 * n, 1)
    s2 = max(float(np.sum(res.fun ** 2)) / dof, 1.0)
    try:
        # 12 x 12 of the inverse information = the Schur complement over the corrections
        H = J.T @ J
        cov12 = s2 * np.linalg.inv(H)[:12, :12]
    except np.linalg.LinAlgError:
        raise DegenerateInputError("hand-eye bundle adjustment is singular") from None
    order = [3, 4, 5, 0, 1, 2]
    covX = _to_own(X, cov12[np.ix_(order, order)])
    covY = _to_own(Y, cov12[np.ix_([o + 6 for o in order], [o + 6 for o in order])])
    corr = np.zeros((len(used), 6))
    corr[used] = d
    return BundleResult(X, Y, covX, covY, corr, float(res.cost), nfev)


def _robust_cost(r: np.ndarray, f: float = 3.0) -> float:
    z = (r / f) ** 2
    return float(np.sum(2.0 * (np.sqrt(1.0 + z) - 1.0)))


def calibrate_handeye(T_base_flange: list[Pose], points_px, camera: Camera,
                      plate: CirclePlate | None = None, *, names: list[str] | None = None,
                      repeatability_mm: float = 0.03, repeatability_deg: float = 0.005,
                      max_position_3sigma_mm: float = 0.3,
                      max_angle_3sigma_deg: float = 0.03,
                      refinement: str = "marginal") -> HandEyeResult:
    """Eye-in-hand calibration from flange poses and the plate's circle centres (module doc).

    Parameters
    ----------
    T_base_flange : n flange poses (``to_frame='base'``, ``from_frame='flange'``).
    points_px : (n, rows*cols, 2) detected circle centres, plate order, observed pixels.
    camera : the calibrated camera (intrinsics fixed).
    repeatability_mm, repeatability_deg : the robot's pose noise per axis (1 sigma).
    max_position_3sigma_mm, max_angle_3sigma_deg : the verdict's limits on ``T_flange_cam``.
    refinement : ``"marginal"`` (step 3: the robot's errors integrated out analytically, each
        station whitened by ``sigma_px^2 I + G_i C_robot G_i^T``) or ``"bundle"`` (then, on the
        stations kept, :func:`bundle_adjust_handeye` with the robot's errors as explicit
        unknowns under their prior). Both are the maximum-likelihood estimate under plate and
        robot noise -- the first is the second with the corrections eliminated in closed form
        (exact to first order in the robot's errors) -- and agree to ~1e-5 mm in the simulated
        cell (docs/RESULTS.md, section 8); ``"bundle"`` is ~5x slower.

    Raises
    ------
    DegenerateInputError
        Fewer than 3 stations, stations without rotation or rotating about one axis only.
    InputError
        Mismatched counts or frames, non-finite points.
    """
    plate = plate or CirclePlate()
    if refinement not in ("marginal", "bundle"):
        raise InputError(f"unknown hand-eye refinement {refinement!r} (marginal or bundle)")
    A = list(T_base_flange)
    for a in A:
        if (a.to_frame, a.from_frame) != ("base", "flange"):
            raise InputError(f"robot poses must be T_base_flange, got {a.name}")
    obs = np.asarray(points_px, float)
    if obs.ndim != 3 or obs.shape[1:] != (plate.n_points, 2) or len(obs) != len(A):
        raise InputError(f"points_px must be ({len(A)}, {plate.n_points}, 2) for {len(A)} "
                         f"stations, got {obs.shape}")
    if not np.all(np.isfinite(obs)):
        raise InputError("points_px holds NaN or inf")
    names = list(names) if names is not None else [f"station{k}" for k in range(len(A))]
    ang = check_station_rotations(A)
    n, N = len(A), plate.n_points
    P = plate.points_mm
    # 1. per-station plate poses, bias-corrected
    B, bias = [], np.zeros_like(obs)
    for k in range(n):
        b0 = _pnp(camera, P, obs[k])
        bias[k] = np.nan_to_num(ellipse_center_bias_px(camera, b0, plate))
        B.append(_pnp(camera, P, obs[k] - bias[k]))
    pnp_r = np.stack([camera.project(b.apply(P)) for b in B]) - (obs - bias)
    sigma_px = float(np.sqrt(np.sum(pnp_r ** 2) / (n * (2 * N - 6))))
    sigma_px = max(sigma_px, 1e-3)
    prob = _Problem(camera, P, A, obs, bias, sigma_px, repeatability_mm,
                    math.radians(repeatability_deg))
    # 2. OpenCV starts, scored on the whitened robust cost
    starts: dict = {}
    scored = []
    for name in list(OPENCV_METHODS) + [f"{m}-numpy" for m in NUMPY_METHODS]:
        try:
            X, Y = (_numpy_start(name[:-6], A, B) if name.endswith("-numpy")
                    else _opencv_start(name, A, B))
        except Exception as e:  # noqa: BLE001 -- cv2.error, a missing binding, a degeneracy
            starts[name] = f"failed: {type(e).__name__}: {str(e).splitlines()[0][:120]}"
            continue
        if not (np.all(np.isfinite(X.matrix)) and np.all(np.isfinite(Y.matrix))):
            starts[name] = "failed: not finite"
            continue
        starts[name] = (X, Y)
        prob.set_weights(X, Y)
        scored.append((_robust_cost(prob.residuals(X, Y)), name))
    if not scored:
        raise DegenerateInputError("no OpenCV hand-eye method gave a start: "
                                   + "; ".join(f"{k} {v}" for k, v in starts.items()))
    start_method = min(scored)[1]
    X, Y = starts[start_method]
    # 3. robust pass, distrust, plain pass (twice: a wrongly distrusted station comes back)
    prob.set_weights(X, Y)
    used = np.ones(n, bool)
    X, Y, _ = _refine(prob, X, Y, used, "soft_l1")
    limit_q = chi2.ppf(0.999, 2 * N)
    for _ in range(2):
        prob.set_weights(X, Y)
        c2 = np.sum(prob.residuals(X, Y) ** 2, axis=1)
        new_used = c2 <= max(limit_q, 5.0 * np.median(c2))
        if new_used.sum() < 3:
            new_used = c2 <= np.sort(c2)[2]
        X, Y, res = _refine(prob, X, Y, new_used, "linear")
        if np.array_equal(new_used, used):
            used = new_used
            break
        used = new_used
    # re-linearise at the solution so the covariance is the one of the left perturbation there
    prob.set_weights(X, Y)
    X, Y, res = _refine(prob, X, Y, used, "linear")
    J = res.jac
    dof = max(len(res.fun) - 12, 1)
    s2 = max(float(np.sum(res.fun ** 2)) / dof, 1.0)
    try:
        cov12 = s2 * np.linalg.inv(J.T @ J)
    except np.linalg.LinAlgError:
        raise DegenerateInputError("hand-eye refinement is singular (stations too alike)") from None
    # parameters (dphi, t) -> (t, dphi) per transform; left -> own axes for the file
    order = [3, 4, 5, 0, 1, 2]
    covX = cov12[np.ix_(order, order)]
    covY = cov12[np.ix_([o + 6 for o in order], [o + 6 for o in order])]
    covX_own, covY_own = _to_own(X, covX), _to_own(Y, covY)
    if refinement == "bundle":
        ba = bundle_adjust_handeye(A, obs, camera, X, Y, plate=plate, sigma_px=sigma_px,
                                   repeatability_mm=repeatability_mm,
                                   repeatability_deg=repeatability_deg, bias_px=bias,
                                   loss="linear", used=used)
        X, Y, covX_own, covY_own = (ba.T_flange_cam, ba.T_base_plate, ba.cov_flange_cam,
                                    ba.cov_base_plate)
    # 4. per-station figures
    raw = (prob.project(X, Y) - prob.obs).reshape(n, N, 2)
    rms = np.sqrt(np.mean(np.sum(raw ** 2, axis=2), axis=1))
    c2 = np.sum(prob.residuals(X, Y) ** 2, axis=1)
    stations = []
    for k in range(n):
        Yk = A[k] @ X @ B[k]
        st = StationResidual(names[k], float(rms[k]), float(np.linalg.norm(Yk.t_mm - Y.t_mm)),
                             float(geodesic_deg(Yk.R, Y.R)), float(c2[k]), bool(used[k]))
        why = []
        if not used[k]:
            why.append(f"outlier (chi-square {c2[k]:.0f}, limit "
                       f"{max(limit_q, 5.0 * np.median(c2[used])):.0f}; plate off by "
                       f"{st.position_mm:.2f} mm / {st.angle_deg:.3f} deg)")
        others = np.delete(ang[k], k)
        if others.min() < DUPLICATE_ROTATION_DEG:
            j = int(np.argmin(np.where(np.arange(n) == k, np.inf, ang[k])))
            why.append(f"adds no rotation (within {others.min():.2f} deg of {names[j]})")
        st.distrust = "; ".join(why)
        stations.append(st)
    used_rms = float(np.sqrt(np.mean(np.sum(raw[used] ** 2, axis=2))))
    he = HandEye(X, Y, covX_own)
    result = HandEyeResult(he, covY_own, stations, starts, start_method, sigma_px, used_rms,
                           True, "", (repeatability_mm, repeatability_deg))
    result.ok, result.verdict = _verdict(result, ang, max_position_3sigma_mm,
                                         max_angle_3sigma_deg)
    return result


def _to_own(T: Pose, cov_left: np.ndarray) -> np.ndarray:
    J = np.eye(6)
    J[3:, 3:] = T.R.T
    return J @ cov_left @ J.T


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


def handeye_from_images(paths, T_base_flange: list[Pose], camera: Camera,
                        plate: CirclePlate | None = None, progress=None,
                        **kwargs) -> HandEyeResult:
    """Detect the plate in each image (sorted order, paired with the robot poses in file
    order), drop the images without a plate (with their poses; ``progress(name, reason)``
    reports each), and calibrate."""
    import cv2

    from .intrinsics import detect_plate

    plate = plate or CirclePlate()
    paths = [Path(p) for p in paths]
    if len(paths) != len(T_base_flange):
        raise InputError(f"{len(paths)} plate images but {len(T_base_flange)} robot poses; "
                         "give one pose per image, in the images' sorted order")
    pts, poses, names = [], [], []
    for p, a in zip(paths, T_base_flange):
        img = cv2.imread(str(p), cv2.IMREAD_GRAYSCALE) if p.is_file() else None
        reason = None
        if img is None:
            reason = "not a readable image"
        else:
            try:
                pts.append(detect_plate(img, plate).points_px)
                poses.append(a)
                names.append(p.name)
            except FeatureError as e:
                reason = str(e)
        if progress is not None:
            progress(p.name, reason)
    return calibrate_handeye(poses, np.array(pts).reshape(len(pts), plate.n_points, 2), camera,
                             plate, names=names, **kwargs)
