"""Camera calibration from images of the circle plate (Zhang's method, division or OpenCV model).

Pipeline:
    1. :func:`detect_plate`: dark blobs (``cv2.SimpleBlobDetector`` tuned to the plate's circle
       size) -> ``cv2.findCirclesGrid`` (symmetric grid) -> sub-pixel ellipse fit of every circle
       on grey-level edge crossings -> point order fixed by the triangular corner mark and by the
       sign of the image orientation (a symmetric grid alone is ambiguous under rotation).
    2. :func:`zhang_init`: homography of every view, Zhang's closed form for ``K`` from the
       constraints ``h1^T B h2 = 0``, ``h1^T B h1 = h2^T B h2`` with ``B = K^-T K^-1``, and
       the plate poses ``[r1 r2 t] = K^-1 H / |K^-1 h1|``.
    3. :func:`refine_division`: Levenberg-Marquardt (``scipy.optimize.least_squares``) of the
       reprojection error over all intrinsics and all plate poses, with the block-sparse
       Jacobian structure; parameter standard deviations from ``s^2 (J^T J)^-1``.
       The OpenCV model goes through ``cv2.calibrateCameraExtended`` instead.
    4. Perspective bias of circle centres (beyond the paper): the centre of a circle's image
       ellipse is not the image of its centre. With the current estimate, the offset is
       predicted per circle (:func:`cutterpose.calibration.plate.ellipse_center_bias_px`),
       subtracted from
       the measured ellipse centres, and the calibration is repeated (2 rounds are enough).

Convention:
    Plate frame and point order: :mod:`cutterpose.calibration.plate`. Poses are ``x_cam = R @
    x_plate + t``
    in mm. Division model as :class:`cutterpose.geometry.camera.DivisionCamera` (HALCON
    ``area_scan_division``): ``f`` [m], ``kappa`` [1/m^2], pixel pitch ``(sx, sy)`` [m], principal
    point [px]. Only ``f / sx`` and ``f / sy`` are observable, so, as HALCON does, the pixel
    height ``sy`` is fixed (the sensor's datasheet value) and ``f``, ``kappa``, ``sx``, ``cx``,
    ``cy`` are estimated; ``sx`` absorbs a non-square pixel aspect (Table 1: sx != sy). Internally
    the solver works in units of ``sy``: ``fy = f / sy`` [px], ``a = sx / sy``,
    ``k = kappa sy^2`` [1/px^2].

References:
    Z. Zhang, "A flexible new technique for camera calibration", IEEE TPAMI 22(11), 2000.
    MVTec HALCON reference, ``calibrate_cameras`` (area_scan_division; Sy fixed, Sx estimated).
    J. Heikkila, "Geometric camera calibration using circular control points", IEEE TPAMI
    22(10), 2000 (bias of ellipse centres).
"""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
from scipy.optimize import least_squares
from scipy.sparse import lil_matrix
from scipy.spatial.transform import Rotation

from ..errors import DegenerateInputError, FeatureError, InputError
from ..geometry.camera import Camera, DivisionCamera, OpenCVCamera
from ..geometry.pose import Pose
from .circle_detect import PlateDetection, detect_plate
from .plate import CirclePlate, ellipse_center_bias_px

__all__ = ["PlateDetection", "detect_plate", "zhang_init", "refine_division", "calibrate",
           "calibrate_images", "CalibrationResult"]


# ------------------------------------------------------------------------------------------
# Zhang's closed form
def _v(H: np.ndarray, i: int, j: int) -> np.ndarray:
    h = H.T  # rows are the columns h1, h2, h3
    return np.array([h[i, 0] * h[j, 0], h[i, 0] * h[j, 1] + h[i, 1] * h[j, 0],
                     h[i, 1] * h[j, 1], h[i, 2] * h[j, 0] + h[i, 0] * h[j, 2],
                     h[i, 2] * h[j, 1] + h[i, 1] * h[j, 2], h[i, 2] * h[j, 2]])


