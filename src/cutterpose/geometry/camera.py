"""Camera models: pinhole, HALCON division and polynomial, OpenCV radial-tangential.

Convention:
    Camera frame x right, y down, z along the optical axis; pixel (0, 0) is the centre of the
    top-left pixel, u along the rows (x), v down the columns (y). Every model maps a camera-frame
    point through an ideal pinhole ``K`` to *ideal* (undistorted) pixels, then through its lens
    distortion to *observed* pixels::

        ideal_px = K @ (X/Z, Y/Z, 1)          observed_px = distort_px(ideal_px)

    All pose computations work on ideal pixels or on normalised coordinates ``K^-1 ideal_px``;
    ``undistort_px`` is the exact inverse of ``distort_px`` (round trip below 1e-9 px).

Files:
    JSON (the format of ``shared/spec/camera_*.json``) and OpenCV FileStorage YAML
    (``camera_matrix``, ``distortion_coefficients``, ``image_width``, ``image_height``).

References:
    HALCON area-scan division model: ``u_u = u_d / (1 + kappa r_d^2)`` in metric image-plane
    coordinates (seed paper, Table 1; MVTec HALCON reference, chapter "Calibration": the same
    equation, so :class:`DivisionCamera` is HALCON's ``area_scan_division``). HALCON
    ``area_scan_polynomial``: :class:`PolynomialCamera`. OpenCV ``calib3d`` documentation for
    the radial-tangential (Brown-Conrady) model.
"""

from __future__ import annotations

import json
import math
from dataclasses import dataclass

import numpy as np

from ..errors import CameraFileError, InputError

__all__ = [
    "Camera", "PinholeCamera", "DivisionCamera", "PolynomialCamera", "OpenCVCamera",
    "brown_conrady", "invert_brown_conrady",
    "camera_from_dict", "default_camera",
]


def _as_points(points, last: int, name: str) -> np.ndarray:
    a = np.asarray(points, dtype=float)
    if a.ndim == 0 or a.shape[-1] != last:
        raise InputError(f"{name} must have shape (..., {last}), got {a.shape}")
    return a


class Camera:
    """Interface shared by every camera model.

    Attributes
    ----------
    image_size_px : (width, height) in pixels.
    K : (3, 3) ideal pinhole intrinsics.
    """

    model: str = "abstract"
    image_size_px: tuple[int, int]
    name: str = ""

    @property
    def K(self) -> np.ndarray:  # pragma: no cover - abstract
        raise NotImplementedError

    @property
    def K_inv(self) -> np.ndarray:
        return np.linalg.inv(self.K)

    @property
    def focal_px(self) -> float:
        """Mean focal length in pixels (converts normalised errors to pixels)."""
        return 0.5 * (self.K[0, 0] + self.K[1, 1])

    # --- distortion (identity for the pinhole) ---------------------------------------------
    def distort_px(self, ideal_px) -> np.ndarray:
        """Ideal pinhole pixels -> observed pixels."""
        return _as_points(ideal_px, 2, "ideal_px").copy()

    def undistort_px(self, observed_px) -> np.ndarray:
        """Observed pixels -> ideal pinhole pixels (exact inverse of :meth:`distort_px`)."""
        return _as_points(observed_px, 2, "observed_px").copy()

    # --- derived ---------------------------------------------------------------------------
    def project(self, points_cam) -> np.ndarray:
        """Camera-frame points ``(..., 3)`` -> observed pixels ``(..., 2)``.

        Points with z <= 0 project to NaN.
        """
        p = _as_points(points_cam, 3, "points_cam")
        with np.errstate(divide="ignore", invalid="ignore"):
            z = np.where(p[..., 2] > 0, p[..., 2], np.nan)
            xn = p[..., :2] / z[..., None]
        K = self.K
        ideal = np.stack([K[0, 0] * xn[..., 0] + K[0, 1] * xn[..., 1] + K[0, 2],
                          K[1, 1] * xn[..., 1] + K[1, 2]], axis=-1)
        return self.distort_px(ideal)

    def normalize_px(self, observed_px) -> np.ndarray:
        """Observed pixels -> normalised coordinates ``(x/z, y/z)`` of the ideal camera."""
        ideal = self.undistort_px(observed_px)
        K = self.K
        y = (ideal[..., 1] - K[1, 2]) / K[1, 1]
        x = (ideal[..., 0] - K[0, 2] - K[0, 1] * y) / K[0, 0]
        return np.stack([x, y], axis=-1)

    def pixel_to_ray(self, observed_px) -> np.ndarray:
        """Observed pixels -> unit viewing rays ``(..., 3)`` in the camera frame."""
        m = self.normalize_px(observed_px)
        rays = np.concatenate([m, np.ones(m.shape[:-1] + (1,))], axis=-1)
        return rays / np.linalg.norm(rays, axis=-1, keepdims=True)

    def in_image(self, observed_px, margin_px: float = 0.0) -> np.ndarray:
        """Boolean mask of pixels inside the image (with a margin)."""
        p = np.asarray(observed_px, float)
        w, h = self.image_size_px
        return ((p[..., 0] >= margin_px) & (p[..., 0] <= w - 1 - margin_px)
                & (p[..., 1] >= margin_px) & (p[..., 1] <= h - 1 - margin_px))

    def to_dict(self) -> dict:  # pragma: no cover - abstract
        raise NotImplementedError

    def to_pinhole(self) -> PinholeCamera:
        """The ideal camera ``K`` without distortion."""
        return PinholeCamera.from_matrix(self.K, self.image_size_px, name=self.name)

    def __repr__(self) -> str:
        return f"{type(self).__name__}({json.dumps(self.to_dict())})"


