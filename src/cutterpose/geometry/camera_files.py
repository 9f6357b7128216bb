"""Camera files: reading and writing every format users have, and conversion between models.

Formats:
    ``halcon``  HALCON camera parameter file as written by ``write_cam_par`` (``.dat``/``.cal``)
                for ``area_scan_division`` and ``area_scan_polynomial``: a ``ParGroup:
                Camera: Parameter;`` block and, per parameter, three lines
                ``Name:shortname: value;`` / ``TYPE:lower:upper;`` / ``"description";``
                for Focus, Kappa (division) or Poly1..Poly5 = K1, K2, K3, P1, P2
                (polynomial; the names K1..P2 are read too), Sx, Sy, Cx, Cy, ImageWidth,
                ImageHeight; an optional ``Model`` statement names the model; ``#`` starts a
                comment.
    ``ros``     ROS ``camera_info`` YAML (``camera_calibration_parsers``): ``image_width``,
                ``image_height``, ``camera_name``, ``camera_matrix`` / ``distortion_coefficients``
                / ``rectification_matrix`` / ``projection_matrix`` as ``{rows, cols, data}``,
                ``distortion_model: plumb_bob`` (k1 k2 p1 p2 k3) or ``rational_polynomial``
                (k1 k2 p1 p2 k3 k4 k5 k6).
    ``opencv``  OpenCV FileStorage YAML/XML; ``json`` the project's JSON (:func:`camera_from_dict`).

Convention:
    HALCON's Focus [m], Kappa [1/m^2], Sx, Sy [m] and Cx, Cy [px] are exactly the fields of
    :class:`cutterpose.geometry.camera.DivisionCamera`, and Poly1..Poly5 (K1 [1/m^2],
    K2 [1/m^4], K3 [1/m^6], P1, P2 [1/m]) those of
    :class:`cutterpose.geometry.camera.PolynomialCamera` (HALCON's pixel coordinates, like
    ours, put the centre of the top-left pixel at (0, 0); Cx is the column). The conversion
    between the HALCON models and OpenCV's is not exact: it is fitted over the image (see
    :func:`convert_camera`) and reported with its worst pixel error.

References:
    MVTec HALCON reference manual, ``read_cam_par`` / ``write_cam_par`` (file syntax; versions
    5.2-12 show the same division-model example); Zivid's public
    ``convert_intrinsics_opencv_to_halcon.py`` sample (a polynomial-model file, Poly1..Poly5).
    ROS ``sensor_msgs/CameraInfo`` and ``camera_calibration_parsers`` (YAML layout).
"""

from __future__ import annotations

import json
import re
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from ..errors import CameraFileError, InputError
from .camera import (
    Camera,
    DivisionCamera,
    OpenCVCamera,
    PinholeCamera,
    PolynomialCamera,
    camera_from_dict,
    check_image_size,
    matrix_field,
)
from .jsonfile import parse_error_text, read_json

__all__ = ["read_halcon", "write_halcon", "read_ros", "write_ros", "detect_format", "sniff_format",
           "write_camera", "load_camera", "save_camera",
           "FORMATS", "convert_camera", "Conversion", "to_division", "to_opencv",
           "to_polynomial"]

FORMATS = ("json", "opencv", "ros", "halcon")

#: Pixel height used when a model without a metric pixel size (pinhole, OpenCV) becomes a
#: division camera. It only sets the metric unit of f and kappa; the projection is the same
#: for any value. 3.45 um is the sensor of the paper's camera (Table 1).
DEFAULT_PIXEL_HEIGHT_M = 3.45e-6


