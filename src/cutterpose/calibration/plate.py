"""The 7x7 circle calibration plate: its geometry, its file, and a renderer.

Convention:
    Plate frame: origin at the centre of the circle grid, x along the grid rows (increasing
    column index ``j``), y along the grid columns (increasing row index ``i``), z into the plate
    (away from a camera that sees its printed face), so a plate seen face-on with ``R = I`` looks
    like the image: x right, y down. Units are millimetres. Point ``k = i * cols + j`` lies at

        x_k = (j - (cols - 1) / 2) * spacing_mm,   y_k = (i - (rows - 1) / 2) * spacing_mm.

    A pose ``x_cam = R_cam_plate @ x_plate + t_cam_plate_mm`` places the plate in the camera.

Layout (dark marks on a light plate, the common kind; sizes in units of the spacing ``s``):
    circles of diameter ``diameter_mm`` (default 15 mm, spacing 30 mm); a dark frame band from
    ``frame_inner`` to ``frame_outer`` (default 3.75 s and 4.25 s from the centre, for a 7x7 grid
    the circles end at 3.25 s); a dark right triangle with legs ``mark_leg`` (0.55 s) in the
    inner corner of the frame next to circle 0 (top-left, at ``(-3 s, -3 s)``). The frame and
    the triangle follow the plates sold for HALCON (a border with a triangular corner mark). The
    triangle breaks the grid's 8-fold symmetry: it fixes which corner circle is point 0, and the
    sign of the image orientation fixes the direction of the rows.

References:
    MVTec HALCON, ``create_caltab`` / ``gen_caltab`` (plate with border and orientation mark).
"""

from __future__ import annotations

import json
from dataclasses import asdict, dataclass
from pathlib import Path

import numpy as np

from ..errors import InputError, ModelFileError
from ..geometry.camera import Camera
from ..geometry.jsonfile import read_json
from ..geometry.pose import Pose

__all__ = ["CirclePlate", "load_plate", "save_plate", "render_plate", "sample_plate_poses",
           "apply_sensor_effects", "ellipse_center_bias_px"]


