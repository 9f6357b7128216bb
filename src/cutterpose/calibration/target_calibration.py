"""Camera calibration from images of any calibration target (:mod:`.targets`).

Every image is either used or skipped with its reason (unreadable, another size, target not
found, too few points, points on one line); each used view keeps its image points, their ids
and the order's rotation ambiguity. The camera models:

* ``opencv``: ``cv2.calibrateCameraExtended`` with a chosen set of coefficients among k1, k2,
  k3, p1, p2 and the rational k4, k5, k6 (:func:`parse_coefficients`; the others are fixed at
  0 with OpenCV's ``CALIB_FIX_K*`` / ``CALIB_ZERO_TANGENT_DIST`` flags); standard deviations
  from OpenCV's ``stdDeviationsIntrinsics``;
* ``division`` and ``polynomial`` (HALCON's ``area_scan_division`` / ``area_scan_polynomial``):
  :func:`cutterpose.calibration.view_refine.calibrate_views` (least squares over ragged views,
  Sy fixed, standard deviations from ``s^2 (J^T J)^-1``).

Circle targets get the ellipse-centre bias correction (:func:`.plate.ellipse_center_bias_px`,
2 rounds) for every model. Images whose residuals stand out are flagged (not dropped): a
per-image RMS above ``median + 5 x 1.4826 MAD`` of the images and above 1.5 x the median, or
a point whose residual exceeds ``max(5 x RMS, 1 px)``.

References:
    OpenCV calib3d ``calibrateCameraExtended`` (Zhang 2000 initialisation, LM refinement);
    Z. Zhang, IEEE TPAMI 22(11), 2000; J. Heikkila, IEEE TPAMI 22(10), 2000.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
from scipy.spatial.transform import Rotation

from ..errors import DegenerateInputError, InputError
from ..geometry.camera import OpenCVCamera
from ..geometry.pose import Pose
from .intrinsics import CalibrationResult
from .plate import ellipse_center_bias_px
from .targets import Target, target_from_spec

__all__ = ["TargetView", "detect_views", "parse_coefficients", "opencv_flags", "fit_opencv",
           "calibrate_target", "calibrate_target_images", "flag_outliers", "MODELS",
           "OPENCV_COEFFICIENTS"]

MODELS = ("opencv", "division", "polynomial")
OPENCV_COEFFICIENTS = ("k1", "k2", "p1", "p2", "k3", "k4", "k5", "k6")
DEFAULT_COEFFICIENTS = "k1,k2,p1,p2,k3"


@dataclass
class TargetView:
    """The target's points found in one image."""

    name: str
    points_px: np.ndarray
    ids: np.ndarray
    rotation_ambiguity_deg: int = 0
    info: dict = field(default_factory=dict)


def _collinear(xy: np.ndarray) -> bool:
    c = xy - xy.mean(axis=0)
    s = np.linalg.svd(c, compute_uv=False)
    return bool(len(xy) < 3 or s[1] < 1e-6 * max(s[0], 1e-12))


def detect_views(paths, target: Target, progress=None):
    """Detect ``target`` in every image file.

    Returns
    -------
    ``(views, skipped, image_size_px)``: the used views in input order, ``{name: reason}``
    of the others, and the (width, height) of the used images (None if none).
    """
    import cv2

    views, skipped, size = [], {}, None
    for p in paths:
        p = Path(p)
        name = p.name if p.name not in skipped and all(v.name != p.name for v in views) \
            else str(p)
        img = cv2.imread(str(p), cv2.IMREAD_GRAYSCALE) if p.is_file() else None
        reason = None
        if img is None:
            reason = "not a readable image"
        elif size is not None and (img.shape[1], img.shape[0]) != size:
            reason = (f"image size {img.shape[1]}x{img.shape[0]} differs from "
                      f"{size[0]}x{size[1]}")
        else:
            det = target.detect(img)
            if not det:
                reason = det.reason or "target not found"
            elif len(det.ids) < target.min_points:
                reason = f"only {len(det.ids)} target points found (need {target.min_points})"
            elif _collinear(target.points_target_mm[det.ids][:, :2]):
                reason = "the points found lie on one line"
            else:
                views.append(TargetView(name, det.points_px, det.ids,
                                        det.rotation_ambiguity_deg, dict(det.info)))
                size = (img.shape[1], img.shape[0])
        if reason:
            skipped[name] = reason
        if progress is not None:
            progress(name, reason)
    return views, skipped, size