# ------------------------------------------------------------------------------------------
# format detection
def detect_format(path, for_writing: bool = False) -> str:
    """The format of a camera file from its suffix and, when reading, its content.

    Suffixes: ``.json`` -> json; ``.dat``/``.cal`` -> halcon; ``.yml``/``.yaml``/``.xml``
    -> opencv unless the content is a ROS camera_info (``distortion_model`` key) or, for
    writing, the name ends in ``.ros.yaml``/``.ros.yml`` or contains ``camera_info``.
    """
    path = Path(path)
    name = path.name.lower()
    suffix = path.suffix.lower()
    if suffix == ".json":
        return "json"
    if suffix in (".dat", ".cal"):
        return "halcon"
    if suffix in (".yml", ".yaml", ".xml"):
        if name.endswith((".ros.yaml", ".ros.yml")) or "camera_info" in name:
            return "ros"
        if not for_writing and path.is_file() and suffix != ".xml":
            head = path.read_text(errors="replace")[:4000]
            if head.lstrip().startswith("%YAML:1.0") or "opencv-matrix" in head:
                return "opencv"
            if re.search(r"^\s*distortion_model\s*:", head, re.M):
                return "ros"
        return "opencv"
    if not for_writing and path.is_file():
        head = path.read_text(errors="replace")[:4000]
        if "ParGroup" in head:
            return "halcon"
        if head.lstrip().startswith("{"):
            return "json"
    raise CameraFileError(f"{path}: unknown camera file type (use .json, .yml/.yaml, .xml, "
                          ".ros.yaml or .dat)")


def sniff_format(path, for_writing: bool = False) -> str | None:
    """:func:`detect_format`, or None when the file type is unknown."""
    try:
        return detect_format(path, for_writing)
    except (CameraFileError, OSError):
        return None


# ------------------------------------------------------------------------------------------
# HALCON
_HALCON_DOC = {
    "Focus": ("foc", "DOUBLE:0.0:", "Focal length of the lens [meter]"),
    "Kappa": ("kappa", "DOUBLE::", "Radial distortion coefficient [1/(meter*meter)]"),
    "Poly1": ("poly1", "DOUBLE::", "1st polynomial distortion coefficient (K1) [1/(meter^2)]"),
    "Poly2": ("poly2", "DOUBLE::", "2nd polynomial distortion coefficient (K2) [1/(meter^4)]"),
    "Poly3": ("poly3", "DOUBLE::", "3rd polynomial distortion coefficient (K3) [1/(meter^6)]"),
    "Poly4": ("poly4", "DOUBLE::", "4th polynomial distortion coefficient (P1) [1/meter]"),
    "Poly5": ("poly5", "DOUBLE::", "5th polynomial distortion coefficient (P2) [1/meter]"),
    "Sx": ("sx", "DOUBLE:0.0:", "Width of a cell on the sensor [meter]"),
    "Sy": ("sy", "DOUBLE:0.0:", "Height of a cell on the sensor [meter]"),
    "Cx": ("cx", "DOUBLE::", "X-coordinate of the image center [pixel]"),
    "Cy": ("cy", "DOUBLE::", "Y-coordinate of the image center [pixel]"),
    "ImageWidth": ("imgw", "INT:1:32767", "Width of the images [pixel]"),
    "ImageHeight": ("imgh", "INT:1:32767", "Height of the images [pixel]"),
}
_HALCON_COMMON = ("Sx", "Sy", "Cx", "Cy", "ImageWidth", "ImageHeight")
_HALCON_POLY = ("Poly1", "Poly2", "Poly3", "Poly4", "Poly5")
#: the parameter names of newer HALCON versions, read as the Poly1..Poly5 they stand for
_HALCON_ALIASES = {"K1": "Poly1", "K2": "Poly2", "K3": "Poly3", "P1": "Poly4", "P2": "Poly5"}


