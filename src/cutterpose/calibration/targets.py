"""Calibration targets: the interface, the registry of kinds, and target specs and files.

A target is a class (registered by its ``kind`` name, in the manner of scikit-image's
``transform`` registry) that knows

* its object points ``points_target_mm`` (N, 3) in the target frame (z = 0 on the printed face);
* how to find them in a grey image: ``detect(gray) -> TargetDetection`` with the image points,
  their ``ids`` (rows of ``points_target_mm``; partial views give a subset) and whether the
  order is unique or only known up to a rotation of the target (a plain grid: 180 deg);
* what it looks like, for the plate renderer: ``darkness(x_mm, y_mm, blur_mm)`` (printed ink
  coverage in [0, 1]) inside ``bounds_mm``, and ``circle_outline_mm`` for circle targets (the
  ellipse-centre bias correction of :mod:`cutterpose.calibration.intrinsics`).

Targets are named by a spec string or a file (:func:`target_from_spec`):

=========================================================  =====================================
``caltab:7x7:30``                                          the project's plate (frame + triangle
                                                           mark; :mod:`.plate`), the default
``circles:COLSxROWS:SPACING_MM[:light][:origin-dot]``      OpenCV symmetric circle grid
``acircles:COLSxROWS:SPACING_MM[:light][:origin-dot]``     OpenCV asymmetric circle grid
``chessboard:COLSxROWS:SQUARE_MM``                         inner corners, as OpenCV counts them
``charuco:COLSxROWS:SQUARE_MM:MARKER_MM:DICT``             squares, as cv2.aruco.CharucoBoard
``path/to/target.yaml`` (or ``.json``)                     the fields of a kind (see
                                                           docs/calibration_targets.md)
``path/to/plate.descr`` / ``.cpd``                         HALCON description files
=========================================================  =====================================

Further ``key=value`` modifiers set optional sizes, e.g. ``circles:6x6:30:diameter=20``.

HALCON files are read by :mod:`cutterpose.calibration.halcon_plate` (imported only when such a
file is named): it provides ``HalconPlate``, a :class:`Target` with a classmethod
``from_file(path)``.

Convention:
    Target frame: x along a row of points (increasing column index), y along a column, z into
    the target (away from a camera that sees its printed face), so a target seen face-on looks
    like ``points_target_mm`` drawn with x right and y down. With a camera that does not mirror,
    the detected order is therefore always right-handed in the image.
"""

from __future__ import annotations

import importlib
import json
from abc import ABC, abstractmethod
from contextlib import contextmanager
from dataclasses import dataclass, field
from pathlib import Path
from typing import ClassVar

import numpy as np

from ..errors import InputError, ModelFileError
from ..geometry.jsonfile import parse_error_text

__all__ = ["TargetDetection", "Target", "TARGET_KINDS", "register_target", "target_from_spec",
           "target_from_dict", "load_target", "save_target", "symmetry_permutations",
           "choose_order",
           "DEFAULT_TARGET_SPEC"]

DEFAULT_TARGET_SPEC = "caltab:7x7:30"

# kind -> class; filled by register_target in the modules of _BUILTIN_MODULES
TARGET_KINDS: dict[str, type[Target]] = {}
_BUILTIN_MODULES = (".circle_grids", ".boards", ".halcon_plate")
# file suffix -> (module, class) read lazily, so this module works without them
_FILE_KINDS = {".descr": (".halcon_plate", "HalconPlate"), ".cpd": (".halcon_plate", "HalconPlate")}


@dataclass
class TargetDetection:
    """Target points found in one image (falsy, with ``reason``, when not found).

    Attributes
    ----------
    points_px : (M, 2) image points (observed pixels, pixel centres at integers).
    ids : (M,) rows of the target's ``points_target_mm`` that the points are images of.
    rotation_ambiguity_deg : 0 when the order is unique; otherwise the target is symmetric
        and the order is known only up to rotations of the target by this angle (a plain circle
        grid: 180, a square one: 90). Intrinsic calibration does not care; a hand-eye
        calibration must resolve it.
    reason : why the target was not found ('' when found).
    axes_px : (M, 2) full axes of the fitted image ellipses (circle targets), else None.
    info : other figures of the detector (e.g. the orientation mark's contrast).
    """

    points_px: np.ndarray
    ids: np.ndarray
    rotation_ambiguity_deg: int = 0
    reason: str = ""
    axes_px: np.ndarray | None = None
    info: dict = field(default_factory=dict)

    def __post_init__(self):
        self.points_px = np.asarray(self.points_px, float).reshape(-1, 2)
        self.ids = np.asarray(self.ids, int).ravel()
        if len(self.ids) != len(self.points_px):
            raise InputError(f"detection: {len(self.ids)} ids for {len(self.points_px)} points")

    def __bool__(self) -> bool:
        return not self.reason and len(self.ids) > 0

    @property
    def unambiguous(self) -> bool:
        return self.rotation_ambiguity_deg == 0

    @classmethod
    def missing(cls, reason: str, **info) -> TargetDetection:
        """A failed detection with its reason."""
        return cls(np.zeros((0, 2)), np.zeros(0, int), reason=reason or "not found", info=info)