def parse_coefficients(text: str | None) -> tuple[str, ...]:
    """OpenCV distortion coefficients to estimate: a comma list of k1 k2 k3 p1 p2 k4 k5 k6,
    ``rational`` (k1..k6, p1, p2), ``none`` or ``default`` (k1, k2, p1, p2, k3)."""
    if text is None or str(text).strip().lower() in ("", "default"):
        text = DEFAULT_COEFFICIENTS
    words = [w.strip().lower() for w in str(text).replace(" ", ",").split(",") if w.strip()]
    out = set()
    for w in words:
        if w == "none":
            continue
        if w == "rational":
            out |= set(OPENCV_COEFFICIENTS)
        elif w in ("p", "tangential"):
            out |= {"p1", "p2"}
        elif w in OPENCV_COEFFICIENTS:
            out.add(w)
        else:
            raise InputError(f"unknown distortion coefficient {w!r}: use k1 k2 k3 p1 p2 k4 k5 "
                             "k6, rational or none")
    if ("p1" in out) != ("p2" in out):
        raise InputError("p1 and p2 are estimated together (OpenCV has one flag for both)")
    return tuple(c for c in OPENCV_COEFFICIENTS if c in out)


def opencv_flags(coefs: tuple[str, ...]) -> int:
    import cv2

    flags = 0
    if any(c in coefs for c in ("k4", "k5", "k6")):
        flags |= cv2.CALIB_RATIONAL_MODEL
    for c, f in (("k1", cv2.CALIB_FIX_K1), ("k2", cv2.CALIB_FIX_K2), ("k3", cv2.CALIB_FIX_K3),
                 ("k4", cv2.CALIB_FIX_K4), ("k5", cv2.CALIB_FIX_K5), ("k6", cv2.CALIB_FIX_K6)):
        if c not in coefs:
            flags |= f
    if "p1" not in coefs:
        flags |= cv2.CALIB_ZERO_TANGENT_DIST
    return flags


def fit_opencv(X_views, px_views, image_size_px, coefficients=DEFAULT_COEFFICIENTS,
               start=None):
    """OpenCV's model over ragged views. Returns ``(camera, poses, residuals per view, std)``
    with the standard deviation of fx, fy, cx, cy and every estimated coefficient. ``start``:
    an OpenCVCamera to start from (``CALIB_USE_INTRINSIC_GUESS``; the bias-correction rounds
    start from the previous round, which keeps a many-coefficient fit in its minimum)."""
    import cv2

    coefs = parse_coefficients(coefficients) if isinstance(coefficients, str) or \
        coefficients is None else tuple(coefficients)
    obj = [np.asarray(X, np.float32).reshape(-1, 1, 3) for X in X_views]
    img = [np.asarray(p, np.float32).reshape(-1, 1, 2) for p in px_views]
    crit = (cv2.TERM_CRITERIA_COUNT + cv2.TERM_CRITERIA_EPS, 200, 1e-12)
    size = tuple(int(v) for v in image_size_px)
    flags = opencv_flags(coefs)
    K0 = d0 = None
    if start is not None:
        flags |= cv2.CALIB_USE_INTRINSIC_GUESS
        K0 = np.array(start.K, float)
        d0 = np.zeros(8)
        d0[:len(start.dist_coeffs)] = start.dist_coeffs
    try:
        out = cv2.calibrateCameraExtended(obj, img, size, K0, d0, flags=flags, criteria=crit)
    except cv2.error as e:
        raise DegenerateInputError(f"OpenCV's calibration failed: {e.err}") from None
    _, K, dist, rvecs, tvecs, sd_intr = out[:6]
    dist = np.asarray(dist, float).ravel()
    rational = any(c in coefs for c in ("k4", "k5", "k6"))
    cam = OpenCVCamera(K, dist[:8] if rational else dist[:5], size,
                       name="calibrated (opencv model)")
    poses = [Pose(Rotation.from_rotvec(np.ravel(r)).as_matrix(), np.ravel(t), "cam", "target")
             for r, t in zip(rvecs, tvecs)]
    res = [cam.project(p.apply(np.asarray(X, float))) - np.asarray(q, float)
           for p, X, q in zip(poses, X_views, px_views)]
    names = ["fx_px", "fy_px", "cx_px", "cy_px", "k1", "k2", "p1", "p2", "k3", "k4", "k5", "k6"]
    sd = np.ravel(sd_intr)
    std = {n: float(v) for n, v in zip(names, sd) if n.endswith("_px") or n in coefs}
    return cam, poses, res, std