def _halcon_statements(path: Path) -> dict[str, str]:
    try:
        text = path.read_text()
    except (OSError, UnicodeDecodeError) as e:
        raise CameraFileError(f"{path}: cannot read ({e})") from None
    # drop comments, then split into ';'-terminated statements
    body = "\n".join(ln for ln in text.splitlines() if not ln.lstrip().startswith("#"))
    if not re.search(r"ParGroup\s*:\s*Camera\s*:\s*Parameter", body):
        kind = "LinescanCamera" if "LinescanCamera" in body else "no 'ParGroup: Camera: Parameter'"
        raise CameraFileError(f"{path}: not a HALCON area-scan camera parameter file ({kind})")
    values: dict[str, str] = {}
    for stmt in body.split(";"):
        m = re.match(r"\s*([A-Za-z][A-Za-z0-9]*)\s*:\s*([A-Za-z0-9_]*)\s*:\s*(\S+)\s*$", stmt)
        if m and m.group(1) not in ("ParGroup",):
            values[_HALCON_ALIASES.get(m.group(1), m.group(1))] = m.group(3)
    return values


def read_halcon(path) -> DivisionCamera | PolynomialCamera:
    """Read a HALCON camera parameter file: ``area_scan_division`` (Kappa) or
    ``area_scan_polynomial`` (Poly1..Poly5, or K1, K2, K3, P1, P2).

    Raises
    ------
    CameraFileError
        Missing parameter, a telecentric/tilt/line-scan model, or a malformed value; the
        message names the parameter.
    """
    path = Path(path)
    values = _halcon_statements(path)
    poly = "Poly1" in values
    model = values.get("Model")
    wanted = "area_scan_polynomial" if poly else "area_scan_division"
    if model is not None and model.strip("'\"") != wanted:
        raise CameraFileError(f"{path}: HALCON model '{model}' is not supported "
                              "(area_scan_division or area_scan_polynomial)")
    keys = ("Focus",) + (_HALCON_POLY if poly else ("Kappa",)) + _HALCON_COMMON
    out = {}
    for key in keys:
        if key not in values:
            raise CameraFileError(f"{path}: missing HALCON parameter '{key}'")
        try:
            out[key] = float(values[key])
        except ValueError:
            raise CameraFileError(f"{path}: HALCON parameter '{key}' is not a number: "
                                  f"{values[key]!r}") from None
    if out["Focus"] == 0:
        raise CameraFileError(f"{path}: Focus = 0 is a telecentric camera (not supported)")
    common = {"pixel_size_m": (out["Sx"], out["Sy"]),
              "principal_point_px": (out["Cx"], out["Cy"]),
              "image_size_px": (out["ImageWidth"], out["ImageHeight"]), "name": path.stem}
    if poly:
        return PolynomialCamera(out["Focus"], *(out[k] for k in _HALCON_POLY), **common)
    return DivisionCamera(focal_length_m=out["Focus"], kappa_per_m2=out["Kappa"], **common)


def write_halcon(cam: Camera, path) -> None:
    """Write a division, polynomial (or skew-free pinhole) camera as a HALCON
    ``write_cam_par`` file (the polynomial model with HALCON's Poly1..Poly5 names)."""
    if isinstance(cam, PinholeCamera) and cam.skew == 0:
        cam = to_division(cam).camera
    if not isinstance(cam, (DivisionCamera, PolynomialCamera)):
        raise CameraFileError(
            f"HALCON files hold the division or polynomial model; convert the {cam.model} "
            "camera first (cutterpose camera convert)")
    sx, sy = cam.pixel_size_m
    cx, cy = cam.principal_point_px
    vals = {"Focus": cam.focal_length_m, "Sx": sx, "Sy": sy, "Cx": cx, "Cy": cy,
            "ImageWidth": cam.image_size_px[0], "ImageHeight": cam.image_size_px[1]}
    if isinstance(cam, PolynomialCamera):
        vals.update(zip(_HALCON_POLY, (getattr(cam, k) for k in cam.coefficient_names)))
    else:
        vals["Kappa"] = cam.kappa_per_m2
    lines = ["# INTERNAL CAMERA PARAMETERS", "", "ParGroup: Camera: Parameter;",
             '\t"Internal camera parameters";', ""]
    for key, (short, typ, desc) in _HALCON_DOC.items():
        if key not in vals:
            continue
        v = vals[key]
        sval = str(int(v)) if typ.startswith("INT") else repr(float(v))
        lines += [f"{key}:{short}:\t{sval};", f"\t{typ};", f'\t"{desc}";', ""]
    Path(path).write_text("\n".join(lines))


