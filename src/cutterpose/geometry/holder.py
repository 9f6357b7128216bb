"""The disc cutter holder model: 20 inner-contour corners on the plane Z = 0.

Convention:
    Holder frame: origin at the centre of the top surface, Z perpendicular to it, X along the
    long side and Y along the short side of the outer rectangle (seed paper, section 2.3).
    Corners are listed counter-clockwise seen from +Z, all at Z = 0, in mm. Edge ``i`` runs from
    corner ``i`` to corner ``i + 1`` (cyclically); edges alternate between the holder's X and Y
    directions.
"""

from __future__ import annotations

import json
from dataclasses import dataclass, field
from importlib import resources

import numpy as np

from ..errors import HolderModelError, InputError
from .jsonfile import is_finite_number, read_json
from .pose import Pose

__all__ = ["Holder", "load_holder", "default_holder", "holder_from_dict",
           "outward_edge_normals"]


def outward_edge_normals(corners_mm) -> np.ndarray:
    """(N, 2) unit normals of a polygon's edges (edge ``k``: corner ``k`` to ``k + 1``)
    pointing out of it (for the pocket contour: away from the pocket), either orientation."""
    c = np.asarray(corners_mm, float)
    d = np.roll(c, -1, axis=0) - c
    x, y = c.T
    ccw = np.dot(x, np.roll(y, -1)) - np.dot(np.roll(x, -1), y) > 0
    n = np.column_stack([d[:, 1], -d[:, 0]]) * (1.0 if ccw else -1.0)
    return n / np.linalg.norm(n, axis=1, keepdims=True)


@dataclass(frozen=True)
class Holder:
    """Holder geometry.

    Attributes
    ----------
    corners_mm : (N, 2) inner-contour corners (X, Y), counter-clockwise.
    outer_length_x_mm, outer_width_y_mm : outer rectangle, centred on the origin.
    name : free text.
    grasp_frame : ``T_holder_grasp``, where the gripper takes the cutter (file field
        ``grasp_frame``); None: the holder frame itself (:mod:`cutterpose.robot.grasp`).
    """

    corners_mm: np.ndarray
    outer_length_x_mm: float
    outer_width_y_mm: float
    name: str = ""
    grasp_frame: Pose | None = None
    _cache: dict = field(default_factory=dict, repr=False, compare=False)

    @property
    def n_corners(self) -> int:
        return len(self.corners_mm)

    @property
    def points_holder_mm(self) -> np.ndarray:
        """(N, 3) corners in the holder frame (Z = 0). Cached and read-only: it is on every
        solve's path."""
        P = self._cache.get("points")
        if P is None:
            P = np.column_stack([self.corners_mm, np.zeros(len(self.corners_mm))])
            P.flags.writeable = False
            self._cache["points"] = P
        return P

    @property
    def edge_normals(self) -> np.ndarray:
        """(N, 2) unit normals of the edges in the face plane, pointing out of the pocket
        (:func:`outward_edge_normals`)."""
        return outward_edge_normals(self.corners_mm)

    @property
    def area_mm2(self) -> float:
        """Area enclosed by the inner contour (shoelace formula)."""
        x, y = self.corners_mm.T
        return 0.5 * float(np.dot(x, np.roll(y, -1)) - np.dot(np.roll(x, -1), y))

    @property
    def edges(self) -> np.ndarray:
        """(N, 2, 2) edges as (start, end) corner pairs: edge i runs corner i -> corner i+1."""
        c = self.corners_mm
        return np.stack([c, np.roll(c, -1, axis=0)], axis=1)

    @property
    def edge_direction_index(self) -> np.ndarray:
        """(N,) 0 for an edge parallel to X, 1 for an edge parallel to Y."""
        d = np.diff(self.edges, axis=1)[:, 0]
        return (np.abs(d[:, 1]) > np.abs(d[:, 0])).astype(int)

    @property
    def edge_directions(self) -> np.ndarray:
        """(2, 3) the holder's two edge directions in the holder frame: X and Y."""
        return np.array([[1.0, 0.0, 0.0], [0.0, 1.0, 0.0]])

    @property
    def outer_rectangle_mm(self) -> np.ndarray:
        """(4, 2) outer rectangle corners, counter-clockwise."""
        a, b = 0.5 * self.outer_length_x_mm, 0.5 * self.outer_width_y_mm
        return np.array([[-a, -b], [a, -b], [a, b], [-a, b]])

    @property
    def edge_lines(self) -> np.ndarray:
        """(N, 3) homogeneous lines ``(a, b, c)`` of the edges in the holder plane,
        ``a x + b y + c = 0`` with ``(a, b)`` a unit normal."""
        p, q = self.edges[:, 0], self.edges[:, 1]
        d = q - p
        n = np.column_stack([-d[:, 1], d[:, 0]]) / np.linalg.norm(d, axis=1, keepdims=True)
        return np.column_stack([n, -np.einsum("ij,ij->i", n, p)])

    def to_dict(self) -> dict:
        d = {"name": self.name, "units": "mm",
             "outer_rectangle": {"length_x": self.outer_length_x_mm,
                                 "width_y": self.outer_width_y_mm},
             "inner_contour_corners": self.corners_mm.tolist()}
        if self.grasp_frame is not None:
            d["grasp_frame"] = {"T_holder_grasp": self.grasp_frame.matrix.tolist()}
        return d