def _rms_of(residuals) -> float:
    return float(np.sqrt(np.mean(np.concatenate([np.sum(r**2, axis=1) for r in residuals]))))


def _poorly_determined(std: dict, camera) -> list:
    """Warnings for parameters whose standard deviation is large (focal length over 1 %,
    principal point over 2 % of the image size)."""
    out = []
    K = getattr(camera, "K", None)
    if K is None:
        return out
    w, h = camera.image_size_px
    for key, ref in (("fx_px", K[0, 0]), ("fy_px", K[1, 1])):
        if std.get(key, 0) > 0.01 * ref:
            out.append(f"{key} is poorly determined (std {std[key]:.3g} px): more images, more "
                       "tilt, or fewer distortion coefficients")
    for key, ref in (("cx_px", w), ("cy_px", h)):
        if std.get(key, 0) > 0.02 * ref:
            out.append(f"{key} is poorly determined (std {std[key]:.3g} px)")
    return out


def flag_outliers(names, residuals, per_image_rms) -> dict:
    """``{name: why}`` of the images whose residuals stand out (module docstring)."""
    rms = np.asarray(per_image_rms, float)
    if len(rms) == 0:
        return {}
    med = float(np.median(rms))
    mad = 1.4826 * float(np.median(np.abs(rms - med)))
    total = float(np.sqrt(np.mean(np.concatenate([np.sum(r**2, axis=1) for r in residuals]))))
    out = {}
    for n, r, e in zip(names, residuals, rms):
        why = []
        if e > med + 5 * mad and e > 1.5 * med:
            why.append(f"RMS {e:.3f} px against the images' median {med:.3f} px")
        worst = float(np.sqrt(np.max(np.sum(r**2, axis=1)))) if len(r) else 0.0
        if worst > max(5 * total, 1.0):
            k = int(np.sum(np.sum(r**2, axis=1) > max(5 * total, 1.0) ** 2))
            why.append(f"{k} point(s) off by up to {worst:.2f} px")
        if why:
            out[n] = "; ".join(why)
    return out


