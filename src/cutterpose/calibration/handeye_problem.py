"""The hand-eye refinement's model: the target's points, their symmetries, the reprojection of
the target at ``T_cam_plate_i = X^-1 A_i^-1 Y`` and its whitening.

Used by :mod:`cutterpose.calibration.handeye` (the calibration) and
:mod:`cutterpose.calibration.handeye_bundle` (the bundle adjustment). Conventions as there:
``X = T_flange_cam``, ``Y = T_base_plate`` (``plate``: the calibration target's frame, whatever
the target), ``A_i = T_base_flange_i``; parameters ``(dphi_X, t_X, dphi_Y, t_Y)`` with the
rotations perturbed on the left (parent axes).
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
from scipy.optimize import least_squares
from scipy.spatial.transform import Rotation

from ..errors import FeatureError, InputError
from ..geometry.camera import Camera
from ..geometry.pose import Pose
from .handeye_starts import stack_poses
from .plate import CirclePlate, ellipse_center_bias_px

__all__ = ["TargetModel", "solve_pnp", "HandEyeProblem", "compose_xy", "refine_xy",
           "predicted_bias", "cov_left_to_own"]


@dataclass
class TargetModel:
    """The calibration target as the hand-eye calibration sees it.

    ``points_mm``: (N, 3) in the target's order. ``symmetries``: permutations ``p`` (each (N,)
    ints, the identity not among them) of the target's in-plane rotations that map its points
    onto themselves, so that a detector may return point ``p[j]`` where it means ``j`` (a plain
    grid turned by 180 deg: ``p = N-1-j``). ``angles_deg``: the rotation of each.
    ``ambiguity_deg``: what a detection of this target leaves open when it does not say (0:
    its marks fix the order; 180, 90: the plain grid's turns). ``marks``: the circles whose
    image-centre bias is removed (None: corners, no bias).
    """

    points_mm: np.ndarray
    symmetries: list = field(default_factory=list)
    marks: object = None
    name: str = ""
    angles_deg: list = field(default_factory=list)
    ambiguity_deg: int | None = None

    def __post_init__(self):
        self.symmetries = [np.asarray(q, int) for q in self.symmetries]
        if len(self.angles_deg) != len(self.symmetries):
            self.angles_deg = [_turn_deg(self.points_mm, q) for q in self.symmetries]
        if self.ambiguity_deg is None:
            self.ambiguity_deg = int(min(self.angles_deg)) if self.angles_deg else 0

    @property
    def n_points(self) -> int:
        return len(self.points_mm)

    def allowed(self, ambiguity_deg) -> np.ndarray:
        """(n, 1 + len(symmetries)) which orders each station may have, from its detection's
        rotation ambiguity (None: the target's own)."""
        amb = np.asarray([self.ambiguity_deg if a is None else a for a in ambiguity_deg], int)
        ang = np.asarray(self.angles_deg, float)
        ok = np.ones((len(amb), 1 + len(ang)), bool)
        for i, a in enumerate(amb):
            ok[i, 1:] = (a > 0) & (np.abs(np.remainder(ang + 1e-6, a if a > 0 else 1) - 1e-6)
                                   < 1e-3)
        return ok

    @classmethod
    def of(cls, target) -> TargetModel:
        """From a :class:`CirclePlate` (default), a target of
        :mod:`cutterpose.calibration.targets`, or a TargetModel."""
        if isinstance(target, TargetModel):
            return target
        if target is None or isinstance(target, CirclePlate):
            plate = target or CirclePlate()
            return cls(plate.points_mm, [], plate, "caltab", [], 0)
        pts = getattr(target, "points_target_mm", None)
        if pts is None:
            raise InputError(f"not a calibration target: {type(target).__name__}")
        from .targets import symmetry_permutations

        pts = np.asarray(pts, float)
        if pts.ndim != 2 or pts.shape[1] != 3:
            raise InputError(f"target points must be (N, 3), got {pts.shape}")
        # every turn of the bare points is a candidate (a detection may say it missed the mark)
        sym = symmetry_permutations(pts[:, :2], None, reflections=False)[1:]
        marks = target if target.circle_outline_mm(4) is not None else None
        spec = target.spec() if hasattr(target, "spec") else type(target).__name__
        return cls(pts, sym, marks, str(spec), [], int(target.rotation_symmetry_deg))

    def bias_px(self, camera: Camera, T_cam_plate: Pose) -> np.ndarray:
        """(N, 2) offset of the marks' image centres from the images of their centres."""
        if self.marks is None:
            return np.zeros((self.n_points, 2))
        return np.nan_to_num(ellipse_center_bias_px(camera, T_cam_plate, self.marks))


def _turn_deg(points_mm: np.ndarray, perm: np.ndarray) -> float:
    """The in-plane rotation [deg, 0..360) that takes ``points`` to ``points[perm]``."""
    P = points_mm[:, :2] - points_mm[:, :2].mean(axis=0)
    Q = P[perm]
    ang = np.degrees(np.arctan2(np.sum(P[:, 0] * Q[:, 1] - P[:, 1] * Q[:, 0]),
                                np.sum(P * Q)))
    return float(np.round(ang % 360.0, 6))


def solve_pnp(camera: Camera, plate_pts: np.ndarray, obs_px: np.ndarray) -> Pose:
    """``T_cam_plate`` by IPPE + Levenberg-Marquardt on the ideal pixels."""
    import cv2

    seen = np.all(np.isfinite(obs_px), axis=1)
    ideal = camera.undistort_px(obs_px[seen]).astype(np.float64)
    obj = plate_pts[seen].astype(np.float64)
    K = camera.K
    ok, rv, tv = cv2.solvePnP(obj, ideal, K, None, flags=cv2.SOLVEPNP_IPPE)
    if not ok:
        raise FeatureError("plate pose not found (PnP failed)")
    rv, tv = cv2.solvePnPRefineLM(obj, ideal, K, None, rv, tv)
    return Pose(Rotation.from_rotvec(rv.ravel()).as_matrix(), tv.ravel(), "cam", "plate")




class HandEyeProblem:
    """Residuals of the joint refinement, vectorised over stations.

    A point a station did not see (a partial view: NaN in ``obs``) has a zero residual and
    decoupled whitening rows, which leaves the others' whitening the marginal one of the
    points seen.
    """

    def __init__(self, camera: Camera, plate_pts: np.ndarray, A: list[Pose], obs: np.ndarray,
                 bias: np.ndarray, sigma_px: float, rep_mm: float, rep_rad: float):
        self.camera, self.P = camera, plate_pts
        self.RA, self.tA = stack_poses(A)
        self.seen = np.all(np.isfinite(obs), axis=2)  # (n, N)
        # observed centres with the perspective bias removed; unseen points 0 (masked)
        self.obs = np.where(self.seen[..., None], obs - bias, 0.0)
        self.sigma_px, self.rep_mm, self.rep_rad = sigma_px, rep_mm, rep_rad
        self.W = None
        self.G = None

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
        linearised at ``(X, Y)`` (central differences of the flange pose, in base axes): the
        symmetric square root ``S^-1/2`` of ``S = sigma_px^2 I + G C_robot G^T``."""
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
        G *= np.repeat(self.seen, 2, axis=1)[:, :, None]
        # S = sigma^2 (I + U U^T), U = G C_robot^1/2 / sigma of rank 6: with U = Q R (thin QR)
        # S^-1/2 = (I + Q M Q^T) / sigma, M = (I + R R^T)^-1/2 - I, applied in O(N) per
        # station (a dense 2N x 2N Cholesky per station is ~100x slower)
        U = G * (np.array([self.rep_mm] * 3 + [self.rep_rad] * 3) / self.sigma_px)
        Q, R = np.linalg.qr(U)
        lam, V = np.linalg.eigh(np.eye(6) + R @ R.transpose(0, 2, 1))
        self.Q = Q
        self.M = np.einsum("nij,nj,nkj->nik", V, lam ** -0.5, V) - np.eye(6)
        self.W = True
        self.G = G  # (n, 2N, 6): pixels per flange error (mm, rad; base axes)

    def residuals(self, X: Pose, Y: Pose) -> np.ndarray:
        """(n, 2N) whitened residuals (raw pixels before :meth:`set_weights`)."""
        r = ((self.project(X, Y) - self.obs) * self.seen[..., None]).reshape(len(self.RA), -1)
        if self.W is None:
            return r
        c = np.einsum("nji,nki,nk->nj", self.M, self.Q, r)  # M Q^T r
        return (r + np.einsum("nki,ni->nk", self.Q, c)) / self.sigma_px

    def raw(self, X: Pose, Y: Pose) -> np.ndarray:
        """(n, N, 2) reprojection residuals in pixels, NaN where a point was not seen."""
        return np.where(self.seen[..., None], self.project(X, Y) - self.obs, np.nan)


def compose_xy(X0: Pose, Y0: Pose, x: np.ndarray) -> tuple[Pose, Pose]:
    """Parameters ``(dphi_X, t_X, dphi_Y, t_Y)``, rotations perturbed on the left."""
    X = Pose(Rotation.from_rotvec(x[:3]).as_matrix() @ X0.R, x[3:6], "flange", "cam")
    Y = Pose(Rotation.from_rotvec(x[6:9]).as_matrix() @ Y0.R, x[9:12], "base", "plate")
    return X, Y


def refine_xy(prob: HandEyeProblem, X0: Pose, Y0: Pose, used: np.ndarray, loss: str):
    x0 = np.concatenate([np.zeros(3), X0.t_mm, np.zeros(3), Y0.t_mm])

    def fun(x):
        X, Y = compose_xy(X0, Y0, x)
        return prob.residuals(X, Y)[used].ravel()

    res = least_squares(fun, x0, loss=loss, f_scale=3.0, method="trf", x_scale="jac",
                        xtol=1e-12, ftol=1e-12, gtol=1e-12, max_nfev=200)
    X, Y = compose_xy(X0, Y0, res.x)
    return X, Y, res


def predicted_bias(camera: Camera, target: TargetModel, A: list[Pose], X: Pose,
                   Y: Pose) -> np.ndarray:
    """(n, N, 2) centre bias of the marks at the plate poses ``X^-1 A_i^-1 Y``."""
    return np.stack([target.bias_px(camera, X.inverse() @ a.inverse() @ Y) for a in A])



def cov_left_to_own(T: Pose, cov_left: np.ndarray) -> np.ndarray:
    """Covariance with rotations about the parent's axes -> about the frame's own axes."""
    J = np.eye(6)
    J[3:, 3:] = T.R.T
    return J @ cov_left @ J.T