@dataclass(frozen=True)
class CirclePlate:
    """Geometry of a circle-grid calibration plate (see the module docstring for the layout).

    Parameters
    ----------
    rows, cols : grid size (7 x 7 by default).
    spacing_mm : centre-to-centre distance of neighbouring circles.
    diameter_mm : circle diameter.
    frame_inner, frame_outer : inner and outer half-width of the dark frame band, in units of
        the spacing, measured from the grid centre along x (and y).
    mark_leg : leg length of the triangular orientation mark, in units of the spacing.
    """

    rows: int = 7
    cols: int = 7
    spacing_mm: float = 30.0
    diameter_mm: float = 15.0
    frame_inner: float = 3.75
    frame_outer: float = 4.25
    mark_leg: float = 0.55

    def __post_init__(self):
        if int(self.rows) < 3 or int(self.cols) < 3:
            raise InputError(f"plate grid must be at least 3x3, got {self.rows}x{self.cols}")
        if not (self.spacing_mm > 0 and 0 < self.diameter_mm < self.spacing_mm):
            raise InputError("plate: need spacing_mm > 0 and 0 < diameter_mm < spacing_mm, got "
                             f"{self.spacing_mm} and {self.diameter_mm}")
        half = 0.5 * (max(self.rows, self.cols) - 1) + 0.5 * self.diameter_mm / self.spacing_mm
        if not (half < self.frame_inner < self.frame_outer):
            raise InputError("plate: the frame must lie outside the circles "
                             f"(frame_inner {self.frame_inner} > {half:.3f} spacings)")

    # --- geometry ---------------------------------------------------------------------------
    @property
    def n_points(self) -> int:
        return self.rows * self.cols

    @property
    def points_mm(self) -> np.ndarray:
        """(rows*cols, 3) circle centres in the plate frame, row-major (z = 0)."""
        i, j = np.mgrid[0:self.rows, 0:self.cols]
        x = (j.ravel() - 0.5 * (self.cols - 1)) * self.spacing_mm
        y = (i.ravel() - 0.5 * (self.rows - 1)) * self.spacing_mm
        return np.stack([x, y, np.zeros_like(x)], axis=1).astype(float)

    @property
    def points_target_mm(self) -> np.ndarray:
        """Same as :attr:`points_mm` (the name every calibration target uses)."""
        return self.points_mm

    @property
    def bounds_mm(self) -> tuple[float, float, float, float]:
        """(x_min, x_max, y_min, y_max) of the plate's outer edge."""
        ex, ey = self.half_extent_mm
        return (-ex, ex, -ey, ey)

    @property
    def half_extent_mm(self) -> tuple[float, float]:
        """Half-width (x) and half-height (y) of the plate's outer edge."""
        s = self.spacing_mm
        ex = 0.5 * (self.cols - 1) + (self.frame_outer - 0.5 * (max(self.rows, self.cols) - 1))
        ey = 0.5 * (self.rows - 1) + (self.frame_outer - 0.5 * (max(self.rows, self.cols) - 1))
        return ex * s, ey * s

    def _frame_half_mm(self, which: float) -> tuple[float, float]:
        # the frame keeps the same distance from the outer circles on every side
        s = self.spacing_mm
        off = which - 0.5 * (max(self.rows, self.cols) - 1)
        return (0.5 * (self.cols - 1) + off) * s, (0.5 * (self.rows - 1) + off) * s

    @property
    def mark_vertices_mm(self) -> np.ndarray:
        """(3, 2) vertices of the triangular mark in the frame's inner corner next to point 0."""
        ix, iy = self._frame_half_mm(self.frame_inner)
        leg = self.mark_leg * self.spacing_mm
        return np.array([[-ix, -iy], [-ix + leg, -iy], [-ix, -iy + leg]])

    def mark_probe_mm(self) -> np.ndarray:
        """(4, 2) centroids of the mark at its own corner and at the three other corners.

        Index 0 is the real mark (corner of point 0); 1, 2, 3 are the mirror images at the
        corners of points ``cols-1``, ``n-1`` and ``(rows-1)*cols``. Only index 0 is dark.
        """
        c = self.mark_vertices_mm.mean(axis=0)
        return np.array([[c[0], c[1]], [-c[0], c[1]], [-c[0], -c[1]], [c[0], -c[1]]])

    def outline_mm(self, n_per_side: int = 32) -> np.ndarray:
        """(4 n, 3) points on the plate's outer edge (for image bounding boxes)."""
        ex, ey = self.half_extent_mm
        t = np.linspace(-1, 1, n_per_side, endpoint=False)
        sides = [np.stack([t * ex, -ey + 0 * t], 1), np.stack([ex + 0 * t, t * ey], 1),
                 np.stack([-t * ex, ey + 0 * t], 1), np.stack([-ex + 0 * t, -t * ey], 1)]
        p = np.concatenate(sides)
        return np.concatenate([p, np.zeros((len(p), 1))], axis=1)

    def circle_outline_mm(self, n: int = 64) -> np.ndarray:
        """(rows*cols, n, 3) points on every circle's edge."""
        a = np.linspace(0, 2 * np.pi, n, endpoint=False)
        r = 0.5 * self.diameter_mm
        ring = np.stack([r * np.cos(a), r * np.sin(a), 0 * a], axis=1)
        return self.points_mm[:, None, :] + ring[None]

    # --- pattern ------------------------------------------------------------------------------
    def darkness(self, x_mm: np.ndarray, y_mm: np.ndarray, blur_mm) -> np.ndarray:
        """Anti-aliased dark coverage in [0, 1] at plate points (1 = printed black).

        ``blur_mm`` is the footprint of one pixel on the plate there; each shape's coverage is
        the signed distance to its edge through a linear ramp one footprint wide, which places
        every edge at its exact sub-pixel position with a single sample per pixel.
        """
        s = self.spacing_mm
        r = 0.5 * self.diameter_mm
        # nearest circle centre (grid indices clipped to the plate)
        j = np.clip(np.rint(x_mm / s + 0.5 * (self.cols - 1)), 0, self.cols - 1)
        i = np.clip(np.rint(y_mm / s + 0.5 * (self.rows - 1)), 0, self.rows - 1)
        dx = x_mm - (j - 0.5 * (self.cols - 1)) * s
        dy = y_mm - (i - 0.5 * (self.rows - 1)) * s
        d_circle = np.hypot(dx, dy) - r
        # frame band: inside the outer square and outside the inner square
        ox, oy = self._frame_half_mm(self.frame_outer)
        ix, iy = self._frame_half_mm(self.frame_inner)
        d_outer = np.maximum(np.abs(x_mm) - ox, np.abs(y_mm) - oy)
        d_inner = np.maximum(np.abs(x_mm) - ix, np.abs(y_mm) - iy)
        d_frame = np.maximum(d_outer, -d_inner)
        # triangle: x >= -ix, y >= -iy, (x + ix) + (y + iy) <= leg  (union with the frame)
        leg = self.mark_leg * s
        d_tri = np.maximum.reduce([-(x_mm + ix), -(y_mm + iy),
                                   ((x_mm + ix) + (y_mm + iy) - leg) / np.sqrt(2.0)])
        d = np.minimum.reduce([d_circle, d_frame, d_tri])
        return np.clip(0.5 - d / np.maximum(blur_mm, 1e-9), 0.0, 1.0)

    def to_dict(self) -> dict:
        d = asdict(self)
        d["kind"] = "circle_grid_plate"
        d["units"] = "mm; frame_* and mark_leg in units of spacing_mm"
        d["point_order"] = ("row-major, point 0 next to the triangular mark; "
                            "x_k = (j - (cols-1)/2) * spacing, y_k = (i - (rows-1)/2) * spacing")
        d["colors"] = "dark circles, frame and mark on a light plate"
        return d

    @classmethod
    def from_dict(cls, d: dict, where: str = "plate") -> CirclePlate:
        if not isinstance(d, dict):
            raise ModelFileError(f"{where}: expected a JSON object")
        fields = {k: d[k] for k in ("rows", "cols", "spacing_mm", "diameter_mm", "frame_inner",
                                     "frame_outer", "mark_leg") if k in d}
        for k in ("rows", "cols", "spacing_mm"):
            if k not in fields:
                raise ModelFileError(f"{where}: missing field '{k}'")
        try:
            fields["rows"] = int(fields["rows"])
            fields["cols"] = int(fields["cols"])
            for k in set(fields) - {"rows", "cols"}:
                fields[k] = float(fields[k])
        except (TypeError, ValueError, OverflowError):
            raise ModelFileError(f"{where}: plate fields must be numbers") from None
        if not all(1 <= fields[k] <= 1000 for k in ("rows", "cols")):
            raise ModelFileError(f"{where}: rows and cols must be from 1 to 1000, got "
                                 f"{fields['rows']} x {fields['cols']}")
        if "diameter_mm" not in fields:
            fields["diameter_mm"] = 0.5 * fields["spacing_mm"]
        try:
            return cls(**fields)
        except (InputError, OverflowError) as e:
            raise ModelFileError(f"{where}: {e}") from None