@dataclass(repr=False)
class PinholeCamera(Camera):
    """Ideal pinhole camera.

    ``fx = f / sx``, ``fy = f / sy`` (focal length and pixel size in metres), principal point
    ``(cx, cy)`` in pixels, optional skew.
    """

    fx: float
    fy: float
    cx: float
    cy: float
    image_size_px: tuple[int, int]
    skew: float = 0.0
    name: str = ""
    model = "pinhole"

    def __post_init__(self):
        _check_positive_finite({"fx": self.fx, "fy": self.fy}, "pinhole camera")
        _check_finite({"cx": self.cx, "cy": self.cy, "skew": self.skew}, "pinhole camera")
        self.image_size_px = check_image_size(self.image_size_px)

    @classmethod
    def from_matrix(cls, K, image_size_px, name: str = "") -> PinholeCamera:
        K = np.asarray(K, float)
        if K.shape != (3, 3):
            raise InputError(f"K must be 3x3, got {K.shape}")
        return cls(K[0, 0], K[1, 1], K[0, 2], K[1, 2], tuple(image_size_px), skew=K[0, 1],
                   name=name)

    @property
    def K(self) -> np.ndarray:
        return np.array([[self.fx, self.skew, self.cx], [0.0, self.fy, self.cy], [0, 0, 1.0]])

    # the two below are Camera's formulas on the fields directly: building K per call cost more
    # than the arithmetic (they sit on every PnP solve's path); not cached, since fields may change
    @property
    def focal_px(self) -> float:
        return np.float64(0.5 * (float(self.fx) + float(self.fy)))

    def normalize_px(self, observed_px) -> np.ndarray:
        ideal = _as_points(observed_px, 2, "observed_px")  # no distortion: no copy needed
        y = (ideal[..., 1] - float(self.cy)) / float(self.fy)
        x = (ideal[..., 0] - float(self.cx) - float(self.skew) * y) / float(self.fx)
        return np.stack([x, y], axis=-1)

    def to_dict(self) -> dict:
        return {"name": self.name, "model": "pinhole", "image_size_px": list(self.image_size_px),
                "camera_matrix": self.K.tolist(), "distortion": None}


