"""Camera calibration from views that each show a subset of a target's points (HALCON models).

Every view ``m`` gives the image points ``points_px[m]`` of the target points
``points_target_mm[ids[m]]``; views may show different subsets (partial views of a hexagonal
plate, a ChArUco board). The HALCON camera models are estimated as HALCON's
``calibrate_cameras`` does, by minimising the reprojection error in pixels over all intrinsics
and all target poses:

* ``division`` (:class:`~cutterpose.geometry.camera.DivisionCamera`, ``area_scan_division``):
  f, kappa, Sx, Cx, Cy;
* ``polynomial`` (:class:`~cutterpose.geometry.camera.PolynomialCamera`,
  ``area_scan_polynomial``): f, K1, K2, K3, P1, P2, Sx, Cx, Cy.

As in HALCON, the pixel height Sy is fixed (only f/Sx and f/Sy are observable). The solver
works in units of Sy and f: ``fy = f / Sy`` [px], ``a = Sx / Sy``, ``k = kappa Sy^2`` and the
polynomial's coefficients in units of f (``K1 f^2, K2 f^4, K3 f^6, P1 f, P2 f``), which keeps
the problem well scaled. Initial values: ``cv2.initCameraMatrix2D`` (closed form from the
views' homographies, which accepts views of different point sets) and ``cv2.solvePnP`` per
view. Refinement: ``scipy.optimize.least_squares`` (Levenberg-Marquardt) with a Jacobian by
forward differences grouped over the views (a view's residuals depend only on its own pose).
Standard deviations: ``s^2 (J^T J)^-1`` with ``s^2 = |r|^2 / (m - n)``, carried to the metric
parameters through the Jacobian of the unit change. The ellipse-centre bias of circular marks
is corrected as in :mod:`cutterpose.calibration.intrinsics` (2 rounds).

References:
    Z. Zhang, IEEE TPAMI 22(11), 2000; MVTec HALCON reference, ``calibrate_cameras`` and the
    chapter "Calibration" (camera models; Sy fixed); J. Heikkila, IEEE TPAMI 22(10), 2000.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.optimize import least_squares
from scipy.spatial.transform import Rotation

from ..errors import DegenerateInputError, InputError
from ..geometry.camera import (
    Camera,
    DivisionCamera,
    PolynomialCamera,
    invert_brown_conrady,
)
from ..geometry.pose import Pose

__all__ = ["refine_views", "calibrate_views", "ViewsCalibration", "VIEW_MODELS"]

VIEW_MODELS = ("division", "polynomial")
_N_DIST = {"division": 1, "polynomial": 5}


def _camera(model: str, q: np.ndarray, sy: float, size, name: str = "") -> Camera:
    fy, a, cx, cy = q[:4]
    f = fy * sy
    common = {"pixel_size_m": (a * sy, sy), "principal_point_px": (cx, cy),
              "image_size_px": tuple(size), "name": name}
    if model == "division":
        return DivisionCamera(focal_length_m=f, kappa_per_m2=q[4] / sy**2, **common)
    c1, c2, c3, p1, p2 = q[4:9]
    return PolynomialCamera(f, c1 / f**2, c2 / f**4, c3 / f**6, p1 / f, p2 / f, **common)


def _metric(model: str, q: np.ndarray, sy: float) -> np.ndarray:
    """The estimated parameters in HALCON's units, in the order of :func:`_metric_names`."""
    cam = _camera(model, q, sy, (1, 1))
    out = [cam.focal_length_m, cam.pixel_size_m[0], *cam.principal_point_px]
    if model == "division":
        return np.array(out + [cam.kappa_per_m2])
    return np.array(out + [getattr(cam, k) for k in cam.coefficient_names])


def _metric_names(model: str) -> list[str]:
    base = ["focal_length_m", "pixel_size_x_m", "cx_px", "cy_px"]
    if model == "division":
        return base + ["kappa_per_m2"]
    return base + list(PolynomialCamera.coefficient_names)