class Target(ABC):
    """A calibration target (see the module docstring for the convention)."""

    kind: ClassVar[str] = ""
    #: fewest points one view must show to be used (a homography needs 4; more for stability)
    min_points: ClassVar[int] = 4

    # --- geometry -----------------------------------------------------------------------------
    @property
    @abstractmethod
    def points_target_mm(self) -> np.ndarray:
        """(N, 3) object points in the target frame, in the order ``ids`` index."""

    @property
    def n_points(self) -> int:
        return len(self.points_target_mm)

    def circle_outline_mm(self, n: int = 64) -> np.ndarray | None:
        """(N, n, 3) points on every mark's circular edge (circle targets), else None."""
        return None

    @property
    def rotation_symmetry_deg(self) -> int:
        """Smallest in-plane rotation (deg) that maps the target onto itself, 0 if none."""
        perms = symmetry_permutations(self.points_target_mm[:, :2], self.point_labels(),
                                      reflections=False)
        return 360 // len(perms) if len(perms) > 1 else 0

    def point_labels(self) -> np.ndarray | None:
        """Per-point labels that break the symmetry of the points (e.g. a larger origin dot)."""
        return None

    # --- detection ----------------------------------------------------------------------------
    @abstractmethod
    def detect(self, gray: np.ndarray) -> TargetDetection:
        """Find the target's points in a grey (H, W) image; never raises on a bad image."""

    # --- rendering ----------------------------------------------------------------------------
    @property
    @abstractmethod
    def bounds_mm(self) -> tuple[float, float, float, float]:
        """(x_min, x_max, y_min, y_max) of the printed target (with its margin) on z = 0."""

    @abstractmethod
    def darkness(self, x_mm: np.ndarray, y_mm: np.ndarray, blur_mm) -> np.ndarray:
        """Anti-aliased ink coverage in [0, 1] at target points (1 = printed black); ``blur_mm``
        is one pixel's footprint there (the ramp width of every edge)."""

    def outline_mm(self, n_per_side: int = 32) -> np.ndarray:
        """(4 n, 3) points on the target's outer edge (for image bounding boxes)."""
        x0, x1, y0, y1 = self.bounds_mm
        t = np.linspace(0.0, 1.0, n_per_side, endpoint=False)
        xs = np.concatenate([x0 + t * (x1 - x0), np.full_like(t, x1), x1 - t * (x1 - x0),
                             np.full_like(t, x0)])
        ys = np.concatenate([np.full_like(t, y0), y0 + t * (y1 - y0), np.full_like(t, y1),
                             y1 - t * (y1 - y0)])
        return np.stack([xs, ys, np.zeros_like(xs)], axis=1)

    # --- description --------------------------------------------------------------------------
    @abstractmethod
    def to_dict(self) -> dict:
        """The target file's fields (``kind`` first); :func:`target_from_dict` reads them."""

    @classmethod
    @abstractmethod
    def from_dict(cls, d: dict, where: str = "target") -> Target:
        """Build from a target file's fields (raise ModelFileError on bad fields)."""

    @classmethod
    @abstractmethod
    def from_spec(cls, fields: list[str], options: dict) -> Target:
        """Build from a spec's ``:``-separated fields after the kind, and its modifiers
        (bare words map to True, ``key=value`` to the string value); raise InputError."""

    def spec(self) -> str:
        """The spec string that names this target (round-trips through target_from_spec)."""
        raise NotImplementedError

    def describe(self) -> str:
        return self.spec()

    def __repr__(self) -> str:
        return f"<{type(self).__name__} {self.describe()}>"


def register_target(cls: type[Target]) -> type[Target]:
    """Class decorator: make a Target kind available by its ``kind`` name."""
    if not cls.kind:
        raise TypeError(f"{cls.__name__} has no kind name")
    TARGET_KINDS[cls.kind] = cls
    return cls


def _load_builtin_kinds() -> None:
    for mod in _BUILTIN_MODULES:
        importlib.import_module(mod, __package__)


# ------------------------------------------------------------------------------------------
# specs and files
def parse_grid_size(text: str, what: str) -> tuple[int, int]:
    try:
        cols, rows = (int(v) for v in text.lower().split("x"))
    except ValueError:
        raise InputError(f"{what}: the size must look like COLSxROWS (e.g. 9x6), got "
                         f"{text!r}") from None
    if cols < 1 or rows < 1:
        raise InputError(f"{what}: the size must be positive, got {text!r}")
    return cols, rows