def zhang_init(plate_xy_mm: np.ndarray, points_px: np.ndarray):
    """Zhang's closed-form intrinsics and plate poses from >= 3 views (no distortion).

    With ``H = lambda K [r1 r2 t]`` per view and ``B = K^-T K^-1`` (symmetric, 6 unknowns
    ``b = (B11, B12, B22, B13, B23, B33)``), the orthonormality of ``r1, r2`` gives
    ``v12^T b = 0`` and ``(v11 - v22)^T b = 0`` with
    ``vij = (hi1 hj1, hi1 hj2 + hi2 hj1, hi2 hj2, hi3 hj1 + hi1 hj3, hi3 hj2 + hi2 hj3, hi3 hj3)``;
    ``b`` is the null vector of the stacked ``V`` (SVD), and K follows in closed form
    (Zhang 2000, appendix B). Skew is dropped (modern sensors have none).

    Parameters
    ----------
    plate_xy_mm : (N, 2) plate points.
    points_px : (M, N, 2) image points of M views (pixel coordinates).

    Returns
    -------
    K : (3, 3); R : (M, 3, 3); t_mm : (M, 3).
    """
    import cv2

    M = len(points_px)
    if M < 3:
        raise DegenerateInputError(f"Zhang's method needs at least 3 views, got {M}")
    # condition the pixels (Hartley) so that V is well scaled
    T = np.diag([1e-3, 1e-3, 1.0])
    Hs = []
    for p in points_px:
        H, _ = cv2.findHomography(plate_xy_mm.astype(np.float64), p.astype(np.float64), 0)
        if H is None:
            raise DegenerateInputError("plate homography failed (collinear points?)")
        Hs.append(T @ H)
    V = np.concatenate([np.stack([_v(H, 0, 1), _v(H, 0, 0) - _v(H, 1, 1)]) for H in Hs])
    b = np.linalg.svd(V)[2][-1]
    B11, B12, B22, B13, B23, B33 = b
    v0 = (B12 * B13 - B11 * B23) / (B11 * B22 - B12**2)
    lam = B33 - (B13**2 + v0 * (B12 * B13 - B11 * B23)) / B11
    if lam / B11 <= 0 or lam * B11 / (B11 * B22 - B12**2) <= 0:
        raise DegenerateInputError("Zhang's closed form failed: the views are too similar "
                                   "(tilt the plate more, in different directions)")
    alpha = np.sqrt(lam / B11)
    beta = np.sqrt(lam * B11 / (B11 * B22 - B12**2))
    u0 = -B13 * alpha**2 / lam  # skew term dropped
    Kc = np.array([[alpha, 0.0, u0], [0.0, beta, v0], [0.0, 0.0, 1.0]])
    K = np.linalg.inv(T) @ Kc
    R, t = _poses_from_homographies(K, [np.linalg.inv(T) @ H for H in Hs])
    return K, R, t


def _poses_from_homographies(K, Hs):
    """Each view's plate pose from its homography (Zhang 2000, 3.1; the shared
    :func:`~cutterpose.geometry.pose.pose_from_plane_homography`)."""
    from ..geometry.pose import pose_from_plane_homography

    Rs, ts = [], []
    for H in Hs:
        pose = pose_from_plane_homography(H, K)
        if pose is None:
            raise DegenerateInputError("a view's homography gives no pose with the plate in "
                                       "front of the camera")
        Rs.append(pose[0])
        ts.append(pose[1])
    return np.array(Rs), np.array(ts)


# ------------------------------------------------------------------------------------------
# division model refinement
def _project_division(q: np.ndarray, rvec: np.ndarray, t: np.ndarray, X: np.ndarray):
    """Observed pixels (M, N, 2) of plate points X (N, 3) for intrinsics
    ``q = (fy, a, k, cx, cy)`` (units of sy, see the module Convention) and poses (M, 3)."""
    fy, a, k, cx, cy = q
    R = Rotation.from_rotvec(rvec).as_matrix()  # (M, 3, 3)
    P = np.einsum("mij,nj->mni", R, X) + t[:, None, :]
    Xs = fy * P[..., 0] / P[..., 2]
    Ys = fy * P[..., 1] / P[..., 2]
    disc = np.maximum(1.0 - 4.0 * k * (Xs * Xs + Ys * Ys), 1e-12)
    s = 2.0 / (1.0 + np.sqrt(disc))
    return np.stack([Xs * s / a + cx, Ys * s + cy], axis=-1)