# ------------------------------------------------------------------------------------------
def _segments_intersect(p1, p2, q1, q2) -> bool:
    def orient(a, b, c):
        return np.sign((b[0] - a[0]) * (c[1] - a[1]) - (b[1] - a[1]) * (c[0] - a[0]))

    o1, o2 = orient(p1, p2, q1), orient(p1, p2, q2)
    o3, o4 = orient(q1, q2, p1), orient(q1, q2, p2)
    if o1 != o2 and o3 != o4 and 0 not in (o1, o2, o3, o4):
        return True

    def on_seg(a, b, c):
        return (min(a[0], b[0]) <= c[0] <= max(a[0], b[0])
                and min(a[1], b[1]) <= c[1] <= max(a[1], b[1]))

    return ((o1 == 0 and on_seg(p1, p2, q1)) or (o2 == 0 and on_seg(p1, p2, q2))
            or (o3 == 0 and on_seg(q1, q2, p1)) or (o4 == 0 and on_seg(q1, q2, p2)))


def validate_corners(corners, where: str = "holder") -> np.ndarray:
    """Check that the corners form a closed simple polygon with edges in two perpendicular
    directions (X and Y of the holder frame) and return them as an (N, 2) array.

    Accepts (N, 2) or (N, 3) input; a third column must be zero (planar at Z = 0).
    """
    try:
        c = np.asarray(corners, dtype=float)
    except (TypeError, ValueError, OverflowError):
        raise HolderModelError(
            f"{where}: field 'inner_contour_corners' must be a list of [x, y] numbers") from None
    if c.ndim != 2 or c.shape[1] not in (2, 3):
        raise HolderModelError(f"{where}: field 'inner_contour_corners' must be a list of [x, y] "
                               f"(or [x, y, z]) points, got shape {c.shape}")
    if not np.all(np.isfinite(c)):
        bad = np.argwhere(~np.isfinite(c))[0]
        raise HolderModelError(f"{where}: field 'inner_contour_corners' holds a non-finite value "
                               f"at corner {bad[0]}")
    if c.shape[1] == 3:
        if np.abs(c[:, 2]).max() > 1e-9:
            i = int(np.argmax(np.abs(c[:, 2])))
            raise HolderModelError(f"{where}: field 'inner_contour_corners' is not planar: corner "
                                   f"{i} has z = {c[i, 2]} (all corners must lie at Z = 0)")
        c = c[:, :2]
    n = len(c)
    if n < 4 or n % 2:
        raise HolderModelError(f"{where}: field 'inner_contour_corners' needs an even number >= 4 "
                               f"of corners (edges alternate X/Y), got {n}")
    d = np.roll(c, -1, axis=0) - c
    lengths = np.linalg.norm(d, axis=1)
    if np.any(lengths < 1e-9):
        i = int(np.argmin(lengths))
        raise HolderModelError(f"{where}: field 'inner_contour_corners': corners {i} and "
                               f"{(i + 1) % n} coincide")
    scale = lengths.max()
    is_x = np.abs(d[:, 1]) <= 1e-9 * scale
    is_y = np.abs(d[:, 0]) <= 1e-9 * scale
    if not np.all(is_x | is_y):
        i = int(np.argmax(~(is_x | is_y)))
        raise HolderModelError(f"{where}: field 'inner_contour_corners': edge {i} "
                               f"({c[i].tolist()} -> {c[(i + 1) % n].tolist()}) is parallel to "
                               "neither X nor Y; the holder's edges must lie in two directions")
    if np.any(is_x == np.roll(is_x, -1)):
        i = int(np.argmax(is_x == np.roll(is_x, -1)))
        raise HolderModelError(f"{where}: field 'inner_contour_corners': edges {i} and "
                               f"{(i + 1) % n} are parallel; consecutive edges must alternate "
                               "between X and Y (remove the middle corner)")
    for i in range(n):
        for j in range(i + 2, n):
            if i == 0 and j == n - 1:
                continue
            if _segments_intersect(c[i], c[(i + 1) % n], c[j], c[(j + 1) % n]):
                raise HolderModelError(f"{where}: field 'inner_contour_corners' is not a simple "
                                       f"polygon: edges {i} and {j} cross")
    x, y = c.T
    area = 0.5 * (np.dot(x, np.roll(y, -1)) - np.dot(np.roll(x, -1), y))
    if area < 0:
        raise HolderModelError(f"{where}: field 'inner_contour_corners' must run "
                               "counter-clockwise seen from +Z (its signed area is negative)")
    return c