@dataclass(repr=False)
class DivisionCamera(Camera):
    """HALCON ``area_scan_division`` camera (the seed paper's Table 1).

    With metric image-plane coordinates ``x_d = (u - cx) sx``, ``y_d = (v - cy) sy`` of an observed
    pixel and ``r_d^2 = x_d^2 + y_d^2``, the undistorted coordinates are

        x_u = x_d / (1 + kappa r_d^2),   y_u = y_d / (1 + kappa r_d^2)

    and an ideal pinhole of focal length ``f`` gives ``x_u = f X / Z``. The inverse is closed-form:
    ``r_u = r_d / (1 + kappa r_d^2)`` is a quadratic in ``r_d`` whose root near ``r_u`` is

        r_d = 2 r_u / (1 + sqrt(1 - 4 kappa r_u^2)),

    so ``x_d = x_u * 2 / (1 + sqrt(1 - 4 kappa r_u^2))``. For ``kappa > 0`` the square root turns
    imaginary beyond ``r_u = 1 / (2 sqrt(kappa))``: such points are not imaged (NaN).
    """

    focal_length_m: float
    kappa_per_m2: float
    pixel_size_m: tuple[float, float]
    principal_point_px: tuple[float, float]
    image_size_px: tuple[int, int]
    name: str = ""
    model = "division"

    def __post_init__(self):
        _check_positive_finite({"focal_length_m": self.focal_length_m}, "division camera")
        _check_finite({"kappa_per_m2": self.kappa_per_m2}, "division camera")
        sx, sy = _check_pair(self.pixel_size_m, "pixel_size_m", positive=True)
        cx, cy = _check_pair(self.principal_point_px, "principal_point_px")
        self.pixel_size_m = (sx, sy)
        self.principal_point_px = (cx, cy)
        self.image_size_px = check_image_size(self.image_size_px)

    @property
    def K(self) -> np.ndarray:
        sx, sy = self.pixel_size_m
        cx, cy = self.principal_point_px
        f = self.focal_length_m
        return np.array([[f / sx, 0.0, cx], [0.0, f / sy, cy], [0.0, 0.0, 1.0]])

    def _metric(self, px):
        sx, sy = self.pixel_size_m
        cx, cy = self.principal_point_px
        return (px[..., 0] - cx) * sx, (px[..., 1] - cy) * sy

    def _pixels(self, x, y):
        sx, sy = self.pixel_size_m
        cx, cy = self.principal_point_px
        return np.stack([x / sx + cx, y / sy + cy], axis=-1)

    def undistort_px(self, observed_px) -> np.ndarray:
        p = _as_points(observed_px, 2, "observed_px")
        x, y = self._metric(p)
        s = 1.0 / (1.0 + self.kappa_per_m2 * (x * x + y * y))
        return self._pixels(x * s, y * s)

    def distort_px(self, ideal_px) -> np.ndarray:
        p = _as_points(ideal_px, 2, "ideal_px")
        x, y = self._metric(p)
        disc = 1.0 - 4.0 * self.kappa_per_m2 * (x * x + y * y)
        with np.errstate(invalid="ignore"):
            s = 2.0 / (1.0 + np.sqrt(np.where(disc >= 0, disc, np.nan)))
        return self._pixels(x * s, y * s)

    def to_dict(self) -> dict:
        return {"name": self.name, "model": "division",
                "image_size_px": list(self.image_size_px),
                "focal_length_m": self.focal_length_m, "kappa_per_m2": self.kappa_per_m2,
                "pixel_size_m": list(self.pixel_size_m),
                "principal_point_px": list(self.principal_point_px)}