@dataclass
class RefineResult:
    camera: Camera
    poses: list[Pose]
    residuals_px: np.ndarray  # (M, N, 2)
    std: dict
    nfev: int = 0


def refine_division(plate_pts_mm: np.ndarray, points_px: np.ndarray, image_size_px,
                    pixel_height_m: float, K0: np.ndarray, R0: np.ndarray, t0: np.ndarray,
                    kappa0_per_m2: float = 0.0) -> RefineResult:
    """Levenberg-Marquardt over (f, kappa, sx, cx, cy) and all plate poses.

    Residuals are observed minus projected pixels of every circle in every view; the Jacobian
    is block sparse (a view's residuals depend on the 5 intrinsics and its own 6 pose
    parameters), which ``least_squares`` exploits through ``jac_sparsity``. Parameter
    covariance ``s^2 (J^T J)^-1`` with ``s^2 = |r|^2 / (m - n)``.
    """
    M, N, _ = points_px.shape
    sy = float(pixel_height_m)
    q0 = np.array([K0[1, 1], K0[1, 1] / K0[0, 0], kappa0_per_m2 * sy * sy, K0[0, 2], K0[1, 2]])
    rv0 = Rotation.from_matrix(R0).as_rotvec()
    x0 = np.concatenate([q0, np.concatenate([rv0, t0], axis=1).ravel()])
    obs = np.asarray(points_px, float)

    def fun(x):
        pose = x[5:].reshape(M, 6)
        return (_project_division(x[:5], pose[:, :3], pose[:, 3:], plate_pts_mm) - obs).ravel()

    S = lil_matrix((M * N * 2, 5 + 6 * M), dtype=int)
    S[:, :5] = 1
    for m in range(M):
        S[m * N * 2:(m + 1) * N * 2, 5 + 6 * m:11 + 6 * m] = 1
    res = least_squares(fun, x0, jac_sparsity=S, method="trf", x_scale="jac",
                        xtol=1e-10, ftol=1e-10, gtol=1e-10, max_nfev=100)
    J = res.jac.toarray() if hasattr(res.jac, "toarray") else np.asarray(res.jac)
    dof = max(len(res.fun) - len(res.x), 1)
    s2 = 2.0 * res.cost / dof
    try:
        cov = s2 * np.linalg.inv(J.T @ J)
        sd = np.sqrt(np.clip(np.diag(cov)[:5], 0, None))
    except np.linalg.LinAlgError:
        sd = np.full(5, np.nan)
    fy, a, k, cx, cy = res.x[:5]
    cam = DivisionCamera(focal_length_m=fy * sy, kappa_per_m2=k / sy**2,
                         pixel_size_m=(a * sy, sy), principal_point_px=(cx, cy),
                         image_size_px=tuple(image_size_px), name="calibrated (division model)")
    std = {"focal_length_m": sd[0] * sy, "kappa_per_m2": sd[2] / sy**2,
           "pixel_size_x_m": sd[1] * sy, "cx_px": sd[3], "cy_px": sd[4]}
    pose = res.x[5:].reshape(M, 6)
    Rs = Rotation.from_rotvec(pose[:, :3]).as_matrix()
    poses = [Pose(R, t, "cam", "plate") for R, t in zip(Rs, pose[:, 3:])]
    return RefineResult(cam, poses, res.fun.reshape(M, N, 2), std, res.nfev + res.njev)