def positive_number(v, what: str) -> float:
    """``v`` as a positive float, or an InputError naming ``what``."""
    try:
        x = float(v)
    except (TypeError, ValueError, OverflowError):
        raise InputError(f"{what} must be a number, got {v!r}") from None
    if not x > 0:
        raise InputError(f"{what} must be positive, got {v!r}")
    return x


def no_more_modifiers(options: dict, what: str) -> None:
    """Refuse modifiers a target kind does not know."""
    if options:
        raise InputError(f"{what} target: unknown modifier(s) {', '.join(sorted(options))}")


@contextmanager
def description_fields(where: str):
    """Turn a missing or malformed field of a target description into one ModelFileError."""
    try:
        yield
    except KeyError as e:
        raise ModelFileError(f"{where}: missing field {e}") from None
    except (TypeError, ValueError, InputError, OverflowError) as e:
        raise ModelFileError(f"{where}: {e}") from None


def parse_spec_fields(spec: str) -> tuple[str, list[str], dict]:
    """Split ``kind:f1:f2:...:mod:key=value`` into the kind, positional fields, modifiers."""
    parts = [p.strip() for p in spec.split(":")]
    kind = parts[0].lower()
    fields, options = [], {}
    for p in parts[1:]:
        if not p:
            raise InputError(f"target {spec!r}: empty field")
        if "=" in p:
            k, v = p.split("=", 1)
            options[k.strip().lower().replace("_", "-")] = v.strip()
        elif p[0].isalpha() and not fields_are_dict_name(kind, fields, p):
            options[p.lower()] = True
        else:
            fields.append(p)
    return kind, fields, options


def fields_are_dict_name(kind: str, fields: list, p: str) -> bool:
    # charuco's 4th positional field is a dictionary name (letters), not a modifier
    return kind == "charuco" and len(fields) == 3


def target_from_spec(spec) -> Target:
    """The target named by ``spec``: a Target (returned as is), a spec string, or a file path
    (``.yaml``/``.yml``/``.json`` target file or ``plate.json``; ``.descr``/``.cpd`` HALCON).

    Raises
    ------
    InputError
        An unknown kind or malformed spec (the message lists the kinds).
    ModelFileError
        A target file that cannot be read.
    """
    if isinstance(spec, Target):
        return spec
    if spec is None or (isinstance(spec, str) and not spec.strip()):
        spec = DEFAULT_TARGET_SPEC
    text = str(spec).strip()
    path = Path(text)
    suffix = path.suffix.lower()
    if suffix in _FILE_KINDS:
        return _target_from_plugin_file(path, suffix)
    if suffix in (".yaml", ".yml", ".json"):
        return load_target(path)
    _load_builtin_kinds()
    kind, fields, options = parse_spec_fields(text)
    if kind not in TARGET_KINDS:
        known = ", ".join(sorted(TARGET_KINDS))
        raise InputError(f"unknown target {text!r}: give one of the kinds {known} (e.g. "
                         "circles:6x6:30), a target file (.yaml/.json) or a HALCON .descr/.cpd")
    return TARGET_KINDS[kind].from_spec(fields, options)


def _target_from_plugin_file(path: Path, suffix: str) -> Target:
    mod_name, cls_name = _FILE_KINDS[suffix]
    try:
        mod = importlib.import_module(mod_name, __package__)
    except ImportError as e:
        raise InputError(f"{path}: {suffix} target files need cutterpose.calibration"
                         f"{mod_name}, which is not available ({e})") from None
    if not path.is_file():
        raise ModelFileError(f"target file not found: {path}")
    return getattr(mod, cls_name).from_file(path)


def target_from_dict(d: dict, where: str = "target") -> Target:
    """A target from a target file's fields (``kind`` selects the class; a ``spec`` field
    may stand for all of them)."""
    _load_builtin_kinds()
    if not isinstance(d, dict):
        raise ModelFileError(f"{where}: expected a mapping with a 'kind' field")
    if "spec" in d and "kind" not in d:
        try:
            return target_from_spec(str(d["spec"]))
        except InputError as e:
            raise ModelFileError(f"{where}: {e}") from None
    kind = str(d.get("kind", "")).lower()
    if kind == "circle_grid_plate":  # plate.json as written by save_plate
        kind = "caltab"
    if kind not in TARGET_KINDS:
        raise ModelFileError(f"{where}: unknown target kind {kind!r} (known: "
                             f"{', '.join(sorted(TARGET_KINDS))})")
    return TARGET_KINDS[kind].from_dict(d, where)


