"""Robot poses as robot controllers write them: readers and writers of pose rows and pose files.

A pose row is a position and a rotation in one of the conventions below. Each convention is
written down once, here, with its source; ``scipy.spatial.transform.Rotation`` does every
conversion. A row ``(x, y, z, ...)`` read in any convention gives the same :class:`Pose`
``T_<to>_<from>`` (default ``T_base_flange``): ``x_base = R @ x_flange + t``, ``t`` in mm.

Convention:
    ===========  ==========================  ===================================  ========
    name         columns                     rotation                             units
    ===========  ==========================  ===================================  ========
    protocol     x_mm,y_mm,z_mm,qx,qy,qz,qw  unit quaternion, scalar last         mm
    quat-xyzw    x,y,z,qx,qy,qz,qw           unit quaternion, scalar last (ROS)   L
    quat-wxyz    x,y,z,qw,qx,qy,qz           unit quaternion, scalar first        L
    abb          x,y,z,q1,q2,q3,q4           quaternion, ``q1 = w``               mm
    ur, rotvec   x,y,z,rx,ry,rz              rotation vector (axis * angle)       L, A
    kuka         x,y,z,a,b,c                 ``Rz(A) Ry(B) Rx(C)``, Z-Y'-X''      mm, deg
    fanuc        x,y,z,w,p,r                 ``Rz(R) Ry(P) Rx(W)``, fixed X-Y-Z   mm, deg
    yaskawa      x,y,z,rx,ry,rz              ``Rz(Rz) Ry(Ry) Rx(Rx)``, fixed X-Y-Z mm, deg
    visp         x,y,z,tux,tuy,tuz           theta-u (rotation vector)            m, rad
    matrix       m00,m01,...,m33             4x4 homogeneous, row-major           L
    ===========  ==========================  ===================================  ========

    L, A: the length (mm or m) and angle (deg or rad) unit must be stated.

    KUKA's A, B, C turn about Z, then the new Y', then the new X'' (intrinsic; scipy ``"ZYX"``
    with ``[A, B, C]``). Fanuc's W, P, R turn about the fixed X, then the fixed Y, then the fixed
    Z of the user frame (extrinsic; scipy ``"xyz"`` with ``[W, P, R]``); both give the same
    matrix ``Rz Ry Rx`` -- only the names and the order of the numbers differ. Yaskawa's Rx, Ry,
    Rz (pendant and job files, mm and deg) are that same fixed X, then Y, then Z order, written
    in the order x, y, z. ViSP's ``vpPoseVector`` is the translation in metres and theta-u (the
    rotation vector, axis * angle) in radians. A UR rotation
    vector is ``axis * angle`` (the pendant shows it in rad; URScript uses m and rad). ABB's
    ``orient`` is ``[q1, q2, q3, q4] = [w, x, y, z]``. A vendor's own units are used only when
    its controller knows no other (KUKA, Fanuc: mm and deg; ABB: mm); every other length or
    angle unit must be stated, in the file or by the caller.

    How a file states its convention and units (the caller's arguments win; a contradiction
    is an error):

    * CSV: comment lines before the header, ``# convention: kuka``, ``# length_unit: mm``,
      ``# angle_unit: deg``; or unit suffixes in the header (``x_mm``, ``a_deg``, ``rx_rad``).
      Quaternion and matrix headers name their own convention (``qx..qw``, ``q1..q4``,
      ``m00..m33``); rotation vectors and Euler angles never do (``a, b, c`` or ``rx, ry, rz``
      mean different things on different robots) and need ``convention``.
    * JSON: ``{"convention": ..., "length_unit": ..., "angle_unit": ..., "poses": [...]}``, each
      pose a list in the convention's column order, an object keyed by column names, or (for
      ``matrix``) a nested 4x4 list.

References:
    KUKA System Software 8.x, Operating and Programming Instructions, section "Coordinate
    systems" (A about Z, B about Y, C about X; mm, deg).
    FANUC R-30iB Operator's Manual, "User frame / position data" (W, P, R about the fixed X, Y,
    Z axes; mm, deg).
    ABB RAPID Reference Manual, data types ``pos`` (mm) and ``orient`` (q1 = scalar).
    Universal Robots, "Explanation on robot orientation" (rotation vector, URScript ``p[x, y, z,
    rx, ry, rz]`` in m and rad).
    ROS REP 103 (quaternion x, y, z, w; metres).
    Yaskawa Rx, Ry, Rz: Roboception rc_visard manual, "Yaskawa pose format" (position in mm,
    angles in deg, ``R = rz(Rz) ry(Ry) rx(Rx)``), and the YRC1000 INFORM manual (``C`` position
    variables in mm and deg).
    ViSP ``vpPoseVector`` (``saveYAML``: ``rows: 6, cols: 1, data: [[tx], [ty], [tz], [tux],
    [tuy], [tuz]]``, metres and radians), as written by ViSP's hand-eye tutorials
    (``pose_fPe_N.yaml``).
"""