def _calibrate_opencv(plate_pts_mm, points_px, image_size_px) -> RefineResult:
    import cv2

    M, N, _ = points_px.shape
    obj = [plate_pts_mm.astype(np.float32)] * M
    img = [p.reshape(-1, 1, 2).astype(np.float32) for p in points_px]
    crit = (cv2.TERM_CRITERIA_COUNT + cv2.TERM_CRITERIA_EPS, 200, 1e-12)
    out = cv2.calibrateCameraExtended(obj, img, tuple(int(v) for v in image_size_px), None, None,
                                      criteria=crit)
    _, K, dist, rvecs, tvecs, sd_intr = out[:6]
    cam = OpenCVCamera(K, np.asarray(dist).ravel()[:5], tuple(image_size_px),
                       name="calibrated (opencv model)")
    poses = [Pose(Rotation.from_rotvec(np.ravel(r)).as_matrix(), np.ravel(t), "cam", "plate")
             for r, t in zip(rvecs, tvecs)]
    proj = np.stack([cam.project(p.apply(plate_pts_mm)) for p in poses])
    sd = np.ravel(sd_intr)
    names = ["fx_px", "fy_px", "cx_px", "cy_px", "k1", "k2", "p1", "p2", "k3"]
    std = {n: float(v) for n, v in zip(names, sd)}
    return RefineResult(cam, poses, proj - points_px, std)


# ------------------------------------------------------------------------------------------
@dataclass
class CalibrationResult:
    """Calibrated camera with its error figures.

    Attributes
    ----------
    camera : the calibrated camera.
    rms_px : RMS reprojection error over all circles of all used images
        (``sqrt(mean |r|^2)`` over points, as ``cv2.calibrateCamera``).
    per_image_rms_px : RMS per used image, in the order of ``used``.
    std : standard deviation of each intrinsic parameter (keys name the parameter and unit).
    poses : plate poses of the used images.
    used : names of the images used; skipped : name -> reason of the images left out.
    uncorrected : the same figures before the ellipse-centre bias correction (or None).
    views : per used image ``{name, ids, points_px, residuals_px, rotation_ambiguity_deg}``
        (residuals = projected - measured, after the bias correction), or None.
    flagged : name -> why, of the used images whose residuals stand out.
    target, model, coefficients, image_size_px : what was calibrated, and how.
    warnings : what the user should know (e.g. poorly determined parameters).
    """

    camera: Camera
    rms_px: float
    per_image_rms_px: list
    std: dict
    poses: list
    used: list
    skipped: dict = field(default_factory=dict)
    uncorrected: dict | None = None
    views: list | None = None
    flagged: dict = field(default_factory=dict)
    target: str | None = None
    model: str | None = None
    coefficients: list | None = None
    image_size_px: tuple | None = None
    warnings: list = field(default_factory=list)

    def to_dict(self) -> dict:
        d = {"camera": self.camera.to_dict(), "rms_px": self.rms_px,
             "per_image_rms_px": dict(zip(self.used, self.per_image_rms_px)),
             "std": self.std, "skipped": self.skipped,
             "plate_poses": {n: p.to_dict() for n, p in zip(self.used, self.poses)},
             "uncorrected": self.uncorrected}
        if self.target is not None:
            d.update(target=self.target, model=self.model, coefficients=self.coefficients,
                     image_size_px=self.image_size_px, flagged=self.flagged,
                     warnings=self.warnings)
        if self.views is not None:
            d["images"] = {v["name"]: {
                "rms_px": float(np.sqrt(np.mean(np.sum(v["residuals_px"] ** 2, axis=1)))),
                "points": int(len(v["ids"])),
                "max_residual_px": float(np.sqrt(np.max(np.sum(v["residuals_px"] ** 2, 1)))),
                "rotation_ambiguity_deg": int(v["rotation_ambiguity_deg"]),
                "flagged": self.flagged.get(v["name"])} for v in self.views}
        return d


def _rms(res: np.ndarray) -> tuple[float, list]:
    sq = np.sum(res**2, axis=-1)
    return float(np.sqrt(sq.mean())), [float(v) for v in np.sqrt(sq.mean(axis=1))]