@dataclass(repr=False)
class OpenCVCamera(Camera):
    """OpenCV's radial-tangential model (``k1, k2, p1, p2[, k3[, k4, k5, k6]]``).

    With normalised coordinates ``(x, y)`` and ``r^2 = x^2 + y^2``::

        radial = (1 + k1 r^2 + k2 r^4 + k3 r^6) / (1 + k4 r^2 + k5 r^4 + k6 r^6)
        x_d = x radial + 2 p1 x y + p2 (r^2 + 2 x^2)
        y_d = y radial + p1 (r^2 + 2 y^2) + 2 p2 x y

    Undistortion has no closed form; it runs Newton's method with the analytic Jacobian to
    machine precision (``cv2.undistortPoints`` stops at a fixed iteration count, which is not
    enough for 1e-9 px round trips at the image corners).
    """

    camera_matrix: np.ndarray
    dist_coeffs: np.ndarray
    image_size_px: tuple[int, int]
    name: str = ""
    model = "opencv"

    def __post_init__(self):
        K = np.asarray(self.camera_matrix, float)
        if K.shape != (3, 3) or not np.all(np.isfinite(K)):
            raise CameraFileError(f"camera_matrix must be a finite 3x3 matrix, got {K.shape}")
        if K[0, 0] <= 0 or K[1, 1] <= 0:
            raise CameraFileError("camera_matrix: focal lengths fx, fy must be positive")
        if K[0, 1] != 0 or np.any(K[2] != [0, 0, 1]) or np.any(K[1, :1] != 0):
            # OpenCV's projection ignores a skew term: accepting one would silently disagree.
            raise CameraFileError("camera_matrix: the OpenCV model has no skew; expected "
                                  "[[fx, 0, cx], [0, fy, cy], [0, 0, 1]]")
        d = np.asarray(self.dist_coeffs, float).ravel()
        if d.size not in (4, 5, 8) or not np.all(np.isfinite(d)):
            raise CameraFileError(
                "distortion_coefficients: need 4, 5 or 8 finite values (k1 k2 p1 p2 [k3 [k4 k5 "
                f"k6]]); got {d.size} (thin-prism and tilt terms are not supported)")
        self.camera_matrix = K
        self.dist_coeffs = d
        self.image_size_px = check_image_size(self.image_size_px)

    @property
    def K(self) -> np.ndarray:
        return self.camera_matrix.copy()

    def _coeffs(self):
        d = np.zeros(8)
        d[: self.dist_coeffs.size] = self.dist_coeffs
        return d

    def _distort_norm(self, x, y, jacobian: bool = False):
        return brown_conrady(x, y, self._coeffs(), jacobian)

    def _to_norm(self, px):
        K = self.camera_matrix
        y = (px[..., 1] - K[1, 2]) / K[1, 1]
        x = (px[..., 0] - K[0, 2] - K[0, 1] * y) / K[0, 0]
        return x, y

    def _to_px(self, x, y):
        K = self.camera_matrix
        return np.stack([K[0, 0] * x + K[0, 1] * y + K[0, 2], K[1, 1] * y + K[1, 2]], axis=-1)

    def distort_px(self, ideal_px) -> np.ndarray:
        p = _as_points(ideal_px, 2, "ideal_px")
        return self._to_px(*self._distort_norm(*self._to_norm(p)))

    def undistort_px(self, observed_px, iterations: int = 50) -> np.ndarray:
        p = _as_points(observed_px, 2, "observed_px")
        return self._to_px(*invert_brown_conrady(*self._to_norm(p), self._coeffs(),
                                                      iterations))

    def to_dict(self) -> dict:
        return {"name": self.name, "model": "opencv", "image_size_px": list(self.image_size_px),
                "camera_matrix": self.camera_matrix.tolist(),
                "distortion_coefficients": self.dist_coeffs.tolist()}


def brown_conrady(x, y, c, jacobian: bool = False):
    """Brown-Conrady map ``(x, y) -> (x', y')`` with ``c = (k1, k2, p1, p2, k3, k4, k5, k6)``.

    OpenCV applies it from ideal to distorted normalised coordinates; HALCON's
    ``area_scan_polynomial`` applies the same polynomial from distorted to undistorted
    coordinates (see :class:`PolynomialCamera`). With ``jacobian`` also returns the four
    partial derivatives ``dx'/dx, dx'/dy, dy'/dx, dy'/dy``.
    """
    k1, k2, p1, p2, k3, k4, k5, k6 = c
    r2 = x * x + y * y
    num = 1 + r2 * (k1 + r2 * (k2 + r2 * k3))
    den = 1 + r2 * (k4 + r2 * (k5 + r2 * k6))
    radial = num / den
    xd = x * radial + 2 * p1 * x * y + p2 * (r2 + 2 * x * x)
    yd = y * radial + p1 * (r2 + 2 * y * y) + 2 * p2 * x * y
    if not jacobian:
        return xd, yd
    dnum = k1 + r2 * (2 * k2 + 3 * k3 * r2)
    dden = k4 + r2 * (2 * k5 + 3 * k6 * r2)
    drad = (dnum * den - num * dden) / (den * den)  # d radial / d r2
    j00 = radial + 2 * x * x * drad + 2 * p1 * y + 6 * p2 * x
    j01 = 2 * x * y * drad + 2 * p1 * x + 2 * p2 * y
    j11 = radial + 2 * y * y * drad + 6 * p1 * y + 2 * p2 * x
    return xd, yd, j00, j01, j01, j11


