"""HALCON calibration plates: their description files (``.descr``, ``.cpd``) and geometry.

Two kinds of plates are sold for HALCON (MVTec HALCON reference, chapter "Calibration"):

* rectangularly arranged marks (``gen_caltab``, file ``.descr``): dark circles in a grid inside
  a dark frame with a triangular corner mark; the project's ``caltab:7x7:30`` plate is one.
  :class:`HalconCaltab` turns the file into a :class:`~cutterpose.calibration.plate.CirclePlate`
  (same frame, same point order) so that the caltab detector and renderer apply unchanged;
* hexagonally arranged marks (``create_caltab``, file ``.cpd``): ``NumRows`` rows of
  ``MarksPerRow`` circles, each mark with six equidistant neighbours, and one to five *finder
  patterns*: a mark hexagon (a mark and its six neighbours) in which four or six marks carry a
  dot-shaped hole; each finder pattern is unique, so one seen whole fixes which marks are seen
  and how the plate is turned. :class:`HexagonalPlate` holds this geometry; its detector is in
  :mod:`cutterpose.calibration.halcon_finder`.

File syntax (both suffixes; "Plate Description" text files, lengths in metres):
    ``#`` starts a comment; a line ``KEY values`` sets a field: ``r`` rows, ``c`` marks per row,
    ``z`` z offset of the coordinate system, ``o`` the plate's rim and ``i`` the outer border of
    the dark frame (each ``min x, max y, max x, min y``), ``t`` the triangular corner mark's two
    corner points on the frame's outer border (``x1 y1 x2 y2``; its third vertex is the frame
    corner between them), ``w`` the frame width, ``p`` the polarity (``light_on_dark`` or
    ``dark_on_light``, the ``Polarity`` of ``create_caltab``); every other line is one mark,
    ``x y radius`` and, for a mark with a hole, its hole radius as a fourth number. Marks are
    listed row by row from the top-left. The keys ``r c z o i t w`` and the mark lines follow the
    ``gen_caltab`` files (Plate Description Version 2); the polarity and hole fields are how this
    project writes the hexagonal plates (see docs/calibration_targets.md, section HALCON).

Convention:
    Plate frame as HALCON's: origin at the plate centre (the centroid of the marks for a
    ``gen_caltab`` plate), x right, y down, z into the plate; the same as
    :mod:`cutterpose.calibration.plate`. Marks are numbered in file order; ``points_target_mm``
    are their centres in millimetres (z = 0 plus the file's ``z`` offset).

References:
    MVTec HALCON reference manual: ``gen_caltab``, ``create_caltab``, ``caltab_points``,
    ``find_calib_object``.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from ..errors import InputError, ModelFileError
from .plate import CirclePlate
from .targets import Target, TargetDetection, register_target

__all__ = ["PlateDescription", "read_plate_description", "write_plate_description",
           "HalconCaltab", "HexagonalPlate", "HalconPlate", "hexagonal_description",
           "caltab_description", "load_halcon_plate", "FINDER_HOLES"]

POLARITIES = ("light_on_dark", "dark_on_light")


@dataclass
class PlateDescription:
    """The content of a HALCON plate description file, in millimetres.

    Attributes
    ----------
    marks_mm : (N, 2) mark centres (x, y) in file order.
    radius_mm : (N,) mark radii.
    hole_radius_mm : (N,) hole radii (0 for a mark without a hole).
    rows, cols : the ``r`` and ``c`` fields (None when absent).
    z_offset_mm : the ``z`` field.
    rim_mm, frame_mm : (min x, min y, max x, max y) of the rim and of the frame's outer border.
    frame_width_mm : the ``w`` field; triangle_mm : (3, 2) corner mark vertices (or None).
    polarity : ``light_on_dark`` or ``dark_on_light``.
    """

    marks_mm: np.ndarray
    radius_mm: np.ndarray
    hole_radius_mm: np.ndarray
    rows: int | None = None
    cols: int | None = None
    z_offset_mm: float = 0.0
    rim_mm: tuple | None = None
    frame_mm: tuple | None = None
    frame_width_mm: float | None = None
    triangle_mm: np.ndarray | None = None
    polarity: str = "dark_on_light"
    name: str = ""
    comments: list = field(default_factory=list)

    @property
    def n_marks(self) -> int:
        return len(self.marks_mm)


def _box(vals, key: str, where: str) -> tuple:
    if len(vals) != 4:
        raise ModelFileError(f"{where}: '{key}' needs 4 numbers (min x, max y, max x, min y)")
    x0, y1, x1, y0 = (v * 1e3 for v in vals)
    if not (x0 < x1 and y0 < y1):
        raise ModelFileError(f"{where}: '{key}' is not a box (min x, max y, max x, min y)")
    return (x0, y0, x1, y1)


def _numbers(tokens, where: str, line_no: int) -> list[float]:
    try:
        vals = [float(t) for t in tokens]
    except ValueError:
        raise ModelFileError(f"{where}, line {line_no}: not a number in {' '.join(tokens)!r}") \
            from None
    if not all(math.isfinite(v) for v in vals):
        raise ModelFileError(f"{where}, line {line_no}: values must be finite")
    return vals


def _triangle(vals, frame, where: str) -> np.ndarray:
    if len(vals) != 4:
        raise ModelFileError(f"{where}: 't' needs 4 numbers (x1 y1 x2 y2)")
    a, b = np.array(vals[:2]) * 1e3, np.array(vals[2:]) * 1e3
    # the third vertex: the frame corner sharing a coordinate with each point
    corner = np.array([a[0], b[1]]) if abs(a[0] - b[0]) > abs(a[1] - b[1]) else None
    if frame is not None:
        xs, ys = (frame[0], frame[2]), (frame[1], frame[3])
        corner = np.array([min(xs, key=lambda x: min(abs(x - a[0]), abs(x - b[0]))),
                           min(ys, key=lambda y: min(abs(y - a[1]), abs(y - b[1])))])
    if corner is None:
        corner = np.array([a[0], b[1]])
    return np.array([corner, a, b])


def read_plate_description(path) -> PlateDescription:
    """Read a HALCON ``.descr`` or ``.cpd`` file (syntax in the module docstring).

    Raises
    ------
    ModelFileError
        Unreadable file, a malformed line (the message gives its number), no marks, or ``r``
        and ``c`` that disagree with the number of marks.
    """
    path = Path(path)
    where = str(path)
    try:
        text = path.read_text()
    except (OSError, UnicodeDecodeError) as e:
        raise ModelFileError(f"{where}: cannot read the plate description ({e})") from None
    fields: dict = {}
    marks, comments = [], []
    for k, raw in enumerate(text.splitlines(), start=1):
        line = raw.split("#", 1)[0].strip()
        if raw.lstrip().startswith("#"):
            comments.append(raw.lstrip()[1:].strip())
        if not line:
            continue
        tokens = line.replace(",", " ").split()
        if tokens[0][0].isalpha():
            key = tokens[0]
            if key == "p":
                fields["p"] = tokens[1] if len(tokens) > 1 else ""
            else:
                fields[key] = _numbers(tokens[1:], where, k)
            continue
        vals = _numbers(tokens, where, k)
        if len(vals) < 3:
            raise ModelFileError(f"{where}, line {k}: a mark needs x y radius, got {line!r}")
        marks.append(vals[:4] + [0.0] * (4 - len(vals[:4])))
    if not marks:
        raise ModelFileError(f"{where}: no calibration marks (lines 'x y radius')")
    m = np.array(marks) * 1e3
    if np.any(m[:, 2] <= 0) or np.any(m[:, 3] < 0) or np.any(m[:, 3] >= m[:, 2]):
        raise ModelFileError(f"{where}: mark radii must be positive and holes smaller than marks")
    frame = _box(fields["i"], "i", where) if "i" in fields else None
    desc = PlateDescription(
        marks_mm=m[:, :2], radius_mm=m[:, 2], hole_radius_mm=m[:, 3],
        rows=int(fields["r"][0]) if "r" in fields else None,
        cols=int(fields["c"][0]) if "c" in fields else None,
        z_offset_mm=fields.get("z", [0.0])[0] * 1e3,
        rim_mm=_box(fields["o"], "o", where) if "o" in fields else None, frame_mm=frame,
        frame_width_mm=fields["w"][0] * 1e3 if "w" in fields else None,
        triangle_mm=_triangle(fields["t"], frame, where) if "t" in fields else None,
        polarity=fields.get("p", "light_on_dark" if m[:, 3].any() else "dark_on_light"),
        name=path.stem, comments=comments)
    if desc.polarity not in POLARITIES:
        raise ModelFileError(f"{where}: polarity must be one of {POLARITIES}, "
                             f"got {desc.polarity!r}")
    if desc.rows and desc.cols and desc.rows * desc.cols != desc.n_marks:
        raise ModelFileError(f"{where}: r x c = {desc.rows} x {desc.cols} but the file lists "
                             f"{desc.n_marks} marks")
    return desc


def write_plate_description(desc: PlateDescription, path, title: str = "") -> None:
    """Write ``desc`` in the syntax :func:`read_plate_description` reads (metres)."""
    def m(v):
        return f"{v * 1e-3:.10g}"

    lines = ["# Plate Description Version 2", f"# {title or desc.name}",
             "# (written by cutterpose; lengths in metres)", ""]
    if desc.rows:
        lines += ["# Number of marks in y-dimension (rows)", f"r {desc.rows}", ""]
    if desc.cols:
        lines += ["# Number of marks per row (columns)", f"c {desc.cols}", ""]
    lines += ["# offset of coordinate system in z-dimension [meter] (optional):",
              f"z {m(desc.z_offset_mm)}", ""]
    if desc.rim_mm is not None:
        x0, y0, x1, y1 = desc.rim_mm
        lines += ["# rim of the calibration plate (min x, max y, max x, min y) [meter]:",
                  f"o {m(x0)} {m(y1)} {m(x1)} {m(y0)}"]
    if desc.frame_mm is not None:
        x0, y0, x1, y1 = desc.frame_mm
        lines += ["# outer border of the black frame (min x, max y, max x, min y) [meter]:",
                  f"i {m(x0)} {m(y1)} {m(x1)} {m(y0)}"]
    if desc.triangle_mm is not None:
        a, b = desc.triangle_mm[1], desc.triangle_mm[2]
        lines += ["# triangular corner mark given by two corner points (x,y, x,y) [meter]:",
                  f"t {m(a[0])} {m(a[1])} {m(b[0])} {m(b[1])}"]
    if desc.frame_width_mm is not None:
        lines += ["# width of the black frame [meter]:", f"w {m(desc.frame_width_mm)}"]
    lines += ["", "# polarity of the marks:", f"p {desc.polarity}", "",
              "# calibration marks: x y radius [hole radius] [meter]"]
    for (x, y), r, h in zip(desc.marks_mm, desc.radius_mm, desc.hole_radius_mm):
        lines.append(f"{m(x)} {m(y)} {m(r)}" + (f" {m(h)}" if h > 0 else ""))
    Path(path).write_text("\n".join(lines) + "\n")


# ------------------------------------------------------------------------------------------
# rectangular plates (gen_caltab)
def caltab_description(plate: CirclePlate | None = None) -> PlateDescription:
    """The ``.descr`` content of a :class:`CirclePlate` (frame, triangle, row-major marks)."""
    p = plate or CirclePlate()
    ox, oy = p.half_extent_mm
    s = p.spacing_mm
    w = (p.frame_outer - p.frame_inner) * s
    leg = p.mark_leg * s + 2 * w  # the triangle's legs from the frame's outer corner
    return PlateDescription(
        marks_mm=p.points_mm[:, :2].copy(), radius_mm=np.full(p.n_points, p.diameter_mm / 2),
        hole_radius_mm=np.zeros(p.n_points), rows=p.rows, cols=p.cols,
        rim_mm=(-ox - 0.1 * s, -oy - 0.1 * s, ox + 0.1 * s, oy + 0.1 * s),
        frame_mm=(-ox, -oy, ox, oy), frame_width_mm=w,
        triangle_mm=np.array([[-ox, -oy], [-ox, -oy + leg], [-ox + leg, -oy]]),
        polarity="dark_on_light", name=f"caltab_{p.rows}x{p.cols}_{p.spacing_mm:g}mm")


class HalconCaltab:
    """A ``gen_caltab`` plate from its ``.descr`` file, as a :class:`CirclePlate`.

    The file must describe a regular grid (``r`` x ``c`` marks of one radius, equal spacing,
    centred at the origin) inside a square-cornered frame with a triangular corner mark next to
    mark 0; other layouts are refused with the reason.
    """

    kind = "caltab"

    def __init__(self, desc: PlateDescription):
        self.description = desc
        self.plate = self._to_circle_plate(desc)
        self.points_target_mm = self.plate.points_mm + [0.0, 0.0, desc.z_offset_mm]
        self.name = desc.name

    @staticmethod
    def _to_circle_plate(d: PlateDescription) -> CirclePlate:
        where = d.name or "caltab"
        if not (d.rows and d.cols) or d.frame_mm is None or d.frame_width_mm is None:
            raise ModelFileError(f"{where}: a .descr plate needs 'r', 'c', 'i' and 'w'")
        if d.triangle_mm is None:
            raise ModelFileError(f"{where}: a .descr plate needs its triangular mark 't'")
        grid = d.marks_mm.reshape(d.rows, d.cols, 2)
        steps = np.concatenate([np.diff(grid[..., 0], axis=1).ravel(),
                                np.diff(grid[..., 1], axis=0).ravel()])
        s = float(np.median(steps))
        if s <= 0 or np.ptp(steps) > 1e-6 * s or np.ptp(d.radius_mm) > 1e-9:
            raise ModelFileError(f"{where}: the marks are not a regular grid of equal circles "
                                 "listed row by row from the top-left")
        if np.abs(d.marks_mm.mean(axis=0)).max() > 1e-6 * s:
            raise ModelFileError(f"{where}: the grid is not centred at the plate origin")
        x0, y0, x1, y1 = d.frame_mm
        half = (0.5 * (max(d.rows, d.cols) - 1))
        outer = (x1 - 0.5 * (d.cols - 1) * s) / s + half  # CirclePlate's frame units
        inner = outer - d.frame_width_mm / s
        corner = d.triangle_mm[0]
        if not np.allclose(corner, [x0, y0], atol=1e-6 * s):
            raise ModelFileError(f"{where}: the triangular mark must sit in the frame corner "
                                 "next to mark 0 (min x, min y)")
        leg = (np.abs(d.triangle_mm[1:] - corner).max(axis=1).mean() - 2 * d.frame_width_mm)
        try:
            return CirclePlate(d.rows, d.cols, s, 2 * float(d.radius_mm[0]), float(inner),
                               float(outer), float(leg / s))
        except InputError as e:
            raise ModelFileError(f"{where}: {e}") from None


# ------------------------------------------------------------------------------------------
# hexagonal plates (create_caltab)
#: Hole patterns of this project's finder patterns, up to five per plate: (centre has a hole,
#: holes among the six neighbours listed anticlockwise on the page starting at the right-hand
#: neighbour). Each has 4 or 6 holes, none is symmetric under a rotation, no two are rotations
#: of each other, and no hexagon around one of a pattern's holed marks holds as many holes
#: as the pattern, so one finder seen whole gives the plate's turn and position.
FINDER_HOLES = ((True, (0, 1, 3)), (True, (0, 2, 3)), (False, (0, 1, 2, 4)),
                (False, (0, 1, 2, 3)), (True, (0, 1, 2, 3, 4)))


def _hex_neighbours_rc(r: int, c: int):
    """The six neighbours (row, col) of mark (r, c), anticlockwise on the page from the right,
    for rows where odd rows are shifted right by half a spacing."""
    sh = r % 2  # odd rows sit half a step to the right
    return [(r, c + 1), (r - 1, c + sh), (r - 1, c - 1 + sh), (r, c - 1), (r + 1, c - 1 + sh),
            (r + 1, c + sh)]


def hexagonal_description(num_rows: int, marks_per_row: int, diameter_m: float,
                          finder_row, finder_column, polarity: str = "light_on_dark",
                          hole_ratio: float = 0.5, name: str = "") -> PlateDescription:
    """A hexagonal plate with the parameters of HALCON's ``create_caltab``.

    Marks of diameter ``D`` are ``2 D`` apart along a row; rows are ``sqrt(3) D`` apart and
    every odd row is shifted by ``D``, so each inner mark has six neighbours at ``2 D``.
    ``finder_row``/``finder_column`` give each finder pattern's central mark; the patterns'
    holes (radius ``hole_ratio`` times the mark radius) follow :data:`FINDER_HOLES`. The
    origin is the centre of the marks' bounding box; the rim lies ``2 D`` outside the marks.
    """
    fr, fc = np.atleast_1d(finder_row).astype(int), np.atleast_1d(finder_column).astype(int)
    if not (1 <= len(fr) == len(fc) <= len(FINDER_HOLES)):
        raise InputError(f"need 1 to {len(FINDER_HOLES)} finder patterns with a row and a "
                         "column each")
    if num_rows < 3 or marks_per_row < 3 or not diameter_m > 0:
        raise InputError("need at least 3 rows and 3 marks per row and a positive diameter")
    if polarity not in POLARITIES:
        raise InputError(f"polarity must be one of {POLARITIES}, got {polarity!r}")
    d_mm = diameter_m * 1e3
    r_idx, c_idx = np.divmod(np.arange(num_rows * marks_per_row), marks_per_row)
    x = 2 * d_mm * c_idx + d_mm * (r_idx % 2)
    y = math.sqrt(3) * d_mm * r_idx
    xy = np.stack([x, y], axis=1)
    xy -= 0.5 * (xy.min(axis=0) + xy.max(axis=0))
    holes = np.zeros(len(xy))
    used: set = set()
    for (rr, cc), (centre, ring) in zip(zip(fr, fc), FINDER_HOLES):
        nb = _hex_neighbours_rc(rr, cc)
        cells = [(rr, cc)] + nb
        if not all(0 <= a < num_rows and 0 <= b < marks_per_row for a, b in cells):
            raise InputError(f"finder pattern at row {rr}, column {cc} leaves the plate")
        if used & set(cells):
            raise InputError(f"finder pattern at row {rr}, column {cc} overlaps another")
        used |= set(cells)
        chosen = ([(rr, cc)] if centre else []) + [nb[k] for k in ring]
        for a, b in chosen:
            holes[a * marks_per_row + b] = hole_ratio * d_mm / 2
    lo, hi = xy.min(axis=0) - 2 * d_mm, xy.max(axis=0) + 2 * d_mm
    return PlateDescription(
        marks_mm=xy, radius_mm=np.full(len(xy), d_mm / 2), hole_radius_mm=holes,
        rows=num_rows, cols=marks_per_row, rim_mm=(lo[0], lo[1], hi[0], hi[1]),
        polarity=polarity, name=name or f"hexplate_{num_rows}x{marks_per_row}")


class HexagonalPlate:
    """A ``create_caltab`` plate: geometry, finder patterns and the renderer's interface.

    Attributes
    ----------
    points_target_mm : (N, 3) mark centres (plate frame, mm).
    neighbours : (N, 6) index of each mark's six neighbours (anticlockwise on the page from
        the right-hand one; -1 off the plate), found from the mark coordinates.
    finders : list of (centre index, (6,) neighbour indices, (7,) hole flags centre-first).
    polarity : ``light_on_dark`` (light marks, dark plate) or ``dark_on_light``.
    """

    kind = "hexagonal"

    def __init__(self, desc: PlateDescription):
        self.description = desc
        self.name = desc.name
        n = desc.n_marks
        if n < 7:
            raise ModelFileError(f"{desc.name}: a hexagonal plate needs at least 7 marks")
        self.marks_mm = np.asarray(desc.marks_mm, float)
        self.points_target_mm = np.c_[self.marks_mm, np.full(n, desc.z_offset_mm)]
        self.radius_mm = np.asarray(desc.radius_mm, float)
        self.hole_radius_mm = np.asarray(desc.hole_radius_mm, float)
        self.polarity = desc.polarity
        self.spacing_mm, self.neighbours = self._lattice()
        self.finders = self._finders()
        if not self.finders:
            raise ModelFileError(f"{desc.name}: no finder pattern (a mark hexagon with 4 or 6 "
                                 "holes) in the description")

    # --- lattice ---------------------------------------------------------------------------
    def _lattice(self):
        from scipy.spatial import cKDTree

        tree = cKDTree(self.marks_mm)
        dist, idx = tree.query(self.marks_mm, k=min(7, len(self.marks_mm)))
        s = float(np.median(dist[:, 1]))
        nb = np.full((len(self.marks_mm), 6), -1, int)
        for k in range(len(self.marks_mm)):
            for d, j in zip(dist[k, 1:], idx[k, 1:]):
                if abs(d - s) > 0.1 * s:
                    continue
                v = self.marks_mm[j] - self.marks_mm[k]
                # direction index 0..5 anticlockwise on the page (y down: angle of (x, -y))
                a = int(round(math.degrees(math.atan2(-v[1], v[0])) / 60.0)) % 6
                nb[k, a] = j
        return s, nb

    def _finders(self):
        """Mark hexagons with 4 or 6 holes; where such hexagons overlap (a hexagon around a
        finder's hole mark can hold 4 holes too) the one with more holes, then the one with a
        holed centre, is the finder pattern."""
        has = self.hole_radius_mm > 0
        full = np.all(self.neighbours >= 0, axis=1)
        cand = []
        for c in np.nonzero(full)[0]:
            flags = np.concatenate([[has[c]], has[self.neighbours[c]]])
            if flags.sum() in (4, 6):
                cand.append((-int(flags.sum()), not has[c], int(c), flags))
        out, used = [], set()
        for _, _, c, flags in sorted(cand):
            cells = {c, *self.neighbours[c].tolist()}
            if cells & used:
                continue
            used |= cells
            out.append((c, self.neighbours[c].copy(), flags))
        return out

    # --- renderer interface (duck-typed like CirclePlate) ----------------------------------
    @property
    def n_points(self) -> int:
        return len(self.marks_mm)

    @property
    def points_mm(self) -> np.ndarray:
        return self.points_target_mm

    @property
    def diameter_mm(self) -> float:
        return float(2 * self.radius_mm.min())

    @property
    def half_extent_mm(self) -> tuple[float, float]:
        rim = self.description.rim_mm
        if rim is None:
            lo = self.marks_mm.min(axis=0) - 1.5 * self.spacing_mm
            hi = self.marks_mm.max(axis=0) + 1.5 * self.spacing_mm
            rim = (lo[0], lo[1], hi[0], hi[1])
        x0, y0, x1, y1 = rim
        return max(-x0, x1), max(-y0, y1)

    @property
    def mark_vertices_mm(self) -> np.ndarray:
        """(3, 2) centres of (up to three) finder patterns: the pose sampler keeps them in the
        image."""
        c = [f[0] for f in self.finders]
        return self.marks_mm[(c * 3)[:3]]

    def outline_mm(self, n_per_side: int = 32) -> np.ndarray:
        ex, ey = self.half_extent_mm
        t = np.linspace(-1, 1, n_per_side, endpoint=False)
        p = np.concatenate([np.stack([t * ex, -ey + 0 * t], 1),
                            np.stack([ex + 0 * t, t * ey], 1),
                            np.stack([-t * ex, ey + 0 * t], 1),
                            np.stack([-ex + 0 * t, -t * ey], 1)])
        return np.c_[p, np.zeros(len(p))]

    def circle_outline_mm(self, n: int = 64) -> np.ndarray:
        a = np.linspace(0, 2 * np.pi, n, endpoint=False)
        ring = np.stack([np.cos(a), np.sin(a), 0 * a], axis=1)
        return self.points_target_mm[:, None, :] + self.radius_mm[:, None, None] * ring[None]

    def darkness(self, x_mm, y_mm, blur_mm) -> np.ndarray:
        """Anti-aliased printed-black coverage in [0, 1] (signed distance through a ramp one
        pixel footprint wide, as :meth:`CirclePlate.darkness`)."""
        from scipy.spatial import cKDTree

        if not hasattr(self, "_tree"):
            self._tree = cKDTree(self.marks_mm)
        q = np.stack([np.ravel(x_mm), np.ravel(y_mm)], axis=1)
        dist, k = self._tree.query(q)
        r, h = self.radius_mm[k], self.hole_radius_mm[k]
        # signed distance to the region of the *other* colour than the marks: outside the
        # mark, or inside its hole
        d_bg = np.where(h > 0, np.minimum(r - dist, dist - h), r - dist)
        d_bg = d_bg.reshape(np.shape(x_mm))
        cover_bg = np.clip(0.5 - d_bg / np.maximum(blur_mm, 1e-9), 0.0, 1.0)
        return cover_bg if self.polarity == "light_on_dark" else 1.0 - cover_bg


def load_halcon_plate(path) -> HalconCaltab | HexagonalPlate:
    """The geometry of a HALCON description file: ``.descr`` -> :class:`HalconCaltab`,
    ``.cpd`` -> :class:`HexagonalPlate` (other suffixes: by content, holes meaning hexagonal).
    :class:`HalconPlate` is the calibration target made of either."""
    desc = read_plate_description(path)
    suffix = Path(path).suffix.lower()
    if suffix == ".descr" or (suffix != ".cpd" and not desc.hole_radius_mm.any()):
        return HalconCaltab(desc)
    return HexagonalPlate(desc)


@register_target
class HalconPlate(Target):
    """A HALCON plate named by its description file, as a calibration target.

    ``.descr`` plates are detected by the caltab detector
    (:class:`~cutterpose.calibration.circle_grids.CaltabTarget`: circle grid, frame and
    triangle); ``.cpd`` plates by their finder patterns
    (:func:`~cutterpose.calibration.halcon_finder.detect_hexagonal`, partial views with ids).
    In a target file: ``{kind: halcon, file: path/to/plate.cpd}`` (a relative path is taken
    from the target file's folder, else from the working directory).
    """

    kind = "halcon"
    min_points = 9

    def __init__(self, geometry: HalconCaltab | HexagonalPlate, path=None):
        self.geometry = geometry
        self.path = None if path is None else Path(path)

    @classmethod
    def from_file(cls, path) -> HalconPlate:
        return cls(load_halcon_plate(path), path)

    @property
    def hexagonal(self) -> bool:
        return isinstance(self.geometry, HexagonalPlate)

    @property
    def points_target_mm(self) -> np.ndarray:
        return self.geometry.points_target_mm

    def circle_outline_mm(self, n: int = 64) -> np.ndarray:
        g = self.geometry
        if self.hexagonal:
            return g.circle_outline_mm(n)
        return g.plate.circle_outline_mm(n) + [0.0, 0.0, g.description.z_offset_mm]

    @property
    def rotation_symmetry_deg(self) -> int:
        return 0  # the triangle or the finder patterns break every symmetry

    def detect(self, gray) -> TargetDetection:
        if self.hexagonal:
            from .halcon_finder import detect_hexagonal

            return detect_hexagonal(gray, self.geometry)
        from .circle_grids import CaltabTarget

        return CaltabTarget(self.geometry.plate).detect(gray)

    @property
    def bounds_mm(self):
        ex, ey = self.half_extent_mm
        return (-ex, ex, -ey, ey)

    def darkness(self, x_mm, y_mm, blur_mm):
        return self._drawn.darkness(x_mm, y_mm, blur_mm)

    # the interface of plate.render_plate / sample_plate_poses (as CirclePlate's)
    @property
    def _drawn(self):
        return self.geometry if self.hexagonal else self.geometry.plate

    @property
    def half_extent_mm(self):
        return self._drawn.half_extent_mm

    @property
    def diameter_mm(self) -> float:
        return self._drawn.diameter_mm

    @property
    def mark_vertices_mm(self) -> np.ndarray:
        return self._drawn.mark_vertices_mm

    @property
    def points_mm(self) -> np.ndarray:
        return self.points_target_mm

    def outline_mm(self, n_per_side: int = 32) -> np.ndarray:
        return self._drawn.outline_mm(n_per_side)

    # --- description -------------------------------------------------------------------------
    def to_dict(self) -> dict:
        return {"kind": self.kind, "file": str(self.path.resolve()) if self.path else None,
                "plate": "hexagonal" if self.hexagonal else "rectangular",
                "marks": self.n_points}

    @classmethod
    def from_dict(cls, d, where="target"):
        f = d.get("file") if isinstance(d, dict) else None
        if not f:
            raise ModelFileError(f"{where}: a halcon target needs 'file' (a .descr or .cpd)")
        path = Path(str(f))
        beside = Path(where).parent / path  # relative to the target file's folder first
        if not path.is_absolute() and beside.is_file():
            path = beside
        if not path.is_file():
            raise ModelFileError(f"{where}: HALCON description file not found: {f}")
        return cls.from_file(path)

    @classmethod
    def from_spec(cls, fields, options):
        if len(fields) != 1 or options:
            raise InputError("halcon target: give halcon:PATH.cpd (or just the .descr/.cpd path)")
        return cls.from_file(fields[0])

    def spec(self) -> str:
        return str(self.path) if self.path else "halcon"

    def describe(self) -> str:
        kind = "hexagonal" if self.hexagonal else "rectangular"
        return f"HALCON {kind} plate {self.geometry.name} ({self.n_points} marks)"