# ------------------------------------------------------------------------------------------
# ROS camera_info
def _ros_matrix(d: dict, key: str, shape, where: str) -> np.ndarray:
    node = d.get(key)
    if not isinstance(node, dict) or "data" not in node:
        raise CameraFileError(f"{where}: missing field '{key}' (a {{rows, cols, data}} map)")
    try:
        a = np.asarray(node["data"], float).ravel()
    except (TypeError, ValueError, OverflowError):
        raise CameraFileError(f"{where}: field '{key}.data' must be numbers") from None
    if shape is not None and a.size != int(np.prod(shape)):
        raise CameraFileError(f"{where}: field '{key}' needs {int(np.prod(shape))} values, "
                              f"got {a.size}")
    return a.reshape(shape) if shape is not None else a


def read_ros(path) -> Camera:
    """Read a ROS ``camera_info`` YAML file (plumb_bob or rational_polynomial)."""
    import yaml

    path = Path(path)
    try:
        d = yaml.safe_load(path.read_text())
    except (OSError, UnicodeDecodeError, yaml.YAMLError) as e:
        raise CameraFileError(f"{path}: not a readable YAML file ({parse_error_text(e)})"
                              ) from None
    where = str(path)
    if not isinstance(d, dict):
        raise CameraFileError(f"{where}: expected a YAML map")
    for k in ("image_width", "image_height"):
        if k not in d:
            raise CameraFileError(f"{where}: missing field '{k}'")
    K = _ros_matrix(d, "camera_matrix", (3, 3), where)
    dist = _ros_matrix(d, "distortion_coefficients", None, where)
    model = str(d.get("distortion_model", "plumb_bob"))
    if model not in ("plumb_bob", "rational_polynomial"):
        raise CameraFileError(f"{where}: distortion_model '{model}' is not supported "
                              "(plumb_bob or rational_polynomial)")
    R = d.get("rectification_matrix")
    if isinstance(R, dict) and not np.allclose(
            _ros_matrix(d, "rectification_matrix", (3, 3), where), np.eye(3)):
        raise CameraFileError(f"{where}: a non-identity rectification_matrix (stereo) is not "
                              "supported")
    size = (d["image_width"], d["image_height"])
    name = str(d.get("camera_name", "") or "")
    if dist.size == 0 or np.allclose(dist, 0):
        return PinholeCamera.from_matrix(K, size, name=name)
    return OpenCVCamera(K, dist, size, name=name)


def write_ros(cam: Camera, path) -> None:
    """Write a pinhole or OpenCV camera as ROS ``camera_info`` YAML."""
    import yaml

    if isinstance(cam, (DivisionCamera, PolynomialCamera)):
        raise CameraFileError(f"ROS camera_info cannot hold the {cam.model} model; convert it "
                              "to the opencv model first (cutterpose camera convert)")
    K = cam.K
    dist = cam.dist_coeffs if isinstance(cam, OpenCVCamera) else np.zeros(5)
    dist = np.asarray(dist, float).ravel()
    if dist.size == 4:
        dist = np.append(dist, 0.0)
    model = "plumb_bob" if dist.size == 5 else "rational_polynomial"
    P = np.concatenate([K, np.zeros((3, 1))], axis=1)

    def mat(a, rows, cols):
        return {"rows": rows, "cols": cols, "data": [float(v) for v in np.ravel(a)]}

    d = {"image_width": int(cam.image_size_px[0]), "image_height": int(cam.image_size_px[1]),
         "camera_name": cam.name or "camera",
         "camera_matrix": mat(K, 3, 3), "distortion_model": model,
         "distortion_coefficients": mat(dist, 1, dist.size),
         "rectification_matrix": mat(np.eye(3), 3, 3), "projection_matrix": mat(P, 3, 4)}
    Path(path).write_text(yaml.safe_dump(d, sort_keys=False, default_flow_style=None))


