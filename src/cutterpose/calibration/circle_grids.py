"""Circle targets: the project's plate (``caltab``) and OpenCV's circle grids.

``circles:COLSxROWS:SPACING_MM`` and ``acircles:COLSxROWS:SPACING_MM`` are the symmetric and
asymmetric grids of OpenCV's ``findCirclesGrid`` with pattern size ``(COLS, ROWS)`` and its
point order (row by row, COLS points per row). Object points as in OpenCV's calibration sample
(``samples/cpp/calibration.cpp``, ``calcChessboardCorners``)::

    circles:  (j * s, i * s, 0)                 i < ROWS, j < COLS
    acircles: ((2 j + i mod 2) * s, i * s, 0)   i < ROWS, j < COLS

so ``s`` of an asymmetric grid is half the distance between neighbouring circles of one row
(the sample's ``squareSize``). Modifiers: ``light`` (light circles on a dark ground) and
``origin-dot`` (ROS-Industrial's "modified circle grid": the circle of point 0 is larger and
fixes the order; without it a symmetric grid keeps OpenCV's order up to 180 deg, or 90 deg
when square), ``diameter=MM`` (default s/2) and ``origin-diameter=MM`` (default 1.6 x the
diameter, at most 0.9 s).

ROS-Industrial's robot_cal_tools numbers the same modified grid with its origin at the large
dot, x along the large dot's row and z out of the target; its frame is this one turned by
180 deg about the diagonal x = y (``x_rct = y, y_rct = x, z_rct = -z``).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from ..errors import FeatureError, ImageError, InputError
from .circle_detect import (
    dark_blob_areas,
    detect_plate,
    find_circle_grid,
    grid_half_windows,
    refine_circle_centres,
    to_gray_u8,
)
from .plate import CirclePlate
from .targets import (
    Target,
    TargetDetection,
    choose_order,
    description_fields,
    no_more_modifiers,
    parse_grid_size,
    positive_number,
    register_target,
    symmetry_permutations,
)

__all__ = ["CaltabTarget", "CircleGridTarget", "AsymmetricCircleGridTarget"]

#: the origin dot must look this much larger (area) than the median circle
ORIGIN_DOT_MIN_AREA_RATIO = 1.3


@register_target
@dataclass(frozen=True)
class CaltabTarget(Target):
    """The project's circle plate with frame and triangular mark (:mod:`.plate`)."""

    plate: CirclePlate = CirclePlate()
    kind = "caltab"
    min_points = 9

    @property
    def points_target_mm(self) -> np.ndarray:
        return self.plate.points_mm

    def circle_outline_mm(self, n: int = 64) -> np.ndarray:
        return self.plate.circle_outline_mm(n)

    @property
    def rotation_symmetry_deg(self) -> int:
        return 0  # the triangle breaks every symmetry

    def detect(self, gray) -> TargetDetection:
        try:
            det = detect_plate(to_gray_u8(gray), self.plate)
        except (FeatureError, ImageError) as e:
            return TargetDetection.missing(str(e))
        return TargetDetection(det.points_px, np.arange(self.n_points), axes_px=det.axes_px,
                               info={"mark_contrast": det.mark_contrast})

    @property
    def bounds_mm(self):
        ex, ey = self.plate.half_extent_mm
        return (-ex, ex, -ey, ey)

    def darkness(self, x_mm, y_mm, blur_mm):
        return self.plate.darkness(x_mm, y_mm, blur_mm)

    def to_dict(self) -> dict:
        return {"kind": self.kind, **{k: v for k, v in self.plate.to_dict().items()
                                      if k != "kind"}}

    @classmethod
    def from_dict(cls, d, where="target"):
        return cls(CirclePlate.from_dict(d, where))

    @classmethod
    def from_spec(cls, fields, options):
        if len(fields) != 2:
            raise InputError("caltab target: give caltab:COLSxROWS:SPACING_MM (e.g. caltab:7x7:30)")
        cols, rows = parse_grid_size(fields[0], "caltab target")
        s = positive_number(fields[1], "caltab spacing")
        d = positive_number(options.pop("diameter", 0.5 * s), "caltab diameter")
        no_more_modifiers(options, "caltab")
        try:
            return cls(CirclePlate(rows=rows, cols=cols, spacing_mm=s, diameter_mm=d))
        except InputError as e:
            raise InputError(f"caltab target: {e}") from None

    def spec(self) -> str:
        p = self.plate
        out = f"caltab:{p.cols}x{p.rows}:{p.spacing_mm:g}"
        return out + (f":diameter={p.diameter_mm:g}" if p.diameter_mm != 0.5 * p.spacing_mm
                      else "")