def invert_brown_conrady(xt, yt, c, iterations: int = 50):
    """Solve ``brown_conrady(x, y, c) = (xt, yt)`` by Newton's method with the analytic
    Jacobian, started at ``(xt, yt)``, to machine precision (no closed form exists)."""
    x, y = np.array(xt, float), np.array(yt, float)
    for _ in range(iterations):
        fx_, fy_, a, b, cc, d = brown_conrady(x, y, c, jacobian=True)
        rx, ry = fx_ - xt, fy_ - yt
        det = a * d - b * cc
        dx = (d * rx - b * ry) / det
        dy = (a * ry - cc * rx) / det
        x = x - dx
        y = y - dy
        step = np.nanmax(np.abs(np.concatenate([np.ravel(dx), np.ravel(dy)])), initial=0.0)
        if step < 1e-15:
            break
    return x, y


@dataclass(repr=False)
class PolynomialCamera(Camera):
    """HALCON ``area_scan_polynomial`` camera (radial K1, K2, K3 and decentering P1, P2).

    With metric image-plane coordinates of an observed (distorted) pixel
    ``u = (col - Cx) Sx``, ``v = (row - Cy) Sy`` and ``r^2 = u^2 + v^2``, HALCON's camera
    model gives the undistorted coordinates ::

        u_u = u + u (K1 r^2 + K2 r^4 + K3 r^6) + 2 P1 u v + P2 (r^2 + 2 u^2)
        v_u = v + v (K1 r^2 + K2 r^4 + K3 r^6) + P1 (r^2 + 2 v^2) + 2 P2 u v

    and an ideal pinhole of focal length ``f`` gives ``u_u = f X / Z``. Units: K1 [1/m^2],
    K2 [1/m^4], K3 [1/m^6], P1, P2 [1/m], f, Sx, Sy [m], Cx, Cy [px]. The map runs from
    distorted to undistorted (the reverse of OpenCV's, whose polynomial has the same form), so
    :meth:`undistort_px` is closed-form and :meth:`distort_px` (projection) inverts it with
    Newton's method. Both work in units of ``f`` (``K1 f^2``, ``K2 f^4``, ``K3 f^6``,
    ``P1 f``, ``P2 f``), where the polynomial has the same coefficients' form.

    References: MVTec HALCON reference manual, chapter "Calibration", camera parameters of
    ``area_scan_polynomial``; D. C. Brown, "Decentering distortion of lenses", 1966.
    """

    focal_length_m: float
    k1_per_m2: float
    k2_per_m4: float
    k3_per_m6: float
    p1_per_m: float
    p2_per_m: float
    pixel_size_m: tuple[float, float]
    principal_point_px: tuple[float, float]
    image_size_px: tuple[int, int]
    name: str = ""
    model = "polynomial"

    def __post_init__(self):
        _check_positive_finite({"focal_length_m": self.focal_length_m}, "polynomial camera")
        _check_finite({k: getattr(self, k) for k in self.coefficient_names},
                      "polynomial camera")
        sx, sy = _check_pair(self.pixel_size_m, "pixel_size_m", positive=True)
        cx, cy = _check_pair(self.principal_point_px, "principal_point_px")
        self.pixel_size_m = (sx, sy)
        self.principal_point_px = (cx, cy)
        self.image_size_px = check_image_size(self.image_size_px)

    coefficient_names = ("k1_per_m2", "k2_per_m4", "k3_per_m6", "p1_per_m", "p2_per_m")

    @property
    def K(self) -> np.ndarray:
        sx, sy = self.pixel_size_m
        cx, cy = self.principal_point_px
        f = self.focal_length_m
        return np.array([[f / sx, 0.0, cx], [0.0, f / sy, cy], [0.0, 0.0, 1.0]])

    def normalized_coefficients(self) -> np.ndarray:
        """``(K1 f^2, K2 f^4, P1 f, P2 f, K3 f^6, 0, 0, 0)``: the polynomial in units of f,
        in OpenCV's coefficient order."""
        f = self.focal_length_m
        return np.array([self.k1_per_m2 * f**2, self.k2_per_m4 * f**4, self.p1_per_m * f,
                         self.p2_per_m * f, self.k3_per_m6 * f**6, 0.0, 0.0, 0.0])

    def _to_norm(self, px):
        (sx, sy), (cx, cy), f = self.pixel_size_m, self.principal_point_px, self.focal_length_m
        return (px[..., 0] - cx) * sx / f, (px[..., 1] - cy) * sy / f

    def _to_px(self, x, y):
        (sx, sy), (cx, cy), f = self.pixel_size_m, self.principal_point_px, self.focal_length_m
        return np.stack([x * f / sx + cx, y * f / sy + cy], axis=-1)

    def undistort_px(self, observed_px) -> np.ndarray:
        p = _as_points(observed_px, 2, "observed_px")
        c = self.normalized_coefficients()
        return self._to_px(*brown_conrady(*self._to_norm(p), c))

    def distort_px(self, ideal_px, iterations: int = 50) -> np.ndarray:
        p = _as_points(ideal_px, 2, "ideal_px")
        c = self.normalized_coefficients()
        return self._to_px(*invert_brown_conrady(*self._to_norm(p), c, iterations))

    def to_dict(self) -> dict:
        d = {"name": self.name, "model": "polynomial", "image_size_px": list(self.image_size_px),
             "focal_length_m": self.focal_length_m}
        d.update({k: getattr(self, k) for k in self.coefficient_names})
        d.update({"pixel_size_m": list(self.pixel_size_m),
                  "principal_point_px": list(self.principal_point_px)})
        return d