def write_camera(cam: Camera, path, fmt: str | None = None) -> None:
    """Write ``cam`` in format ``fmt`` (default: from the file name, :func:`detect_format`).

    The camera must fit the format (see :func:`convert_camera`)."""
    import json


    fmt = fmt or detect_format(path, for_writing=True)
    if fmt == "halcon":
        write_halcon(cam, path)
    elif fmt == "ros":
        write_ros(cam, path)
    elif fmt == "opencv":
        _write_opencv_yaml(cam, Path(path))
    elif fmt == "json":
        Path(path).write_text(json.dumps(cam.to_dict(), indent=2) + "\n")
    else:
        raise InputError(f"unknown camera format {fmt!r}; choose from {FORMATS}")


# ------------------------------------------------------------------------------------------
# model conversion
@dataclass
class Conversion:
    """A converted camera and how well it reproduces the source.

    Attributes
    ----------
    camera : the converted camera.
    exact : True when the target model holds the source exactly.
    max_error_px, rms_error_px : worst and RMS pixel distance between the two cameras'
        projections of the same rays, over a grid covering the whole image (0 when exact).
    """

    camera: Camera
    exact: bool
    max_error_px: float = 0.0
    rms_error_px: float = 0.0


def _image_grid(cam: Camera, n: int = 41) -> np.ndarray:
    w, h = cam.image_size_px
    nu, nv = n, max(int(round(n * h / w)), 3)
    u, v = np.meshgrid(np.linspace(0, w - 1, nu), np.linspace(0, h - 1, nv))
    return np.stack([u.ravel(), v.ravel()], axis=1)


def _fit(src: Camera, build, x0, n: int = 41) -> Conversion:
    """Fit the parameters ``x`` of ``build(x) -> Camera`` so that it images the rays of the
    source camera's pixel grid at the same pixels (least squares over the whole image)."""
    from scipy.optimize import least_squares

    grid = _image_grid(src, n)
    rays = src.pixel_to_ray(grid)
    ok = np.all(np.isfinite(rays), axis=1)
    grid, rays = grid[ok], rays[ok]

    def fun(x):
        try:
            r = build(x).project(rays) - grid
        except CameraFileError:
            return np.full(2 * len(grid), 1e6)
        return np.nan_to_num(r, nan=1e6).ravel()

    res = least_squares(fun, x0, method="lm", xtol=1e-15, ftol=1e-15, gtol=1e-15,
                        max_nfev=2000, x_scale="jac")
    cam = build(res.x)
    # evaluate on a denser grid than the fit
    g2 = _image_grid(src, 2 * n + 1)
    r2 = src.pixel_to_ray(g2)
    err = np.linalg.norm(cam.project(r2) - g2, axis=1)
    err = err[np.isfinite(err)]
    return Conversion(cam, False, float(err.max()), float(np.sqrt(np.mean(err**2))))


def to_opencv(cam: Camera) -> Conversion:
    """The OpenCV model (k1, k2, p1, p2, k3) closest to ``cam`` over its image.

    For a division camera the radial series of its inverse,
    ``r_d = r_u (1 + kappa r_u^2 + 2 kappa^2 r_u^4 + 5 kappa^3 r_u^6 + ...)``, is truncated by
    the fit; ``K`` is kept (fx = f / sx, fy = f / sy).
    """
    if isinstance(cam, OpenCVCamera):
        return Conversion(cam, True)
    if isinstance(cam, PinholeCamera):
        return Conversion(OpenCVCamera(cam.K, np.zeros(5), cam.image_size_px, name=cam.name),
                          True)
    K = cam.K
    f = np.array([K[0, 0], K[1, 1]])

    def build(x):
        Kx = np.array([[f[0], 0, K[0, 2]], [0, f[1], K[1, 2]], [0, 0, 1.0]])
        p = (x[3], x[4]) if len(x) == 5 else (0.0, 0.0)  # tangential terms when the source has
        return OpenCVCamera(Kx, np.array([x[0], x[1], *p, x[2]]), cam.image_size_px,
                            name=cam.name)

    if isinstance(cam, DivisionCamera):
        # series start: r_d = r_u (1 + k r_u^2 + 2 k^2 r_u^4 + 5 k^3 r_u^6) in normalised units
        k = cam.kappa_per_m2 * cam.focal_length_m**2
        x0 = np.array([k, 2 * k * k, 5 * k**3])
    elif isinstance(cam, PolynomialCamera):  # first-order inverse of its radial series
        c = cam.normalized_coefficients()
        x0 = np.array([-c[0], 3 * c[0] ** 2 - c[1], 0.0, -c[2], -c[3]])
    else:
        x0 = np.zeros(3)
    return _fit(cam, build, x0)