def _project(model: str, q, rvec, t, X, view_of):
    """Observed pixels of all points: ``X`` (n, 3), ``view_of`` (n,) view index of each."""
    fy, a, cx, cy = q[:4]
    R = Rotation.from_rotvec(rvec).as_matrix()[view_of]  # (n, 3, 3)
    P = np.einsum("nij,nj->ni", R, X) + t[view_of]
    x, y = P[:, 0] / P[:, 2], P[:, 1] / P[:, 2]
    if model == "division":
        k = q[4] * fy * fy  # kappa in units of f: (kappa sy^2) fy^2
        disc = np.maximum(1.0 - 4.0 * k * (x * x + y * y), 1e-12)
        s = 2.0 / (1.0 + np.sqrt(disc))
        x, y = x * s, y * s
    else:
        c1, c2, c3, p1, p2 = q[4:9]
        x, y = invert_brown_conrady(x, y, (c1, c2, p1, p2, c3, 0.0, 0.0, 0.0), 20)
    return np.stack([x * fy / a + cx, y * fy + cy], axis=-1)


def _initial(X_views, px_views, size):
    import cv2

    obj = [np.asarray(X, np.float32).reshape(-1, 1, 3) for X in X_views]
    img = [np.asarray(p, np.float32).reshape(-1, 1, 2) for p in px_views]
    K = cv2.initCameraMatrix2D(obj, img, tuple(int(v) for v in size), 1.0)
    rv, tv = [], []
    for o, i in zip(obj, img):
        ok, r, t = cv2.solvePnP(o, i, K, None, flags=cv2.SOLVEPNP_ITERATIVE)
        if not ok:
            raise DegenerateInputError("a view's initial pose could not be found")
        rv.append(np.ravel(r))
        tv.append(np.ravel(t))
    return K, np.array(rv), np.array(tv)


def refine_views(model: str, X_views, px_views, image_size_px, pixel_height_m: float,
                 warm: tuple | None = None):
    """Least-squares intrinsics and poses from ragged views (module docstring).

    ``warm`` = ``(q, rvecs, tvecs)`` of an earlier solution. Returns ``(camera, poses,
    residuals per view, std dict, q, rvecs, tvecs)``.
    """
    if model not in VIEW_MODELS:
        raise InputError(f"model must be one of {VIEW_MODELS}, got {model!r}")
    M = len(X_views)
    sy = float(pixel_height_m)
    nq = 4 + _N_DIST[model]
    if warm is None:
        K, rv0, t0 = _initial(X_views, px_views, image_size_px)
        q0 = np.zeros(nq)
        q0[:4] = [K[1, 1], K[1, 1] / K[0, 0], K[0, 2], K[1, 2]]
    else:
        q0, rv0, t0 = warm
    X = np.concatenate([np.asarray(v, float) for v in X_views])
    obs = np.concatenate([np.asarray(v, float) for v in px_views])
    counts = [len(v) for v in X_views]
    view_of = np.repeat(np.arange(M), counts)
    x0 = np.concatenate([q0, np.concatenate([rv0, t0], axis=1).ravel()])

    def fun(x):
        pose = x[nq:].reshape(M, 6)
        return (_project(model, x[:nq], pose[:, :3], pose[:, 3:], X, view_of) - obs).ravel()

    def jac(x):
        # forward differences, grouped: one evaluation per intrinsic, and one per pose
        # parameter for all views at once (a view's residuals depend on its own pose only)
        f0 = fun(x)
        J = np.zeros((len(f0), len(x)))
        rows = np.repeat(view_of, 2)
        for j in range(nq + 6):
            h = 1e-7 * max(abs(x[j]), 1.0) if j < nq else 1e-7
            dx = np.zeros_like(x)
            cols = [j] if j < nq else nq + 6 * np.arange(M) + (j - nq)
            dx[cols] = h if j < nq else np.maximum(1e-7 * np.abs(x[cols]), 1e-7)
            d = (fun(x + dx) - f0)
            if j < nq:
                J[:, j] = d / h
            else:
                J[np.arange(len(f0)), np.asarray(cols)[rows]] = d / dx[np.asarray(cols)[rows]]
        return J

    res = least_squares(fun, x0, jac=jac, method="lm", x_scale="jac",
                        xtol=1e-12, ftol=1e-12, gtol=1e-12, max_nfev=100)
    q = res.x[:nq]
    J = res.jac.toarray() if hasattr(res.jac, "toarray") else np.asarray(res.jac)
    s2 = 2.0 * res.cost / max(len(res.fun) - len(res.x), 1)
    try:
        cov_q = s2 * np.linalg.inv(J.T @ J)[:nq, :nq]
        # carry the covariance to HALCON's units: numerical Jacobian of _metric at q
        g0 = _metric(model, q, sy)
        G = np.empty((len(g0), nq))
        for j in range(nq):
            h = 1e-6 * max(abs(q[j]), 1e-6)
            dq = np.zeros(nq)
            dq[j] = h
            G[:, j] = (_metric(model, q + dq, sy) - _metric(model, q - dq, sy)) / (2 * h)
        sd = np.sqrt(np.clip(np.diag(G @ cov_q @ G.T), 0, None))
    except np.linalg.LinAlgError:
        sd = np.full(len(_metric_names(model)), np.nan)
    std = dict(zip(_metric_names(model), (float(v) for v in sd)))
    cam = _camera(model, q, sy, image_size_px, name=f"calibrated ({model} model)")
    pose = res.x[nq:].reshape(M, 6)
    Rs = Rotation.from_rotvec(pose[:, :3]).as_matrix()
    poses = [Pose(R, t, "cam", "target") for R, t in zip(Rs, pose[:, 3:])]
    r = res.fun.reshape(-1, 2)
    residuals = np.split(r, np.cumsum(counts)[:-1])
    return cam, poses, residuals, std, q, pose[:, :3], pose[:, 3:]