from __future__ import annotations

import csv
import io
import json
import math
from dataclasses import dataclass
from pathlib import Path

import numpy as np
from scipy.spatial.transform import Rotation

from ..errors import InputError
from ..geometry.pose import Pose, nearest_rotation

__all__ = ["CONVENTIONS", "PoseConvention", "read_poses", "write_poses", "poses_from_rows",
           "poses_to_rows", "parse_pose_row", "load_flange_pose", "LENGTH_UNITS", "ANGLE_UNITS"]

LENGTH_UNITS = {"mm": 1.0, "m": 1000.0}
ANGLE_UNITS = {"deg": 1.0, "rad": 180.0 / math.pi}
_MATRIX_COLUMNS = tuple(f"m{i}{j}" for i in range(4) for j in range(4))


@dataclass(frozen=True)
class PoseConvention:
    """One way of writing a pose as a row of numbers (module table)."""

    name: str
    columns: tuple[str, ...]
    rotation: str                 #: matrix | quat_xyzw | quat_wxyz | rotvec | euler
    euler_seq: str = ""           #: scipy sequence for ``euler`` (upper case: intrinsic)
    euler_order: tuple = ()       #: column indices of the three angles in scipy's order
    length_unit: str | None = None  #: the vendor's only length unit, else None (state it)
    angle_unit: str | None = None   #: the vendor's only angle unit, else None (state it)
    inferable: bool = False       #: the header's column names alone identify it

    @property
    def needs_angle_unit(self) -> bool:
        return self.rotation in ("rotvec", "euler")


CONVENTIONS: dict[str, PoseConvention] = {c.name: c for c in [
    PoseConvention("protocol", ("x", "y", "z", "qx", "qy", "qz", "qw"), "quat_xyzw",
                   length_unit="mm"),
    PoseConvention("quat-xyzw", ("x", "y", "z", "qx", "qy", "qz", "qw"), "quat_xyzw",
                   inferable=True),
    PoseConvention("quat-wxyz", ("x", "y", "z", "qw", "qx", "qy", "qz"), "quat_wxyz",
                   inferable=True),
    PoseConvention("abb", ("x", "y", "z", "q1", "q2", "q3", "q4"), "quat_wxyz",
                   length_unit="mm", inferable=True),
    PoseConvention("ur", ("x", "y", "z", "rx", "ry", "rz"), "rotvec"),
    PoseConvention("rotvec", ("x", "y", "z", "rx", "ry", "rz"), "rotvec"),
    PoseConvention("kuka", ("x", "y", "z", "a", "b", "c"), "euler", "ZYX", (3, 4, 5),
                   length_unit="mm", angle_unit="deg"),
    PoseConvention("fanuc", ("x", "y", "z", "w", "p", "r"), "euler", "xyz", (3, 4, 5),
                   length_unit="mm", angle_unit="deg"),
    PoseConvention("yaskawa", ("x", "y", "z", "rx", "ry", "rz"), "euler", "xyz", (3, 4, 5),
                   length_unit="mm", angle_unit="deg"),
    PoseConvention("visp", ("x", "y", "z", "tux", "tuy", "tuz"), "rotvec", length_unit="m",
                   angle_unit="rad"),
    PoseConvention("matrix", _MATRIX_COLUMNS, "matrix", inferable=True),
]}


def _convention(name: str) -> PoseConvention:
    try:
        return CONVENTIONS[str(name).strip().lower()]
    except KeyError:
        raise InputError(f"unknown pose convention {name!r}; choose one of "
                         f"{', '.join(CONVENTIONS)}") from None


def _unit(value, table: dict, what: str) -> str | None:
    if value is None:
        return None
    v = str(value).strip().lower()
    aliases = {"millimetre": "mm", "millimeter": "mm", "metre": "m", "meter": "m",
               "degree": "deg", "degrees": "deg", "radian": "rad", "radians": "rad"}
    v = aliases.get(v, v)
    if v not in table:
        raise InputError(f"unknown {what} unit {value!r}; use {' or '.join(table)}")
    return v