# ------------------------------------------------------------------------------------------
# validation helpers
def _check_finite(values: dict, what: str):
    for k, v in values.items():
        if not isinstance(v, (int, float, np.floating, np.integer)) or isinstance(v, bool):
            raise CameraFileError(f"{what}: field '{k}' must be a number, got {type(v).__name__}")
        if not math.isfinite(float(v)):
            raise CameraFileError(f"{what}: field '{k}' must be finite, got {v}")


def _check_positive_finite(values: dict, what: str):
    _check_finite(values, what)
    for k, v in values.items():
        if float(v) <= 0:
            raise CameraFileError(f"{what}: field '{k}' must be positive, got {v}")


def _check_pair(v, field: str, positive: bool = False):
    try:
        a, b = (float(x) for x in v)
    except (TypeError, ValueError, OverflowError):
        raise CameraFileError(f"field '{field}' must be a pair of numbers, got {v!r}") from None
    if not (math.isfinite(a) and math.isfinite(b)):
        raise CameraFileError(f"field '{field}' must be finite, got {v!r}")
    if positive and (a <= 0 or b <= 0):
        raise CameraFileError(f"field '{field}' must be positive, got {v!r}")
    return a, b


def check_image_size(v):
    try:
        w, h = v
        if isinstance(w, bool) or isinstance(h, bool) or int(w) != w or int(h) != h:
            raise ValueError
        w, h = int(w), int(h)
    except (TypeError, ValueError, OverflowError):
        raise CameraFileError(
            f"field 'image_size_px' must be two integers (width, height), got {v!r}") from None
    if w <= 0 or h <= 0:
        raise CameraFileError(f"field 'image_size_px' must be positive, got {v!r}")
    if w > 1 << 20 or h > 1 << 20:  # OpenCV's largest image side
        raise CameraFileError(f"field 'image_size_px' must be at most {1 << 20} px a side, "
                              f"got {v!r}")
    return (w, h)


# ------------------------------------------------------------------------------------------
# files
def _require(d: dict, key: str, where: str):
    if key not in d:
        raise CameraFileError(f"{where}: missing field '{key}'")
    return d[key]