def load_plate(path) -> CirclePlate:
    """Read ``plate.json`` (as written by :func:`save_plate`)."""
    return CirclePlate.from_dict(read_json(path, ModelFileError, "plate file"), where=str(path))


def save_plate(plate: CirclePlate, path) -> None:
    Path(path).write_text(json.dumps(plate.to_dict(), indent=2) + "\n")


# ------------------------------------------------------------------------------------------
# rendering
def apply_sensor_effects(image: np.ndarray, rng: np.random.Generator,
                         settings=None) -> np.ndarray:
    """Defocus blur, shot and read noise and 8-bit quantisation of a float image in DN.

    The holder renderer's own helpers (:func:`cutterpose.render.analytic.defocus`,
    :func:`cutterpose.render.analytic.add_sensor_noise`) with a
    :class:`cutterpose.render.analytic.RenderSettings`
    (default: the ``easy`` preset), so plate and holder images share one sensor model.
    """
    from ..render.analytic import add_sensor_noise, defocus, preset

    s = settings if settings is not None else preset("easy")
    return add_sensor_noise(defocus(image, s.defocus_sigma_px, s.defocus_kernel), s, rng)


def render_plate(camera: Camera, pose: Pose, plate=None, *,
                 settings=None, light: float = 215.0, dark: float = 30.0,
                 background: float = 90.0, rng: np.random.Generator | None = None,
                 strip_rows: int = 256) -> np.ndarray:
    """Render the plate at ``pose`` (plate frame in camera frame) through ``camera``.

    ``plate`` is a :class:`CirclePlate` (default) or any calibration target
    (:class:`cutterpose.calibration.targets.Target`: ``bounds_mm``, ``darkness``, ``outline_mm``).

    Every pixel centre is traced back: observed pixel -> ``camera.pixel_to_ray`` (undoes the
    lens distortion exactly) -> intersection with the plate plane -> plate coordinates, where
    :meth:`CirclePlate.darkness` is evaluated with a footprint from the local Jacobian of that
    map. Perspective and distortion are therefore exact, circles appear as the true (not
    ellipse-fitted) images. Pixels off the plate show ``background``. ``settings`` (a
    :class:`cutterpose.render.analytic.RenderSettings`, e.g. ``render.preset("blurred")``; default
    ``easy``) sets defocus and sensor noise exactly as for the holder images.

    Returns
    -------
    (H, W) uint8 image.
    """
    plate = plate if plate is not None else CirclePlate()
    rng = rng if rng is not None else np.random.default_rng(0)
    w, h = camera.image_size_px
    img = np.full((h, w), background, np.float32)
    # bounding box of the plate in the image
    outline_px = camera.project(pose.apply(plate.outline_mm()))
    ok = np.all(np.isfinite(outline_px), axis=1)
    if ok.any():
        lo = np.floor(np.nanmin(outline_px[ok], axis=0)).astype(int) - 2
        hi = np.ceil(np.nanmax(outline_px[ok], axis=0)).astype(int) + 2
        u0, v0 = max(lo[0], 0), max(lo[1], 0)
        u1, v1 = min(hi[0], w - 1), min(hi[1], h - 1)
        if not ok.all():  # outline partly behind the camera: render everything
            u0, v0, u1, v1 = 0, 0, w - 1, h - 1
        R, t = pose.R, pose.t_mm
        n = R[:, 2]  # plate normal in the camera frame
        bx0, bx1, by0, by1 = plate.bounds_mm
        for vs in range(v0, v1 + 1, strip_rows):
            ve = min(vs + strip_rows, v1 + 1)
            # one extra row/col for the finite-difference footprint
            uu, vv = np.meshgrid(np.arange(u0, u1 + 2, dtype=float),
                                 np.arange(vs, ve + 1, dtype=float))
            rays = camera.pixel_to_ray(np.stack([uu, vv], axis=-1))
            with np.errstate(invalid="ignore", divide="ignore"):
                lam = (n @ t) / (rays @ n)
                p_cam = rays * lam[..., None]
                p_pl = (p_cam - t) @ R  # R^T (p - t)
            x, y = p_pl[..., 0], p_pl[..., 1]
            dxu = np.hypot(np.diff(x, axis=1)[:-1], np.diff(y, axis=1)[:-1])
            dxv = np.hypot(np.diff(x, axis=0)[:, :-1], np.diff(y, axis=0)[:, :-1])
            foot = np.sqrt(dxu * dxv)
            x, y, lam = x[:-1, :-1], y[:-1, :-1], lam[:-1, :-1]
            on = np.isfinite(x) & (lam > 0) & (x >= bx0) & (x <= bx1) & (y >= by0) & (y <= by1)
            dk = plate.darkness(np.nan_to_num(x), np.nan_to_num(y), np.nan_to_num(foot, nan=1.0))
            # anti-alias the plate's own edge against the background too
            xx, yy = np.nan_to_num(x), np.nan_to_num(y)
            d_edge = np.maximum.reduce([bx0 - xx, xx - bx1, by0 - yy, yy - by1])
            cover = np.clip(0.5 - d_edge / np.maximum(np.nan_to_num(foot, nan=1.0), 1e-9), 0, 1)
            cover = np.where(np.isfinite(x) & (lam > 0), cover, 0.0)
            val = light + (dark - light) * dk
            strip = background + (val - background) * cover
            img[vs:ve, u0:u1 + 1] = np.where(on | (cover > 0), strip, background)
    return apply_sensor_effects(img, rng, settings)