# ------------------------------------------------------------------------------------------
# rows <-> poses
def _rotations_from_rows(rows: np.ndarray, conv: PoseConvention, angle_scale_deg: float):
    """scipy ``Rotation`` (vectorised) and translations (in the file's length unit)."""
    if conv.rotation == "matrix":
        T = rows.reshape(-1, 4, 4)
        if np.abs(T[:, 3] - [0, 0, 0, 1]).max() > 1e-6:
            raise InputError("a 4x4 pose matrix must end with the row 0 0 0 1")
        R = T[:, :3, :3]
        # controllers print 4-6 decimals: accept a rotation that far off, then make it exact
        err = np.abs(np.swapaxes(R, 1, 2) @ R - np.eye(3)).max(axis=(1, 2))
        if np.any(err > 1e-3) or np.any(np.linalg.det(R) < 0):
            k = int(np.argmax(err))
            raise InputError(f"pose {k}: the 3x3 block is not a rotation (R^T R - I up to "
                             f"{err[k]:.2g})")
        return Rotation.from_matrix(nearest_rotation(R)), T[:, :3, 3]
    t = rows[:, :3]
    if conv.rotation in ("quat_xyzw", "quat_wxyz"):
        q = rows[:, 3:7]
        if conv.rotation == "quat_wxyz":
            q = q[:, [1, 2, 3, 0]]
        n = np.linalg.norm(q, axis=1)
        if np.any(np.abs(n - 1.0) > 1e-3):
            k = int(np.argmax(np.abs(n - 1.0)))
            raise InputError(f"pose {k}: the quaternion has norm {n[k]:.6g}, not 1 (check the "
                             f"column order: {', '.join(conv.columns[3:])})")
        return Rotation.from_quat(q / n[:, None]), t
    # a controller writes angles within one turn: more means degrees read as radians
    turn = (np.linalg.norm(rows[:, 3:6], axis=1) if conv.rotation == "rotvec"
            else np.abs(rows[:, 3:6]).max(axis=1)) * angle_scale_deg
    if np.any(turn > 360.0 + 1e-6):
        k = int(np.argmax(turn))
        raise InputError(f"pose {k}: a rotation of {turn[k]:.0f} deg (more than one turn): the "
                         "angles are likely in degrees read as radians; state the angle unit")
    if conv.rotation == "rotvec":
        return Rotation.from_rotvec(np.radians(rows[:, 3:6] * angle_scale_deg)), t
    angles = rows[:, list(conv.euler_order)] * angle_scale_deg
    return Rotation.from_euler(conv.euler_seq, angles, degrees=True), t


def poses_from_rows(rows, convention: str, length_unit: str | None = None,
                    angle_unit: str | None = None, to_frame: str = "base",
                    from_frame: str = "flange") -> list[Pose]:
    """Poses from an ``(n, k)`` array of rows in ``convention`` (module table).

    Raises
    ------
    InputError
        Unknown convention, a unit missing that the convention does not fix, wrong column
        count, non-finite values, a quaternion that is not unit or a matrix that is not rigid.
    """
    conv = _convention(convention)
    lu = _unit(length_unit, LENGTH_UNITS, "length") or conv.length_unit
    au = _unit(angle_unit, ANGLE_UNITS, "angle") or conv.angle_unit
    if lu is None:
        raise InputError(f"pose convention {conv.name!r}: no length unit; state mm or m "
                         "(length_unit, a '# length_unit: mm' line or an x_mm column)")
    if conv.needs_angle_unit and au is None:
        raise InputError(f"pose convention {conv.name!r}: no angle unit; state deg or rad "
                         "(angle_unit, a '# angle_unit: deg' line or an rx_deg column)")
    try:
        a = np.asarray(rows, float)
    except (TypeError, ValueError, OverflowError):
        raise InputError("pose rows must be numbers") from None
    a = a.reshape(len(a), -1) if a.ndim > 1 else a.reshape(1, -1)
    if a.shape[1] != len(conv.columns):
        raise InputError(f"pose convention {conv.name!r} needs {len(conv.columns)} numbers "
                         f"per pose ({','.join(conv.columns)}), got {a.shape[1]}")
    if not np.all(np.isfinite(a)):
        k = int(np.argwhere(~np.isfinite(a))[0, 0])
        raise InputError(f"pose {k} holds a non-finite value")
    rot, t = _rotations_from_rows(a, conv, ANGLE_UNITS.get(au, 1.0))
    t_mm = t * LENGTH_UNITS[lu]
    R = rot.as_matrix().reshape(-1, 3, 3)
    return [Pose(Rk, tk, to_frame, from_frame) for Rk, tk in zip(R, t_mm)]