def to_division(cam: Camera, pixel_height_m: float | None = None) -> Conversion:
    """The division model closest to ``cam`` over its image (exact for a skew-free pinhole).

    ``Sy`` is ``pixel_height_m`` (default: 3.45 um, :data:`DEFAULT_PIXEL_HEIGHT_M`); f, kappa,
    Sx, Cx, Cy are fitted. Tangential terms of an OpenCV camera cannot be represented; the
    principal point absorbs what it can.
    """
    if isinstance(cam, DivisionCamera) and pixel_height_m is None:
        return Conversion(cam, True)
    sy = float(pixel_height_m or DEFAULT_PIXEL_HEIGHT_M)
    K = cam.K
    if abs(K[0, 1]) > 1e-9 * K[0, 0]:
        raise InputError("the division model has no skew; this camera has K[0, 1] != 0")
    f0, sx0 = K[1, 1] * sy, sy * K[1, 1] / K[0, 0]
    if isinstance(cam, PinholeCamera):
        return Conversion(DivisionCamera(f0, 0.0, (sx0, sy), (K[0, 2], K[1, 2]),
                                         cam.image_size_px, name=cam.name), True)
    if isinstance(cam, DivisionCamera):  # re-express in another sy: exact
        s = sy / cam.pixel_size_m[1]
        return Conversion(DivisionCamera(cam.focal_length_m * s, cam.kappa_per_m2 / s**2,
                                         (cam.pixel_size_m[0] * s, sy), cam.principal_point_px,
                                         cam.image_size_px, name=cam.name), True)

    def build(x):
        x = [float(v) for v in x]
        return DivisionCamera(f0 * x[0], x[1] / sy**2, (sx0 * x[2], sy), (x[3], x[4]),
                              cam.image_size_px, name=cam.name)

    # kappa start from k1: 1 / (1 + kappa r_d^2) ~ 1 + k1 r^2  ->  kappa ~ -k1 / f^2
    k1 = float(cam.dist_coeffs[0]) if isinstance(cam, OpenCVCamera) else 0.0
    x0 = np.array([1.0, -k1 / K[1, 1] ** 2, 1.0, K[0, 2], K[1, 2]])
    return _fit(cam, build, x0)