def calibrate_views(target, ids_views, px_views, image_size_px, *, model: str = "polynomial",
                    pixel_height_m: float = 3.45e-6, bias_rounds: int = 2, names=None):
    """Calibrate from ``M >= 3`` views of ``target`` (any object with ``points_target_mm`` and,
    for circular marks, ``circle_outline_mm``); view ``m`` shows ``ids_views[m]`` at
    ``px_views[m]``. Returns a :class:`ViewsCalibration` (the fields of
    :class:`cutterpose.calibration.intrinsics.CalibrationResult`, which wraps it).
    """
    from .plate import ellipse_center_bias_px

    M = len(ids_views)
    if M < 3:
        raise DegenerateInputError(f"calibration needs at least 3 usable views, got {M}")
    # a Target (points_target_mm) or a CirclePlate (points_mm)
    pts_all = np.asarray(getattr(target, "points_target_mm", None)
                         if hasattr(target, "points_target_mm") else target.points_mm, float)
    X_views = [pts_all[np.asarray(i, int)] for i in ids_views]
    px = [np.asarray(p, float) for p in px_views]
    if any(len(x) < 6 or len(x) != len(p) for x, p in zip(X_views, px)):
        raise InputError("every view needs at least 6 points, with one id per image point")
    names = list(names) if names is not None else [f"view{m}" for m in range(M)]
    first = refine_views(model, X_views, px, image_size_px, pixel_height_m)
    sol = first
    outline = getattr(target, "circle_outline_mm", None)
    for _ in range(bias_rounds if outline is not None and outline() is not None else 0):
        obs = []
        for ids, p, pose in zip(ids_views, px, sol[1]):
            bias = ellipse_center_bias_px(sol[0], pose, target, ids=ids)
            obs.append(p - np.nan_to_num(bias))
        sol = refine_views(model, X_views, obs, image_size_px, pixel_height_m,
                           warm=(sol[4], sol[5], sol[6]))
    cam, poses, res, std = sol[:4]
    sq = np.concatenate([np.sum(r**2, axis=1) for r in res])
    per = [float(np.sqrt(np.mean(np.sum(r**2, axis=1)))) for r in res]
    unc = None
    if sol is not first:
        sq0 = np.concatenate([np.sum(r**2, axis=1) for r in first[2]])
        unc = {"camera": first[0].to_dict(), "rms_px": float(np.sqrt(sq0.mean())),
               "std": first[3]}
    return ViewsCalibration(cam, float(np.sqrt(sq.mean())), per, std, poses, names, unc, res)


@dataclass
class ViewsCalibration:
    """Result of :func:`calibrate_views`: the camera, the RMS reprojection error over all
    points (and per view), the parameters' standard deviations (HALCON's units), the target
    poses, the view names, the figures before the ellipse-centre bias correction, and the
    residuals (n_m, 2) of every view."""

    camera: Camera
    rms_px: float
    per_image_rms_px: list
    std: dict
    poses: list
    used: list
    uncorrected: dict | None
    residuals_px: list