@register_target
@dataclass(frozen=True)
class CircleGridTarget(Target):
    """OpenCV's symmetric circle grid (module docstring), optionally light or with an origin
    dot."""

    cols: int
    rows: int
    spacing_mm: float
    diameter_mm: float | None = None
    light: bool = False
    origin_dot: bool = False
    origin_diameter_mm: float | None = None
    kind = "circles"
    asymmetric = False

    def __post_init__(self):
        if self.cols < 2 or self.rows < 2 or self.cols * self.rows < 4:
            raise InputError(f"{self.kind} target: the grid must be at least 2x2 with 4 "
                             f"points, got {self.cols}x{self.rows}")
        if self.diameter_mm is None:
            object.__setattr__(self, "diameter_mm", 0.5 * self.spacing_mm)
        if self.origin_diameter_mm is None:
            od = min(1.6 * self.diameter_mm, 0.9 * self.nearest_mm)
            object.__setattr__(self, "origin_diameter_mm", od if self.origin_dot else None)
        if not 0 < self.diameter_mm < self.nearest_mm:
            raise InputError(f"{self.kind} target: the diameter must be below the distance "
                             f"between neighbouring circles ({self.nearest_mm:g} mm)")
        if self.origin_dot and not (self.diameter_mm < self.origin_diameter_mm
                                    < self.nearest_mm):
            raise InputError(f"{self.kind} target: the origin dot's diameter must lie between "
                             f"the circles' ({self.diameter_mm:g}) and {self.nearest_mm:g} mm")

    @property
    def nearest_mm(self) -> float:
        """Distance between neighbouring circles."""
        return self.spacing_mm * (np.sqrt(2.0) if self.asymmetric else 1.0)

    # --- geometry -----------------------------------------------------------------------------
    @property
    def points_target_mm(self) -> np.ndarray:
        i, j = np.mgrid[0:self.rows, 0:self.cols]
        i, j = i.ravel(), j.ravel()
        x = (2 * j + i % 2) if self.asymmetric else j
        return np.stack([x * self.spacing_mm, i * self.spacing_mm, 0.0 * i], 1).astype(float)

    @property
    def radii_mm(self) -> np.ndarray:
        r = np.full(self.n_points, 0.5 * self.diameter_mm)
        if self.origin_dot:
            r[0] = 0.5 * self.origin_diameter_mm
        return r

    def point_labels(self):
        if not self.origin_dot:
            return None
        lab = np.zeros(self.n_points)
        lab[0] = 1
        return lab

    def circle_outline_mm(self, n: int = 64) -> np.ndarray:
        a = np.linspace(0, 2 * np.pi, n, endpoint=False)
        ring = np.stack([np.cos(a), np.sin(a), 0 * a], axis=1)
        return self.points_target_mm[:, None, :] + self.radii_mm[:, None, None] * ring[None]

    # --- rendering ----------------------------------------------------------------------------
    @property
    def bounds_mm(self):
        P = self.points_target_mm
        m = self.spacing_mm + self.radii_mm.max()
        return (P[:, 0].min() - m, P[:, 0].max() + m, P[:, 1].min() - m, P[:, 1].max() + m)

    def darkness(self, x_mm, y_mm, blur_mm):
        x, y = np.asarray(x_mm, float), np.asarray(y_mm, float)
        s, r = self.spacing_mm, 0.5 * self.diameter_mm
        # distance to the nearest circle edge, lattice by lattice: a symmetric grid is one
        # lattice; an asymmetric one is two (even rows at (2 j s, 2 k s), odd rows shifted s)
        lattices = ([(0.0, 0.0, 2 * s, 2 * s, self.cols, (self.rows + 1) // 2),
                     (s, s, 2 * s, 2 * s, self.cols, self.rows // 2)] if self.asymmetric
                    else [(0.0, 0.0, s, s, self.cols, self.rows)])
        d = np.full(x.shape, np.inf)
        for ox, oy, sx, sy, nx, ny in lattices:
            if ny == 0:
                continue
            j = np.clip(np.rint((x - ox) / sx), 0, nx - 1)
            i = np.clip(np.rint((y - oy) / sy), 0, ny - 1)
            d = np.minimum(d, np.hypot(x - ox - j * sx, y - oy - i * sy) - r)
        if self.origin_dot:  # the larger circle of point 0 at the origin covers its own
            d = np.minimum(d, np.hypot(x, y) - 0.5 * self.origin_diameter_mm)
        circle = np.clip(0.5 - d / np.maximum(blur_mm, 1e-9), 0.0, 1.0)
        return 1.0 - circle if self.light else circle

    # --- detection ----------------------------------------------------------------------------
    def detect(self, gray) -> TargetDetection:
        try:
            g = to_gray_u8(gray)
        except ImageError as e:
            return TargetDetection.missing(str(e))
        if self.light:
            g = 255 - g  # light marks on a dark ground: the same detector on the negative
        d_over_s = self.diameter_mm / self.spacing_mm
        rough = find_circle_grid(g, self.cols, self.rows, d_over_s, asymmetric=self.asymmetric)
        if rough is None:
            return TargetDetection.missing(f"{self.cols}x{self.rows} "
                                           f"{'asymmetric ' if self.asymmetric else ''}circle "
                                           "grid not found")
        half = grid_half_windows(rough, self.cols, self.rows, asymmetric=self.asymmetric)
        centres, axes, reasons = refine_circle_centres(g, rough, half)
        ok = np.all(np.isfinite(centres), axis=1)
        pts = np.where(ok[:, None], centres, rough)  # order on all points; drop failed later
        score = None
        if self.origin_dot:
            # the dot labelled 0 against its 3 nearest neighbours on the target (perspective
            # changes sizes across the target, hardly between neighbours)
            P = self.points_target_mm[:, :2]
            near = np.argsort(np.linalg.norm(P - P[0], axis=1))[1:4]
            cache: dict[int, float] = {}

            def area(k):  # dark area at image point k, measured when first needed
                if k not in cache:
                    a = dark_blob_areas(g, rough[k:k + 1], 1.5 * half[k])[0]
                    cache[k] = 0.0 if not np.isfinite(a) else float(a)
                return cache[k]

            def score(ids):
                where = np.argsort(ids)  # image index of each object point
                return area(where[0]) / max(float(np.median([area(k) for k in where[near]])),
                                            1e-9)

        perms = symmetry_permutations(self.points_target_mm[:, :2])
        ids, amb, why = choose_order(self.points_target_mm, pts, perms, score,
                                     ORIGIN_DOT_MIN_AREA_RATIO if self.origin_dot else None)
        if ids is None:
            return TargetDetection.missing(("origin dot not found: " if self.origin_dot else "")
                                           + why)
        info = {"failed_circles": list(reasons.values())} if reasons else {}
        if ok.sum() < self.min_points:
            return TargetDetection.missing(f"only {ok.sum()} circles measured; "
                                           + "; ".join(reasons.values()))
        return TargetDetection(centres[ok], ids[ok], amb, axes_px=axes[ok], info=info)

    # --- description --------------------------------------------------------------------------
    def to_dict(self) -> dict:
        d = {"kind": self.kind, "cols": self.cols, "rows": self.rows,
             "spacing_mm": self.spacing_mm, "diameter_mm": self.diameter_mm,
             "light": self.light, "origin_dot": self.origin_dot}
        if self.origin_dot:
            d["origin_diameter_mm"] = self.origin_diameter_mm
        return d

    @classmethod
    def from_dict(cls, d, where="target"):
        with description_fields(where):
            return cls(int(d["cols"]), int(d["rows"]), float(d["spacing_mm"]),
                       _opt_float(d.get("diameter_mm")), bool(d.get("light", False)),
                       bool(d.get("origin_dot", False)), _opt_float(d.get("origin_diameter_mm")))

    @classmethod
    def from_spec(cls, fields, options):
        if len(fields) != 2:
            raise InputError(f"{cls.kind} target: give {cls.kind}:COLSxROWS:SPACING_MM"
                             f"[:light][:origin-dot] (e.g. {cls.kind}:4x11:20)")
        cols, rows = parse_grid_size(fields[0], f"{cls.kind} target")
        s = positive_number(fields[1], f"{cls.kind} spacing")
        opts = dict(options)
        light = bool(opts.pop("light", False))
        origin = bool(opts.pop("origin-dot", False))
        d = opts.pop("diameter", None)
        od = opts.pop("origin-diameter", None)
        no_more_modifiers(opts, cls.kind)
        return cls(cols, rows, s, None if d is None else positive_number(d, "diameter"), light,
                   origin, None if od is None else positive_number(od, "origin-diameter"))

    def spec(self) -> str:
        out = f"{self.kind}:{self.cols}x{self.rows}:{self.spacing_mm:g}"
        if self.light:
            out += ":light"
        if self.origin_dot:
            out += ":origin-dot"
        if self.diameter_mm != 0.5 * self.spacing_mm:
            out += f":diameter={self.diameter_mm:g}"
        if self.origin_dot and self.origin_diameter_mm != min(1.6 * self.diameter_mm,
                                                              0.9 * self.nearest_mm):
            out += f":origin-diameter={self.origin_diameter_mm:g}"
        return out


def _opt_float(v):
    return None if v is None else float(v)


@register_target
@dataclass(frozen=True)
class AsymmetricCircleGridTarget(CircleGridTarget):
    """OpenCV's asymmetric circle grid (module docstring)."""

    kind = "acircles"
    asymmetric = True