def poses_to_rows(poses, convention: str = "protocol", length_unit: str | None = None,
                  angle_unit: str | None = None) -> np.ndarray:
    """Rows ``(n, k)`` of ``poses`` in ``convention`` (inverse of :func:`poses_from_rows`).

    Quaternions are written with a non-negative scalar part.
    """
    conv = _convention(convention)
    lu = _unit(length_unit, LENGTH_UNITS, "length") or conv.length_unit or "mm"
    au = _unit(angle_unit, ANGLE_UNITS, "angle") or conv.angle_unit or "deg"
    R = np.stack([p.R for p in poses])
    t = np.stack([p.t_mm for p in poses]) / LENGTH_UNITS[lu]
    if conv.rotation == "matrix":
        T = np.tile(np.eye(4), (len(R), 1, 1))
        T[:, :3, :3], T[:, :3, 3] = R, t
        return T.reshape(len(R), 16)
    rot = Rotation.from_matrix(R)
    if conv.rotation in ("quat_xyzw", "quat_wxyz"):
        q = rot.as_quat()
        q *= np.where(q[:, 3:] < 0, -1.0, 1.0)
        if conv.rotation == "quat_wxyz":
            q = q[:, [3, 0, 1, 2]]
        return np.concatenate([t, q], axis=1)
    scale = ANGLE_UNITS[au]
    if conv.rotation == "rotvec":
        return np.concatenate([t, np.degrees(rot.as_rotvec()) / scale], axis=1)
    ang = rot.as_euler(conv.euler_seq, degrees=True) / scale
    out = np.empty((len(R), 6))
    out[:, :3] = t
    out[:, list(conv.euler_order)] = ang
    return out


# ------------------------------------------------------------------------------------------
# files
def _split_name(name: str) -> tuple[str, str | None]:
    """``'x_mm'`` -> ``('x', 'mm')``; ``'qx'`` -> ``('qx', None)``."""
    n = name.strip().lower()
    for suffix in ("_mm", "_m", "_deg", "_rad"):
        if n.endswith(suffix) and len(n) > len(suffix):
            return n[: -len(suffix)], suffix[1:]
    return n, None


def _units_from_header(names, where: str) -> tuple[str | None, str | None]:
    lengths, angles = set(), set()
    for n in names:
        _, u = _split_name(n)
        if u in LENGTH_UNITS:
            lengths.add(u)
        elif u in ANGLE_UNITS:
            angles.add(u)
    if len(lengths) > 1 or len(angles) > 1:
        raise InputError(f"{where}: the header mixes units ({', '.join(names)})")
    return (lengths.pop() if lengths else None), (angles.pop() if angles else None)


def _convention_from_header(bases: list[str], where: str) -> str | None:
    if bases == list(CONVENTIONS["protocol"].columns):
        return "quat-xyzw"
    for c in CONVENTIONS.values():
        if c.inferable and bases == list(c.columns):
            return c.name
    return None


def _merge(stated, found, what: str, where: str):
    """The caller's value wins when the file says nothing; a contradiction is an error."""
    if stated is not None and found is not None and str(stated).lower() != str(found).lower():
        raise InputError(f"{where}: the file says {what} {found!r}, the caller {stated!r}")
    return stated if stated is not None else found


def _parse_meta_line(line: str, meta: dict) -> None:
    body = line.lstrip("#").strip()
    for sep in (":", "="):
        if sep in body:
            k, v = body.split(sep, 1)
            k = k.strip().lower().replace(" ", "_")
            if k in ("convention", "length_unit", "angle_unit", "frames"):
                meta[k] = v.strip()
            return