def holder_from_dict(d: dict, where: str = "holder") -> Holder:
    """Build a :class:`Holder` from the JSON object of ``shared/spec/holder.json``."""
    if not isinstance(d, dict):
        raise HolderModelError(f"{where}: expected a JSON object, got {type(d).__name__}")
    if d.get("units", "mm") != "mm":
        raise HolderModelError(f"{where}: field 'units' must be 'mm', got {d.get('units')!r}")
    if "inner_contour_corners" not in d:
        raise HolderModelError(f"{where}: missing field 'inner_contour_corners'")
    corners = validate_corners(d["inner_contour_corners"], where)
    rect = d.get("outer_rectangle")
    if not isinstance(rect, dict):
        raise HolderModelError(f"{where}: missing or malformed field 'outer_rectangle' "
                               "(an object with 'length_x' and 'width_y')")
    dims = []
    for key in ("length_x", "width_y"):
        v = rect.get(key)
        if not is_finite_number(v) or v <= 0:
            raise HolderModelError(f"{where}: field 'outer_rectangle.{key}' must be a positive "
                                   f"number, got {v!r}")
        dims.append(float(v))
    a, b = dims[0] / 2, dims[1] / 2
    if np.any(np.abs(corners[:, 0]) >= a) or np.any(np.abs(corners[:, 1]) >= b):
        raise HolderModelError(f"{where}: the inner contour must lie inside 'outer_rectangle'")
    return Holder(corners, dims[0], dims[1], name=str(d.get("name", "")),
                  grasp_frame=_grasp_frame(d.get("grasp_frame"), where))


def _grasp_frame(g, where: str) -> Pose | None:
    """Optional ``"grasp_frame"``: ``{"T_holder_grasp": 4x4}`` or ``{"position_mm": [x, y, z],
    "euler_deg": [alpha, beta, gamma]}`` (the protocol's Z-Y-X angles), in the holder frame."""
    if g is None:
        return None
    try:
        if isinstance(g, dict) and "T_holder_grasp" in g:
            return Pose.from_matrix(np.asarray(g["T_holder_grasp"], float), "holder", "grasp")
        if isinstance(g, dict) and "position_mm" in g:
            e = np.asarray(g.get("euler_deg", [0.0, 0.0, 0.0]), float).reshape(3)
            return Pose.from_euler(*e, *np.asarray(g["position_mm"], float).reshape(3),
                                   to_frame="holder", from_frame="grasp")
    except (InputError, TypeError, ValueError, OverflowError) as e:
        raise HolderModelError(f"{where}: field 'grasp_frame': {e}") from None
    raise HolderModelError(f"{where}: field 'grasp_frame' must hold 'T_holder_grasp' (4x4) or "
                           "'position_mm' (and optionally 'euler_deg')")


def load_holder(path) -> Holder:
    """Read and validate a holder JSON file."""
    return holder_from_dict(read_json(path, HolderModelError, "holder file"), where=str(path))


def default_holder() -> Holder:
    """The bundled reference holder (a copy of ``shared/spec/holder.json``).

    Examples
    --------
    >>> holder = default_holder()
    >>> holder.n_corners, holder.area_mm2                    # the pocket's corners, mm^2
    (20, 57600.0)
    >>> holder.outer_length_x_mm, holder.outer_width_y_mm
    (480.0, 260.0)
    >>> holder.points_holder_mm[0]                           # corner 0, top face Z = 0
    array([-120.,  -90.,    0.])
    """
    text = resources.files("cutterpose.data").joinpath("holder.json").read_text()
    return holder_from_dict(json.loads(text), where="holder.json")