def load_target(path) -> Target:
    """Read a target file (YAML or JSON; docs/calibration_targets.md)."""
    path = Path(path)
    if not path.is_file():
        raise ModelFileError(f"target file not found: {path}")
    try:
        text = path.read_text()
        if path.suffix.lower() == ".json":
            d = json.loads(text)
        else:
            import yaml

            d = yaml.safe_load(text)
    except (OSError, UnicodeDecodeError, ValueError) as e:
        raise ModelFileError(f"{path}: cannot read the target file ({parse_error_text(e)})"
                             ) from None
    except Exception as e:  # yaml.YAMLError without importing yaml at module level
        raise ModelFileError(f"{path}: not valid YAML ({parse_error_text(e)})") from None
    if isinstance(d, dict) and isinstance(d.get("target"), dict):
        d = d["target"]
    return target_from_dict(d, str(path))


def save_target(target: Target, path) -> None:
    """Write a target file (JSON for .json, else YAML)."""
    path = Path(path)
    d = target.to_dict()
    if path.suffix.lower() == ".json":
        path.write_text(json.dumps(d, indent=2) + "\n")
    else:
        import yaml

        path.write_text(yaml.safe_dump(d, sort_keys=False))


# ------------------------------------------------------------------------------------------
# symmetry
def symmetry_permutations(points_xy: np.ndarray, labels: np.ndarray | None = None, *,
                          reflections: bool = True, tol: float = 1e-6) -> list[np.ndarray]:
    """Index permutations ``p`` of the in-plane symmetries of a labelled point set.

    A symmetry ``g`` (a rotation by a multiple of 90 deg about the centroid, or such a rotation
    after a mirror about the x axis) maps the set onto itself: ``g(points[k]) = points[p[k]]``
    with equal labels. The identity comes first. A detector that returns points in an order
    fixed only up to such ``g`` can try every ``p`` (e.g. keep the right-handed ones, or the one
    that puts a larger origin dot first).
    """
    from scipy.spatial import cKDTree

    P = np.asarray(points_xy, float)[:, :2]
    lab = np.zeros(len(P)) if labels is None else np.asarray(labels, float)
    Q = P - P.mean(axis=0)
    tree = cKDTree(Q)
    scale = max(float(np.abs(Q).max()), 1e-12)
    quarter = np.array([[0.0, -1.0], [1.0, 0.0]])
    perms = []
    for mirror in ((False, True) if reflections else (False,)):
        for r in range(4):
            M = np.linalg.matrix_power(quarter, r) @ (np.diag([1.0, -1.0]) if mirror else np.eye(2))
            d, p = tree.query(Q @ M.T)
            if (np.all(d < tol * scale) and len(np.unique(p)) == len(p)
                    and np.all(lab[p] == lab)):
                perms.append(p)
    return perms


def _orientation_sign(H: np.ndarray, xy: np.ndarray) -> float:
    """Sign of the Jacobian determinant of the homography ``H`` at the plane point ``xy``
    (``det J = det H / w^3``): positive when the image keeps the target's handedness."""
    w = H[2, 0] * xy[0] + H[2, 1] * xy[1] + H[2, 2]
    return float(np.sign(np.linalg.det(H)) * np.sign(w) ** 3)


def choose_order(points_xy_target: np.ndarray, points_px: np.ndarray, perms: list,
                 label_score=None, min_score: float | None = None):
    """Which object point each detected point is, for a detector whose order is fixed only up
    to the target's symmetries.

    Parameters
    ----------
    points_xy_target : (N, 2) object points.
    points_px : (N, 2) image points in the detector's order.
    perms : :func:`symmetry_permutations` of the target (identity first): candidate ``ids``.
    label_score : optional ``f(ids) -> float``, how well the image shows the target's marks
        under a candidate (e.g. the size of the dot labelled as the origin dot); the best
        candidate must reach ``min_score``.

    Returns
    -------
    ``(ids, rotation_ambiguity_deg, reason)``: ``ids`` (N,) of the first right-handed
    candidate (the detector's own order when it is right-handed) that the marks support, the
    angle of the rotations that remain possible (0 when unique), and ``reason`` ('' on success).
    """
    import cv2

    obj = np.asarray(points_xy_target, float)[:, :2]
    img = np.asarray(points_px, float)
    keep = []
    for p in perms:
        H, _ = cv2.findHomography(obj[p], img, 0)
        if H is not None and _orientation_sign(H, obj.mean(axis=0)) > 0:
            keep.append(p)
    if not keep:
        return None, 0, "the detected points do not map the target by a homography"
    if label_score is not None:
        scores = np.array([label_score(p) for p in keep])
        best = int(np.argmax(scores))
        if min_score is None:
            keep = [keep[best]]
        elif not scores[best] >= min_score:
            return None, 0, f"mark score {scores[best]:.2f} below {min_score:.2f}"
        else:  # every candidate the marks support (a symmetric pattern of marks: several)
            keep = [p for p, sc in zip(keep, scores) if sc >= min_score]
    amb = 360 // len(keep) if len(keep) > 1 else 0
    return np.asarray(keep[0], int), amb, ""