def _read_csv(text: str, where: str, convention, length_unit, angle_unit):
    meta: dict = {}
    lines = []
    for line in text.splitlines():
        s = line.strip()
        if not s:
            continue
        if s.startswith("#"):
            _parse_meta_line(s, meta)
        else:
            lines.append(s)
    if not lines:
        raise InputError(f"{where}: no poses in the file")
    rows = list(csv.reader(io.StringIO("\n".join(lines)), skipinitialspace=True))
    header = None
    try:
        [float(v) for v in rows[0]]
    except ValueError:
        header, rows = [h.strip() for h in rows[0]], rows[1:]
    conv_name = _merge(convention, meta.get("convention"), "convention", where)
    lu = _merge(length_unit, meta.get("length_unit"), "length unit", where)
    au = _merge(angle_unit, meta.get("angle_unit"), "angle unit", where)
    if header is not None:
        hl, ha = _units_from_header(header, where)
        lu, au = _merge(lu, hl, "length unit", where), _merge(au, ha, "angle unit", where)
        bases = [_split_name(h)[0] for h in header]
        if conv_name is None:
            conv_name = _convention_from_header(bases, where)
        if conv_name is not None and bases != list(_convention(conv_name).columns):
            raise InputError(f"{where}: convention {conv_name!r} needs the columns "
                             f"{','.join(_convention(conv_name).columns)}, the header has "
                             f"{','.join(header)}")
    if conv_name is None:
        raise InputError(
            f"{where}: no pose convention; add a line '# convention: NAME' (one of "
            f"{', '.join(CONVENTIONS)}) or give it on the command line")
    width = len(header) if header is not None else len(rows[0]) if rows else 0
    for k, r in enumerate(rows):
        if len(r) != width:
            raise InputError(f"{where}: pose row {k + 1} has {len(r)} values, the "
                             f"{'header' if header is not None else 'first row'} {width} "
                             "(a ragged row)")
    try:
        data = np.array([[float(v) for v in r] for r in rows], float)
    except ValueError as e:
        raise InputError(f"{where}: a pose row is not numbers ({e})") from None
    if len(data) == 0:
        raise InputError(f"{where}: no poses in the file")
    return data, conv_name, lu, au


def _read_json(text: str, where: str, convention, length_unit, angle_unit):
    try:
        doc = json.loads(text)
    except json.JSONDecodeError as e:
        raise InputError(f"{where}: not valid JSON ({e})") from None
    if isinstance(doc, list):
        doc = {"poses": doc}
    if not isinstance(doc, dict) or not isinstance(doc.get("poses"), list):
        raise InputError(f"{where}: expected an object with a 'poses' list")
    conv_name = _merge(convention, doc.get("convention"), "convention", where)
    lu = _merge(length_unit, doc.get("length_unit"), "length unit", where)
    au = _merge(angle_unit, doc.get("angle_unit"), "angle unit", where)
    poses = doc["poses"]
    if poses and isinstance(poses[0], dict):
        keys = list(poses[0])
        hl, ha = _units_from_header(keys, where)
        lu, au = _merge(lu, hl, "length unit", where), _merge(au, ha, "angle unit", where)
        bases = [_split_name(k)[0] for k in keys]
        if conv_name is None:
            conv_name = _convention_from_header(sorted(bases, key=_column_rank), where)
        if conv_name is None:
            raise InputError(f"{where}: no pose convention; add \"convention\": NAME (one of "
                             f"{', '.join(CONVENTIONS)})")
        cols = _convention(conv_name).columns
        if not all(isinstance(p, dict) for p in poses):
            raise InputError(f"{where}: every pose must be an object like the first one")
        lookup = [{_split_name(k)[0]: v for k, v in p.items()} for p in poses]
        missing = [c for c in cols if c not in lookup[0]]
        if missing:
            raise InputError(f"{where}: convention {conv_name!r} needs the keys "
                             f"{','.join(cols)}; missing {','.join(missing)}")
        rows = [[p.get(c, math.nan) for c in cols] for p in lookup]
    else:
        if conv_name is None:
            raise InputError(f"{where}: no pose convention; add \"convention\": NAME (one of "
                             f"{', '.join(CONVENTIONS)})")
        try:
            rows = [np.ravel(np.asarray(p, float)) for p in poses] if poses else []
        except (TypeError, ValueError, OverflowError):
            raise InputError(f"{where}: every pose must be a list of numbers") from None
    if not rows:
        raise InputError(f"{where}: no poses in the file")
    try:
        data = np.array(rows, float)
    except (TypeError, ValueError, OverflowError):
        raise InputError(f"{where}: every pose must have the same number of numbers") from None
    return data, conv_name, lu, au


def _column_rank(name: str) -> int:
    order = ["x", "y", "z", "qw", "qx", "qy", "qz", "q1", "q2", "q3", "q4"]
    return order.index(name) if name in order else len(order)