def camera_from_dict(d: dict, where: str = "camera") -> Camera:
    """Build a camera from the JSON object of ``shared/spec/camera_*.json``.

    ``model`` is ``pinhole`` (either ``camera_matrix`` or ``focal_length_m`` + ``pixel_size_m`` +
    ``principal_point_px``), ``division`` (``focal_length_m``, ``kappa_per_m2``, ``pixel_size_m``,
    ``principal_point_px``), ``polynomial`` (HALCON ``area_scan_polynomial``: ``focal_length_m``,
    ``k1_per_m2``, ``k2_per_m4``, ``k3_per_m6``, ``p1_per_m``, ``p2_per_m``, ``pixel_size_m``,
    ``principal_point_px``) or ``opencv`` (``camera_matrix``, ``distortion_coefficients``).
    """
    if not isinstance(d, dict):
        raise CameraFileError(f"{where}: expected a JSON object, got {type(d).__name__}")
    model = _require(d, "model", where)
    size = _require(d, "image_size_px", where)
    name = str(d.get("name", ""))
    if model == "pinhole":
        if "camera_matrix" in d:
            K = matrix_field(d["camera_matrix"], "camera_matrix", where)
            return PinholeCamera.from_matrix(K, check_image_size(size), name=name)
        f = _number(_require(d, "focal_length_m", where), "focal_length_m", where)
        sx, sy = _check_pair(_require(d, "pixel_size_m", where), "pixel_size_m", positive=True)
        cx, cy = _check_pair(_require(d, "principal_point_px", where), "principal_point_px")
        if d.get("distortion") not in (None, {}, []):
            raise CameraFileError(f"{where}: a pinhole camera has no 'distortion'; use model "
                                  "'division' or 'opencv'")
        return PinholeCamera(f / sx, f / sy, cx, cy, check_image_size(size), name=name)
    if model == "division":
        return DivisionCamera(
            focal_length_m=_number(_require(d, "focal_length_m", where), "focal_length_m", where),
            kappa_per_m2=_number(_require(d, "kappa_per_m2", where), "kappa_per_m2", where),
            pixel_size_m=_require(d, "pixel_size_m", where),
            principal_point_px=_require(d, "principal_point_px", where),
            image_size_px=size, name=name)
    if model == "polynomial":
        coeffs = {k: _number(_require(d, k, where), k, where)
                  for k in ("focal_length_m",) + PolynomialCamera.coefficient_names}
        return PolynomialCamera(**coeffs, pixel_size_m=_require(d, "pixel_size_m", where),
                                principal_point_px=_require(d, "principal_point_px", where),
                                image_size_px=size, name=name)
    if model == "opencv":
        K = matrix_field(_require(d, "camera_matrix", where), "camera_matrix", where)
        dist = _require(d, "distortion_coefficients", where)
        try:
            dist = np.asarray(dist, float).ravel()
        except (TypeError, ValueError, OverflowError):
            raise CameraFileError(
                f"{where}: field 'distortion_coefficients' must be a list of numbers") from None
        return OpenCVCamera(K, dist, size, name=name)
    raise CameraFileError(f"{where}: field 'model' must be 'pinhole', 'division', 'polynomial' "
                          f"or 'opencv', got {model!r}")


def _number(v, field: str, where: str) -> float:
    if isinstance(v, bool) or not isinstance(v, (int, float)):
        raise CameraFileError(f"{where}: field '{field}' must be a number, got {v!r}")
    if not math.isfinite(v):
        raise CameraFileError(f"{where}: field '{field}' must be finite, got {v!r}")
    return float(v)


def matrix_field(v, field: str, where: str) -> np.ndarray:
    try:
        K = np.asarray(v, float)
    except (TypeError, ValueError, OverflowError):
        raise CameraFileError(f"{where}: field '{field}' must be a 3x3 matrix of numbers") from None
    if K.size == 9:
        K = K.reshape(3, 3)
    if K.shape != (3, 3) or not np.all(np.isfinite(K)):
        raise CameraFileError(f"{where}: field '{field}' must be a finite 3x3 matrix")
    return K


def default_camera(which: str = "table1") -> Camera:
    """The bundled cameras: ``"table1"`` (division model of the paper's Table 1) or
    ``"synthetic"`` (pinhole of the synthetic experiments).

    Examples
    --------
    >>> import numpy as np
    >>> from cutterpose import Pose, default_holder
    >>> camera = default_camera("table1")
    >>> camera.model, camera.image_size_px
    ('division', (4112, 3008))
    >>> X_cam = Pose.nominal().apply(default_holder().points_holder_mm)   # mm, camera frame
    >>> uv_px = camera.project(X_cam)                   # observed (distorted) pixels
    >>> uv_px[0].round(2)
    array([1590.66, 1107.12])
    >>> bool(np.allclose(camera.normalize_px(uv_px), X_cam[:, :2] / X_cam[:, 2:]))
    True
    """
    from importlib import resources

    names = {"table1": "camera_table1.json", "synthetic": "camera_synthetic.json"}
    if which not in names:
        raise InputError(f"unknown default camera {which!r}; choose from {sorted(names)}")
    text = resources.files("cutterpose.data").joinpath(names[which]).read_text()
    return camera_from_dict(json.loads(text), where=names[which])