def calibrate(points_px: np.ndarray, plate: CirclePlate, image_size_px, *,
              model: str = "division", pixel_height_m: float = 3.45e-6,
              bias_rounds: int = 2, names: list | None = None) -> CalibrationResult:
    """Calibrate from ordered circle centres of M >= 3 views.

    Parameters
    ----------
    points_px : (M, rows*cols, 2) measured ellipse centres.
    model : ``"division"`` (our least squares), ``"polynomial"`` (HALCON's
        ``area_scan_polynomial``, :mod:`cutterpose.calibration.view_refine`) or ``"opencv"``
        (``cv2.calibrateCamera``, k1, k2, p1, p2, k3).
    pixel_height_m : the fixed pixel height ``sy`` of the HALCON models (only sets the metric
        unit of f and the distortion; the projection does not depend on it).
    bias_rounds : rounds of ellipse-centre bias correction (0 = plain ellipse centres).
    """
    pts = np.asarray(points_px, float)
    if pts.ndim != 3 or pts.shape[1:] != (plate.n_points, 2):
        raise InputError(f"points_px must be (M, {plate.n_points}, 2), got {pts.shape}")
    M = len(pts)
    if M < 3:
        raise DegenerateInputError(f"calibration needs at least 3 usable plate images, got {M}")
    if model not in ("division", "opencv", "polynomial"):
        raise InputError(f"model must be 'division', 'polynomial' or 'opencv', got {model!r}")
    names = list(names) if names is not None else [f"view{m}" for m in range(M)]
    if model == "polynomial":
        from .view_refine import calibrate_views

        r = calibrate_views(plate, [np.arange(plate.n_points)] * M, list(pts), image_size_px,
                            model=model, pixel_height_m=pixel_height_m,
                            bias_rounds=bias_rounds, names=names)
        return CalibrationResult(r.camera, r.rms_px, r.per_image_rms_px, r.std, r.poses,
                                 names, uncorrected=r.uncorrected)
    X = plate.points_mm

    def solve(obs, warm: RefineResult | None):
        if model == "opencv":
            return _calibrate_opencv(X, obs, image_size_px)
        if warm is None:
            K, R, t = zhang_init(X[:, :2], obs)
            return refine_division(X, obs, image_size_px, pixel_height_m, K, R, t)
        R = np.array([p.R for p in warm.poses])
        t = np.array([p.t_mm for p in warm.poses])
        return refine_division(X, obs, image_size_px, pixel_height_m, warm.camera.K, R, t,
                               warm.camera.kappa_per_m2)

    first = solve(pts, None)
    result = first
    for _ in range(bias_rounds):
        bias = np.stack([ellipse_center_bias_px(result.camera, p, plate) for p in result.poses])
        obs = pts - np.nan_to_num(bias)
        result = solve(obs, result)
    rms, per = _rms(result.residuals_px)
    unc = None
    if bias_rounds > 0:
        rms0, per0 = _rms(first.residuals_px)
        unc = {"camera": first.camera.to_dict(), "rms_px": rms0, "std": first.std}
    return CalibrationResult(result.camera, rms, per, result.std, result.poses, names,
                             uncorrected=unc)


def calibrate_images(paths, plate: CirclePlate, *, model: str = "division",
                     pixel_height_m: float = 3.45e-6, bias_rounds: int = 2,
                     progress=None) -> CalibrationResult:
    """Detect the plate in every image file and calibrate; unusable images are skipped.

    Raises
    ------
    DegenerateInputError
        Fewer than 3 images with a detected plate; the message lists every skipped image with
        its reason.
    """
    import cv2

    points, used, skipped = [], [], {}
    size = None
    for p in paths:
        p = Path(p)
        name = p.name
        img = cv2.imread(str(p), cv2.IMREAD_GRAYSCALE) if p.is_file() else None
        if img is None:
            skipped[name] = "not a readable image"
        elif size is not None and (img.shape[1], img.shape[0]) != size:
            skipped[name] = (f"image size {img.shape[1]}x{img.shape[0]} differs from "
                             f"{size[0]}x{size[1]}")
        else:
            try:
                det = detect_plate(img, plate)
                points.append(det.points_px)
                used.append(name)
                size = (img.shape[1], img.shape[0])
            except FeatureError as e:
                skipped[name] = str(e)
        if progress is not None:
            progress(name, skipped.get(name))
    if len(used) < 3:
        listing = "; ".join(f"{k}: {v}" for k, v in skipped.items()) or "none"
        raise DegenerateInputError(
            f"calibration needs at least 3 images with a detected plate, got {len(used)} "
            f"(skipped: {listing})")
    res = calibrate(np.stack(points), plate, size, model=model, pixel_height_m=pixel_height_m,
                    bias_rounds=bias_rounds, names=used)
    res.skipped = skipped
    return res