def to_polynomial(cam: Camera, pixel_height_m: float | None = None) -> Conversion:
    """The HALCON polynomial model closest to ``cam`` over its image (exact for a skew-free
    pinhole and for a polynomial camera).

    ``Sy`` is ``pixel_height_m`` (default: the camera's own, else 3.45 um); f, K1, K2, K3,
    P1, P2, Sx, Cx, Cy are fitted. From the OpenCV model the start is the first-order inverse
    of its series (``K1 f^2 ~ -k1``, ``P1 f ~ -p1``, ``P2 f ~ -p2``): OpenCV's polynomial runs
    from ideal to distorted, HALCON's from distorted to ideal.
    """
    if isinstance(cam, PolynomialCamera):
        return Conversion(_rescale_polynomial(cam, pixel_height_m), True)
    sy = float(pixel_height_m or getattr(cam, "pixel_size_m", (0, DEFAULT_PIXEL_HEIGHT_M))[1])
    K = cam.K
    if abs(K[0, 1]) > 1e-9 * K[0, 0]:
        raise InputError("the polynomial model has no skew; this camera has K[0, 1] != 0")
    f0, sx0 = K[1, 1] * sy, sy * K[1, 1] / K[0, 0]
    if isinstance(cam, PinholeCamera):
        return Conversion(PolynomialCamera(f0, 0.0, 0.0, 0.0, 0.0, 0.0, (sx0, sy),
                                           (K[0, 2], K[1, 2]), cam.image_size_px,
                                           name=cam.name), True)

    def build(x):
        f = f0 * x[0]
        return PolynomialCamera(f, x[1] / f**2, x[2] / f**4, x[3] / f**6, x[4] / f, x[5] / f,
                                (sx0 * x[6], sy), (x[7], x[8]), cam.image_size_px,
                                name=cam.name)

    c = np.zeros(5)
    if isinstance(cam, OpenCVCamera):
        d = np.zeros(5)
        d[:min(5, cam.dist_coeffs.size)] = cam.dist_coeffs[:5]
        c = np.array([-d[0], 3 * d[0] ** 2 - d[1], 0.0, -d[2], -d[3]])
    elif isinstance(cam, DivisionCamera):
        c[0] = cam.kappa_per_m2 * cam.focal_length_m**2
    x0 = np.array([1.0, *c, 1.0, K[0, 2], K[1, 2]])
    return _fit(cam, build, x0)


def _rescale_polynomial(cam: PolynomialCamera, pixel_height_m: float | None):
    """The same polynomial camera expressed with pixel height ``pixel_height_m`` (exact: only
    f/Sx and f/Sy are observable; f, Sx and the coefficients scale with Sy)."""
    if pixel_height_m is None or pixel_height_m == cam.pixel_size_m[1]:
        return cam
    s = float(pixel_height_m) / cam.pixel_size_m[1]
    return PolynomialCamera(cam.focal_length_m * s, cam.k1_per_m2 / s**2, cam.k2_per_m4 / s**4,
                            cam.k3_per_m6 / s**6, cam.p1_per_m / s, cam.p2_per_m / s,
                            (cam.pixel_size_m[0] * s, float(pixel_height_m)),
                            cam.principal_point_px, cam.image_size_px, name=cam.name)


def convert_camera(cam: Camera, target_format: str,
                   pixel_height_m: float | None = None,
                   halcon_model: str | None = None) -> Conversion:
    """Convert ``cam`` to a model that ``target_format`` can hold.

    ``json`` holds every model (exact); ``halcon`` holds the division and polynomial models
    (``halcon_model`` chooses; by default a polynomial camera stays one and anything else
    becomes a division camera); ``opencv`` and
    ``ros`` need a pinhole or OpenCV camera. Division <-> radial polynomial is fitted (not
    exact) and the returned :class:`Conversion` gives the worst pixel error over the image.
    """
    if target_format == "json":
        return Conversion(cam, True)
    if target_format == "halcon":
        if halcon_model not in (None, "division", "polynomial"):
            raise InputError(f"HALCON model must be division or polynomial, got "
                             f"{halcon_model!r}")
        if halcon_model == "polynomial" or (halcon_model is None
                                            and isinstance(cam, PolynomialCamera)):
            return to_polynomial(cam, pixel_height_m)
        return to_division(cam, pixel_height_m)
    if target_format in ("opencv", "ros"):
        if isinstance(cam, (PinholeCamera, OpenCVCamera)):
            return Conversion(cam, True)
        return to_opencv(cam)
    raise InputError(f"unknown camera format {target_format!r}; choose from {FORMATS}")