def calibrate_target(views: list[TargetView], target: Target, image_size_px, *,
                     model: str = "opencv", coefficients=None, pixel_height_m: float = 3.45e-6,
                     bias_rounds: int = 2) -> CalibrationResult:
    """Calibrate from ``M >= 3`` views (module docstring). The result's ``views`` holds per
    used image its points, ids and residuals; ``flagged`` the images that stand out."""
    if model not in MODELS:
        raise InputError(f"model must be one of {', '.join(MODELS)}, got {model!r}")
    if len(views) < 3:
        raise DegenerateInputError(f"calibration needs at least 3 usable images, got "
                                   f"{len(views)}")
    X_all = np.asarray(target.points_target_mm, float)
    X_views = [X_all[v.ids] for v in views]
    px = [np.asarray(v.points_px, float) for v in views]
    names = [v.name for v in views]
    has_circles = target.circle_outline_mm(8) is not None and bias_rounds > 0
    if model != "opencv":
        from .view_refine import calibrate_views

        r = calibrate_views(target, [v.ids for v in views], px, image_size_px, model=model,
                            pixel_height_m=pixel_height_m, bias_rounds=bias_rounds, names=names)
        res = CalibrationResult(r.camera, r.rms_px, r.per_image_rms_px, r.std, r.poses, names,
                                uncorrected=r.uncorrected)
        residuals = _residuals(res.camera, res.poses, X_views, px, views, target, has_circles)
    else:
        coefs = parse_coefficients(coefficients)
        cam, poses, residuals, std = fit_opencv(X_views, px, image_size_px, coefs)
        first = (cam, residuals, std)
        warnings = []
        for _ in range(bias_rounds if has_circles else 0):
            obs = [p - np.nan_to_num(ellipse_center_bias_px(cam, pose, target, ids=v.ids))
                   for p, pose, v in zip(px, poses, views)]
            nxt = fit_opencv(X_views, obs, image_size_px, coefs, cam)
            if _rms_of(nxt[2]) > 1.2 * _rms_of(residuals) + 0.01:
                # the correction is a small shift of the points: a fit that gets much worse
                # under it is ill-conditioned (too many coefficients for these views)
                warnings.append("the ellipse-centre bias correction made the fit worse and was "
                                "stopped: the model is poorly determined by these images (use "
                                "fewer coefficients or more images)")
                break
            cam, poses, residuals, std = nxt
        sq = np.concatenate([np.sum(r**2, axis=1) for r in residuals])
        per = [float(np.sqrt(np.mean(np.sum(r**2, axis=1)))) for r in residuals]
        unc = None
        if first[0] is not cam:
            sq0 = np.concatenate([np.sum(r**2, axis=1) for r in first[1]])
            unc = {"camera": first[0].to_dict(), "rms_px": float(np.sqrt(sq0.mean())),
                   "std": first[2]}
        res = CalibrationResult(cam, float(np.sqrt(sq.mean())), per, std, poses, names,
                                uncorrected=unc, coefficients=list(coefs), warnings=warnings)
    res.views = [{"name": v.name, "ids": v.ids, "points_px": v.points_px,
                  "residuals_px": r, "rotation_ambiguity_deg": v.rotation_ambiguity_deg}
                 for v, r in zip(views, residuals)]
    res.flagged = flag_outliers(names, residuals, res.per_image_rms_px)
    res.warnings = list(res.warnings) + _poorly_determined(res.std, res.camera)
    res.target = target.describe()
    res.model = model
    return res


def _residuals(camera, poses, X_views, px_views, views, target, corrected: bool):
    """Reprojection residuals (projected - measured) of every view; with ``corrected`` the
    measured circle centres are bias-corrected first (what the model was fitted to)."""
    out = []
    for pose, X, q, v in zip(poses, X_views, px_views, views):
        if corrected:
            q = q - np.nan_to_num(ellipse_center_bias_px(camera, pose, target, ids=v.ids))
        out.append(camera.project(pose.apply(X)) - q)
    return out


def calibrate_target_images(paths, target, *, model: str = "opencv", coefficients=None,
                            pixel_height_m: float = 3.45e-6, bias_rounds: int = 2,
                            progress=None) -> CalibrationResult:
    """Detect ``target`` (a Target or a spec) in every image and calibrate.

    Raises
    ------
    DegenerateInputError
        Fewer than 3 usable images; the message lists every skipped image with its reason.
    """
    target = target_from_spec(target)
    views, skipped, size = detect_views(paths, target, progress)
    if len(views) < 3:
        listing = "; ".join(f"{k}: {v}" for k, v in skipped.items()) or "none"
        raise DegenerateInputError(
            f"calibration needs at least 3 images with the target {target.describe()} found, "
            f"got {len(views)} (skipped: {listing})")
    res = calibrate_target(views, target, size, model=model, coefficients=coefficients,
                           pixel_height_m=pixel_height_m, bias_rounds=bias_rounds)
    res.skipped = skipped
    res.image_size_px = size
    return res