def _keep_in_view(plate):
    """Target points that must be inside the image, the size (mm) of its smallest feature and
    the fewest pixels that feature needs."""
    if isinstance(plate, CirclePlate):
        probe = np.concatenate([plate.mark_vertices_mm, np.zeros((3, 1))], axis=1)
        return (np.concatenate([plate.circle_outline_mm(16).reshape(-1, 3), probe]),
                plate.diameter_mm, 6.0)
    circles = plate.circle_outline_mm(16)
    if circles is not None:
        pts = circles.reshape(-1, 3)
        mark = getattr(plate, "mark_vertices_mm", None)  # an orientation mark is needed too
        if mark is not None:
            pts = np.concatenate([pts, np.c_[mark, np.zeros(len(mark))]])
        return pts, float(getattr(plate, "diameter_mm", 1.0)), 6.0
    marker = getattr(plate, "marker_mm", None)
    if marker is not None:  # ArUco markers need ~3 px per cell (6x6 bits with the border)
        return plate.outline_mm(8), float(marker), 20.0
    return plate.outline_mm(8), float(getattr(plate, "square_mm", 1.0)), 8.0


def sample_plate_poses(camera: Camera, count: int, plate=None, *,
                       distance_mm: tuple[float, float] = (400.0, 700.0),
                       tilt_deg: tuple[float, float] = (20.0, 45.0),
                       seed: int = 0, margin_px: float = 10.0,
                       max_tries: int = 20000) -> list[Pose]:
    """Plate poses that cover the field of view, for calibration.

    Pose ``k`` tilts the plate by an angle drawn in ``tilt_deg`` about an axis whose direction
    turns by the golden angle from pose to pose (so the tilts point in all directions), spins
    it in-plane by a random angle, and aims the plate centre at a random image point (drawn
    over the whole image, so circles reach the corners). A draw is kept when every circle and
    the orientation mark lie inside the image with ``margin_px``; otherwise it is redrawn.
    Without tilt Zhang's method is degenerate, and without circles near the corners kappa and
    f cannot be told apart.
    """
    plate = plate if plate is not None else CirclePlate()
    rng = np.random.default_rng(seed)
    w, h = camera.image_size_px
    pts, feature_mm, min_px = _keep_in_view(plate)
    x0, x1, y0, y1 = plate.bounds_mm
    centre = np.array([0.5 * (x0 + x1), 0.5 * (y0 + y1), 0.0])
    poses: list[Pose] = []
    from scipy.spatial.transform import Rotation

    golden = np.pi * (3.0 - np.sqrt(5.0))
    tries = 0
    while len(poses) < count:
        tries += 1
        if tries > max_tries:
            raise InputError(f"could not place {count} plate poses inside the image; the plate "
                             "is too large for this camera at the requested distances")
        k = len(poses)
        phi = k * golden + rng.uniform(-0.3, 0.3)
        tilt = np.radians(rng.uniform(*tilt_deg))
        axis = np.array([np.cos(phi), np.sin(phi), 0.0])
        spin = rng.uniform(-np.pi, np.pi)
        R = (Rotation.from_rotvec(axis * tilt) * Rotation.from_rotvec([0, 0, spin])).as_matrix()
        z = rng.uniform(*distance_mm)
        target = np.array([rng.uniform(0.1, 0.9) * w, rng.uniform(0.1, 0.9) * h])
        ray = camera.pixel_to_ray(target)
        t = ray / ray[2] * z - R @ centre  # the target's centre on that ray
        pose = Pose(R, t, "cam", "plate")
        px = camera.project(pose.apply(pts))
        if not np.all(np.isfinite(px)) or not np.all(camera.in_image(px, margin_px)):
            continue
        # the plate must face the camera
        if (R[:, 2] @ t) <= 0:
            continue
        # circles (markers, squares) must stay a few pixels wide
        f = camera.focal_px
        if feature_mm / np.linalg.norm(t + R @ centre) * f * np.cos(tilt) < min_px:
            continue
        poses.append(pose)
    return poses