def _read_opencv_yaml(path: Path) -> Camera:
    import cv2

    try:
        fs = cv2.FileStorage(str(path), cv2.FILE_STORAGE_READ)
    except (cv2.error, SystemError) as e:  # OpenCV's parser raises on malformed text
        raise CameraFileError(f"{path}: not a readable OpenCV FileStorage file "
                              f"({parse_error_text(e)})") from None
    if not fs.isOpened():
        raise CameraFileError(f"{path}: not a readable OpenCV FileStorage file")
    try:
        where = str(path)

        def node(key):
            n = fs.getNode(key)
            if n.empty():
                raise CameraFileError(f"{where}: missing field '{key}'")
            return n

        K = node("camera_matrix").mat()
        if K is None:
            raise CameraFileError(f"{where}: field 'camera_matrix' is not a matrix")
        dist = node("distortion_coefficients").mat()
        if dist is None:
            raise CameraFileError(f"{where}: field 'distortion_coefficients' is not a matrix")
        w = node("image_width").real()
        h = node("image_height").real()
        name = fs.getNode("name").string() if not fs.getNode("name").empty() else ""
    except (cv2.error, SystemError, UnicodeDecodeError) as e:  # a node of another shape
        raise CameraFileError(f"{where}: not an OpenCV camera file ({parse_error_text(e)})"
                              ) from None
    finally:
        fs.release()
    K = matrix_field(K, "camera_matrix", where)
    dist = np.asarray(dist, float).ravel()
    if dist.size == 0 or np.allclose(dist, 0):
        return PinholeCamera.from_matrix(K, check_image_size((w, h)), name=name)
    return OpenCVCamera(K, dist, (w, h), name=name)


def _write_opencv_yaml(cam: Camera, path: Path) -> None:
    import cv2

    if isinstance(cam, (DivisionCamera, PolynomialCamera)):
        raise CameraFileError(
            f"OpenCV YAML cannot hold the {cam.model} model exactly; convert it to the opencv "
            "model first (cutterpose camera convert)")
    fs = cv2.FileStorage(str(path), cv2.FILE_STORAGE_WRITE)
    fs.write("image_width", int(cam.image_size_px[0]))
    fs.write("image_height", int(cam.image_size_px[1]))
    fs.write("camera_matrix", cam.K)
    dist = cam.dist_coeffs if isinstance(cam, OpenCVCamera) else np.zeros(5)
    fs.write("distortion_coefficients", np.asarray(dist, float).reshape(1, -1))
    if cam.name:
        fs.write("name", cam.name)
    fs.release()


def load_camera(path) -> Camera:
    """Read a camera file: JSON (``.json``) or OpenCV YAML (``.yml``/``.yaml``/``.xml``); a HALCON
    camera parameter file (``.dat``/``.cal`` or ``ParGroup`` content) or a ROS camera_info YAML
    (``distortion_model`` key) is read by this module.

    Raises
    ------
    CameraFileError
        If the file is missing or malformed; the message names the field.
    """
    path = Path(path)
    if not path.is_file():
        raise CameraFileError(f"{path}: camera file not found")
    suffix = path.suffix.lower()
    fmt = sniff_format(path)
    if fmt == "halcon":
        return read_halcon(path)
    if fmt == "ros":
        return read_ros(path)
    if suffix in (".yml", ".yaml", ".xml"):
        return _read_opencv_yaml(path)
    return camera_from_dict(read_json(path, CameraFileError, "camera file"), where=str(path))


def save_camera(cam: Camera, path) -> None:
    """Write a camera as JSON (``.json``) or OpenCV YAML (``.yml``/``.yaml``/``.xml``); HALCON
    (``.dat``/``.cal``) and ROS camera_info (``.ros.yaml``, ``*camera_info*.yaml``) via
    this module."""
    path = Path(path)
    fmt = sniff_format(path, for_writing=True)
    if fmt == "halcon":
        write_halcon(cam, path)
    elif fmt == "ros":
        write_ros(cam, path)
    elif path.suffix.lower() in (".yml", ".yaml", ".xml"):
        _write_opencv_yaml(cam, path)
    else:
        path.write_text(json.dumps(cam.to_dict(), indent=2) + "\n")