def read_poses(path, convention: str | None = None, length_unit: str | None = None,
               angle_unit: str | None = None, to_frame: str = "base",
               from_frame: str = "flange") -> list[Pose]:
    """Read a pose file (CSV or JSON; module doc), one :class:`Pose` per row, in file order.

    Parameters
    ----------
    path : ``.csv`` / ``.txt`` or ``.json`` file.
    convention, length_unit, angle_unit : what the file does not state itself.
    to_frame, from_frame : frame names of the poses (default ``T_base_flange``).

    Raises
    ------
    InputError
        Missing file, no convention or unit where one is needed (the message names what to
        add), a contradiction between the file and the caller, malformed rows.
    """
    p = Path(path)
    where = str(p)
    if not p.is_file():
        raise InputError(f"{where}: pose file not found")
    try:
        text = p.read_text()
    except (OSError, UnicodeDecodeError) as e:
        raise InputError(f"{where}: cannot be read ({e})") from None
    reader = _read_json if p.suffix.lower() == ".json" else _read_csv
    data, conv, lu, au = reader(text, where, convention, length_unit, angle_unit)
    try:
        return poses_from_rows(data, conv, lu, au, to_frame, from_frame)
    except InputError as e:
        raise InputError(f"{where}: {e}") from None


def write_poses(path, poses, convention: str = "protocol", length_unit: str | None = None,
                angle_unit: str | None = None) -> Path:
    """Write poses as CSV (``.csv``) or JSON (``.json``) that :func:`read_poses` reads back.

    ``protocol`` writes exactly PROTOCOL.md's pose file (header ``x_mm,y_mm,z_mm,qx,qy,qz,qw``,
    nothing else); every other convention states itself and its units in the file.
    """
    conv = _convention(convention)
    lu = _unit(length_unit, LENGTH_UNITS, "length") or conv.length_unit or "mm"
    au = _unit(angle_unit, ANGLE_UNITS, "angle") or conv.angle_unit or "deg"
    rows = poses_to_rows(poses, conv.name, lu, au)
    p = Path(path)
    frames = poses[0].name if len(poses) else ""
    if p.suffix.lower() == ".json":
        doc = {"convention": conv.name, "length_unit": lu, "frames": frames,
               "poses": rows.tolist()}
        if conv.needs_angle_unit:
            doc["angle_unit"] = au
        p.write_text(json.dumps(doc, indent=1) + "\n")
        return p
    cols = []
    for c in conv.columns:
        if c in ("x", "y", "z"):
            cols.append(f"{c}_{lu}")
        elif conv.needs_angle_unit and c in conv.columns[3:]:
            cols.append(f"{c}_{au}")
        else:
            cols.append(c)
    if conv.rotation == "matrix":
        cols = list(conv.columns)
    lines = []
    if conv.name != "protocol":
        lines += [f"# convention: {conv.name}", f"# length_unit: {lu}"]
        if conv.needs_angle_unit:
            lines.append(f"# angle_unit: {au}")
        if frames:
            lines.append(f"# frames: {frames}")
    lines.append(",".join(cols))
    lines += [",".join(repr(float(v)) for v in r) for r in rows]
    p.write_text("\n".join(lines) + "\n")
    return p


def parse_pose_row(text: str, to_frame: str = "base", from_frame: str = "flange") -> Pose:
    """One pose inline in the PROTOCOL's row form ``x_mm,y_mm,z_mm,qx,qy,qz,qw``."""
    try:
        vals = [float(v) for v in str(text).split(",")]
    except ValueError:
        vals = []
    if len(vals) != 7:
        raise InputError(f"an inline pose needs 7 comma-separated numbers x_mm,y_mm,z_mm,qx,qy,"
                         f"qz,qw; got {text!r}")
    return poses_from_rows([vals], "protocol", to_frame=to_frame, from_frame=from_frame)[0]


def load_flange_pose(spec: str, convention: str | None = None,
                     length_unit: str | None = None, angle_unit: str | None = None) -> Pose:
    """``T_base_flange`` from a one-row pose file or an inline PROTOCOL row."""
    p = Path(spec)
    try:
        is_file = p.is_file()
    except (OSError, ValueError):      # not a usable path (too long, NUL): an inline row
        is_file = False
    if p.suffix.lower() in (".csv", ".json", ".txt") or is_file:
        poses = read_poses(p, convention, length_unit, angle_unit)
        if len(poses) != 1:
            raise InputError(f"{spec}: a flange pose file must hold one pose, it holds "
                             f"{len(poses)}")
        return poses[0]
    return parse_pose_row(spec)