def ellipse_center_bias_px(camera: Camera, pose: Pose, plate, n_edge: int = 64,
                           ids=None) -> np.ndarray:
    """Offset of each circle's image-ellipse centre from the image of its true centre.

    Under perspective a circle projects to an ellipse whose centre is not the projection of the
    circle's centre (the near half of the circle looks bigger); lens distortion adds to it. The
    edge of every circle is projected through ``camera`` and fitted with an ellipse (least
    squares, ``cv2.fitEllipse``); the result is ``centre(fitted ellipse) - project(centre)``,
    shape (n, 2) in pixels. Subtracting it from measured ellipse centres removes the bias.

    ``plate`` is a :class:`CirclePlate` or any circle target (``points_target_mm`` and
    ``circle_outline_mm``); ``ids`` selects its circles (default: all).
    """
    import cv2

    pts = getattr(plate, "points_target_mm", None)
    pts = plate.points_mm if pts is None else pts
    outline = plate.circle_outline_mm(n_edge)
    if ids is not None:
        ids = np.asarray(ids, int)
        pts, outline = pts[ids], outline[ids]
    edge = camera.project(pose.apply(outline))
    ctr = camera.project(pose.apply(pts))
    bias = np.full_like(ctr, np.nan)
    for k in range(len(ctr)):
        e = edge[k]
        if not np.all(np.isfinite(e)):
            continue
        # local coordinates keep float32 precise
        (cu, cv), _, _ = cv2.fitEllipse((e - ctr[k]).astype(np.float32))
        bias[k] = (cu, cv)
    return bias
