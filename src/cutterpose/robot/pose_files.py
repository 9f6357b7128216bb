"""Pose files as robot controllers, ROS and ViSP write them, and pose sets for hand-eye calibration.

:mod:`cutterpose.robot.poses` reads rows of numbers (CSV, JSON) in a named convention. This
module reads the other files users have, each one pose or many, and a folder of them:

=============  ==================================================================  ===========
format         content                                                             units
=============  ==================================================================  ===========
``csv/json``   rows in a convention of :mod:`~cutterpose.robot.poses` (its doc)    stated
``ros-yaml``   ``x, y, z, qx, qy, qz, qw`` at the top level (robot_cal_tools'       m (REP 103)
               ``poses/N.yaml``), or ``geometry_msgs`` ``position``/``orientation``
               or ``translation``/``rotation`` (optionally under ``pose:`` or
               ``transform:``); one such mapping, a list of them, or ``poses: [...]``
``visp-yaml``  ``vpPoseVector::saveYAML``: ``rows: 6``, ``cols: 1``, ``data: [[tx],  m, rad
               [ty], [tz], [tux], [tuy], [tuz]]`` (theta-u), one pose per file
``yaskawa``    a Yaskawa/Motoman job file (``.JBI``): the ``//POS`` section's        mm, deg
               Cartesian position variables ``Cnnnnn=X,Y,Z,Rx,Ry,Rz`` under
               ``///RECTAN``; ``R = Rz(Rz) Ry(Ry) Rx(Rx)``
=============  ==================================================================  ===========

A folder is read as one station per file (every pose file in it, natural order: ``2.yaml``
before ``10.yaml``); robot_cal_tools' ``cal_data.yaml`` (a list of ``{pose: FILE, image:
FILE}``) reads each pose file it names, the pose named after its image.
Each pose gets a name: the file's stem, ``stem:Cnnnnn`` for a job file's
variable, ``stem:k`` for row ``k`` of a many-pose file. :func:`pair_with_images` pairs poses
and images by the number in their names when both have one (``images/3.png`` with
``poses/3.yaml``, ``image-3.png`` with ``pose_fPe_3.yaml``), else in order.

A Yaskawa job file whose positions are joint pulses (``///PULSE``) is refused (a hand-eye
calibration needs the Cartesian flange pose); positions taught with a tool (``///TOOL n``,
``n > 0``) are the pose of that tool's TCP: the calibration is then of ``T_tcp_cam``, which is
right only if every station used the same tool, so a file mixing tools is refused.

References:
    ROS REP 103 (metres, quaternion x, y, z, w); ``geometry_msgs/Pose``, ``Transform``.
    robot_cal_tools (ROS-Industrial), ``rct_examples/data/*/poses/N.yaml``.
    ViSP ``vpPoseVector::saveYAML``; ViSP tutorial "Camera extrinsic calibration (eye-in-hand)".
    Yaskawa YRC1000 / DX200 INFORM manuals: job file ``//POS`` section, ``///RECTAN``,
    ``///TOOL``, position variables ``C`` (mm, deg; Rx, Ry, Rz about the fixed X, Y, Z).
"""

from __future__ import annotations

import math
import re
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from ..errors import InputError
from ..geometry.pose import Pose
from .poses import poses_from_rows, read_poses

__all__ = ["POSE_FORMATS", "PoseSet", "read_pose_set", "read_pose_file", "pair_with_images",
           "check_flange_units"]

POSE_FORMATS = ("auto", "csv", "json", "ros-yaml", "visp-yaml", "yaskawa")
_POSE_SUFFIXES = {".csv": "csv", ".txt": "csv", ".json": "json", ".yaml": "yaml",
                  ".yml": "yaml", ".jbi": "yaskawa"}


@dataclass
class PoseSet:
    """Poses in file order with their names (see module doc) and the format each was read in."""

    poses: list[Pose]
    names: list[str]
    formats: list[str]

    def __len__(self) -> int:
        return len(self.poses)


def _natural_key(p: Path) -> tuple:
    return tuple(int(t) if t.isdigit() else t.lower() for t in re.split(r"(\d+)", p.name))


def _load_yaml(path: Path):
    import yaml

    try:
        return yaml.safe_load(path.read_text())
    except (OSError, UnicodeDecodeError) as e:
        raise InputError(f"{path}: cannot be read ({e})") from None
    except yaml.YAMLError as e:
        first = str(e).splitlines()[0] if str(e) else type(e).__name__
        raise InputError(f"{path}: not valid YAML ({first})") from None


def _number(d: dict, key: str, where: str) -> float:
    if key not in d:
        raise InputError(f"{where}: missing '{key}'")
    v = d[key]
    if isinstance(v, bool) or not isinstance(v, (int, float)):
        raise InputError(f"{where}: '{key}' is not a number ({repr(v)[:40]})")
    try:
        return float(v)
    except OverflowError:
        raise InputError(f"{where}: '{key}' is too large ({repr(v)[:40]})") from None


def _ros_row(d, where: str) -> list[float]:
    """One ROS pose mapping -> ``[x, y, z, qx, qy, qz, qw]`` (m)."""
    if not isinstance(d, dict):
        raise InputError(f"{where}: expected a pose mapping, got {type(d).__name__}")
    for wrap in ("pose", "transform"):
        if wrap in d and isinstance(d[wrap], dict):
            d = d[wrap]
    for pos, ori in (("position", "orientation"), ("translation", "rotation")):
        if pos in d or ori in d:
            p, q = d.get(pos), d.get(ori)
            if not isinstance(p, dict) or not isinstance(q, dict):
                raise InputError(f"{where}: '{pos}' and '{ori}' must both be mappings")
            return ([_number(p, k, f"{where}: {pos}") for k in "xyz"]
                    + [_number(q, k, f"{where}: {ori}") for k in "xyzw"])
    return [_number(d, k, where) for k in ("x", "y", "z", "qx", "qy", "qz", "qw")]


def _visp_row(d: dict, where: str) -> list[float]:
    if d.get("rows") != 6 or d.get("cols") != 1:
        raise InputError(f"{where}: a ViSP pose vector has rows: 6 and cols: 1, got rows: "
                         f"{d.get('rows')!r}, cols: {d.get('cols')!r}")
    data = d.get("data")
    try:
        row = [float(np.ravel(v)[0]) if np.size(v) == 1 else math.nan for v in data]
    except (TypeError, ValueError, OverflowError):
        row = []
    if len(row) != 6 or not all(math.isfinite(v) for v in row):
        raise InputError(f"{where}: 'data' must hold 6 one-number rows [tx], [ty], [tz], [tux], "
                         "[tuy], [tuz]")
    return row


def _read_yaml(path: Path, fmt: str, to_frame: str, from_frame: str, in_data_set=False):
    doc = _load_yaml(path)
    where = str(path)
    if fmt == "auto":
        fmt = "visp-yaml" if isinstance(doc, dict) and "rows" in doc and "data" in doc \
            else "ros-yaml"
    if _is_data_set(doc):
        if in_data_set:  # a list naming itself or another list would never end
            raise InputError(f"{where}: a data set entry's pose file is itself a data set "
                             "(a list of {pose, image}), not one pose")
        return _read_data_set(doc, path, to_frame, from_frame)
    if fmt == "visp-yaml":
        if not isinstance(doc, dict):
            raise InputError(f"{where}: expected a ViSP pose vector (rows, cols, data)")
        rows, conv, suffixes = [_visp_row(doc, where)], "visp", [""]
    else:
        items = doc.get("poses") if isinstance(doc, dict) and "poses" in doc else doc
        many = isinstance(items, list)
        items = items if many else [items]
        if not items:
            raise InputError(f"{where}: no poses in the file")
        rows = [_ros_row(it, f"{where}: pose {k}" if many else where)
                for k, it in enumerate(items)]
        conv, suffixes = "quat-xyzw", [f":{k}" for k in range(len(rows))] if many else [""]
    try:
        poses = poses_from_rows(rows, conv, "m", "rad", to_frame, from_frame)
    except InputError as e:
        raise InputError(f"{where}: {e}") from None
    return poses, suffixes, fmt


def _is_data_set(doc) -> bool:
    """robot_cal_tools' ``cal_data.yaml``: a list of ``{pose: FILE, image: FILE}``."""
    return (isinstance(doc, list) and bool(doc) and all(isinstance(d, dict) for d in doc)
            and all(isinstance(d.get("pose"), str) for d in doc))


def _read_data_set(doc: list, path: Path, to_frame: str, from_frame: str):
    """Each entry's pose file (relative to the data set file), named after its image."""
    poses, names = [], []
    for k, d in enumerate(doc):
        f = path.parent / d["pose"]
        if not f.is_file():
            raise InputError(f"{path}: entry {k}: pose file {d['pose']} not found")
        one, _, _ = _read_yaml(f, "auto", to_frame, from_frame, in_data_set=True)
        if len(one) != 1:
            raise InputError(f"{f}: a data set entry's pose file must hold one pose")
        poses.append(one[0])
        names.append("@" + Path(str(d.get("image") or d["pose"])).stem)
    return poses, names, "ros-yaml"


_JBI_C = re.compile(r"^C(\d{5})\s*=\s*(.*)$")


def _read_jbi(path: Path, to_frame: str, from_frame: str):
    where = str(path)
    try:
        lines = path.read_text(errors="replace").splitlines()
    except OSError as e:
        raise InputError(f"{where}: cannot be read ({e})") from None
    in_pos, cartesian, tools = False, None, set()
    rows, names = [], []
    for n, raw in enumerate(lines, 1):
        s = raw.strip()
        if s.startswith("//") and not s.startswith("///"):
            in_pos = s.upper().startswith("//POS") and not s.upper().startswith("//POS-")
            continue
        if not in_pos:
            continue
        up = s.upper()
        if up.startswith("///TOOL"):
            tools.add(up.split()[-1])
        elif up.startswith("///PULSE"):
            cartesian = False
        elif up.startswith("///RECTAN"):
            cartesian = True
        m = _JBI_C.match(s)
        if m:
            if not cartesian:
                raise InputError(f"{where}, line {n}: C{m.group(1)} is in joint pulses "
                                 "(///PULSE); hand-eye calibration needs Cartesian flange "
                                 "poses: export the positions as ///RECTAN (X, Y, Z, Rx, Ry, "
                                 "Rz)")
            vals = [v.strip() for v in m.group(2).split(",")]
            try:
                row = [float(v) for v in vals]
            except ValueError:
                raise InputError(f"{where}, line {n}: C{m.group(1)} is not numbers") from None
            if len(row) != 6:
                raise InputError(f"{where}, line {n}: C{m.group(1)} has {len(row)} values, "
                                 "a Cartesian position has 6 (X, Y, Z in mm, Rx, Ry, Rz in "
                                 "deg)")
            rows.append(row)
            names.append(f":C{m.group(1)}")
    if len(tools) > 1:
        raise InputError(f"{where}: the positions use different tools ({', '.join(sorted(tools))})"
                         "; every station must report the same frame (the flange: TOOL 0)")
    if not rows:
        raise InputError(f"{where}: no Cartesian position variables (Cnnnnn=X,Y,Z,Rx,Ry,Rz) in "
                         "a //POS section")
    try:
        poses = poses_from_rows(rows, "yaskawa", "mm", "deg", to_frame, from_frame)
    except InputError as e:
        raise InputError(f"{where}: {e}") from None
    return poses, names


def read_pose_file(path, fmt: str = "auto", convention: str | None = None,
                   length_unit: str | None = None, angle_unit: str | None = None,
                   to_frame: str = "base", from_frame: str = "flange") -> PoseSet:
    """Read one pose file of any format of the module table.

    Raises
    ------
    InputError
        Unknown format, unreadable or malformed file (the message names the file, and the line
        or pose where it can), a quaternion that is not unit, a rotation that is not one.
    """
    p = Path(path)
    fmt = str(fmt or "auto").strip().lower()
    if fmt not in POSE_FORMATS:
        raise InputError(f"unknown pose format {fmt!r}; choose one of {', '.join(POSE_FORMATS)}")
    if not p.is_file():
        raise InputError(f"{p}: pose file not found")
    kind = _POSE_SUFFIXES.get(p.suffix.lower()) if fmt == "auto" else fmt
    if kind == "yaskawa" and convention is None and p.suffix.lower() != ".jbi":
        kind, convention = "csv", "yaskawa"  # a CSV of X, Y, Z, Rx, Ry, Rz rows
    if kind == "yaskawa":
        poses, suffixes = _read_jbi(p, to_frame, from_frame)
        fmts = ["yaskawa"] * len(poses)
    elif kind in ("yaml", "ros-yaml", "visp-yaml"):
        poses, suffixes, got = _read_yaml(p, "auto" if kind == "yaml" else kind, to_frame,
                                          from_frame)
        fmts = [got] * len(poses)
    elif kind in ("csv", "json"):
        poses = read_poses(p, convention, length_unit, angle_unit, to_frame, from_frame)
        suffixes = [f":{k}" for k in range(len(poses))] if len(poses) > 1 else [""]
        fmts = [kind] * len(poses)
    else:
        raise InputError(f"{p}: unknown pose file type {p.suffix!r}; give --pose-format (one of "
                         f"{', '.join(POSE_FORMATS[1:])})")
    # "@name": a data set entry named after its image; else the file's stem (and its row)
    names = [q[1:] if q.startswith("@") else p.stem + q for q in suffixes]
    return PoseSet(poses, names, fmts)


def read_pose_set(path, fmt: str = "auto", convention: str | None = None,
                  length_unit: str | None = None, angle_unit: str | None = None,
                  to_frame: str = "base", from_frame: str = "flange") -> PoseSet:
    """A pose file, or a folder of them (one station per file, natural order)."""
    p = Path(path)
    if not p.is_dir():
        return read_pose_file(p, fmt, convention, length_unit, angle_unit, to_frame, from_frame)
    files = sorted((q for q in p.iterdir() if q.is_file() and q.suffix.lower() in _POSE_SUFFIXES),
                   key=_natural_key)
    if not files:
        raise InputError(f"{p}: no pose files in the folder (.yaml, .yml, .json, .csv, .txt, "
                         ".jbi)")
    out = PoseSet([], [], [])
    for f in files:
        one = read_pose_file(f, fmt, convention, length_unit, angle_unit, to_frame, from_frame)
        out.poses += one.poses
        out.names += one.names
        out.formats += one.formats
    return out


def _number_in(name: str) -> int | None:
    nums = re.findall(r"\d+", Path(name).stem if "." in name else name)
    return int(nums[-1]) if nums else None


def pair_with_images(image_names: list[str], pose_names: list[str]) -> list[int]:
    """For each image, the index of its pose: by the number in both names when every image and
    every pose has a distinct one and the two sets match, else in order (equal counts).

    Raises
    ------
    InputError
        Different counts and no matching numbers.
    """
    ki = [_number_in(Path(n).name) for n in image_names]
    kp = [_number_in(n.split(":")[0]) for n in pose_names]
    if (None not in ki and None not in kp and len(set(ki)) == len(ki) == len(set(kp))
            == len(kp) and set(ki) == set(kp)):
        where = {k: j for j, k in enumerate(kp)}
        return [where[k] for k in ki]
    if len(image_names) != len(pose_names):
        raise InputError(f"{len(image_names)} images but {len(pose_names)} robot poses; give "
                         "one pose per image, in the images' order (or name both with the "
                         "station number: 3.png and 3.yaml)")
    return list(range(len(image_names)))


def check_flange_units(poses: list[Pose], where: str = "robot poses") -> None:
    """Refuse flange positions whose unit is evidently wrong.

    A flange is always some hundred mm from the base origin (which lies inside the robot's
    base) and within a few metres of it: every position within 5 mm of the origin means
    metres read as mm; a position beyond 20 m means mm read as metres.
    """
    if not poses:
        return
    d = np.linalg.norm(np.stack([p.t_mm for p in poses]), axis=1)
    if d.max() < 5.0:
        raise InputError(f"{where}: every flange position is within {d.max():.2f} mm of the "
                         "base origin: the file is in metres read as mm; state the length "
                         "unit m")
    if d.max() > 20000.0:
        raise InputError(f"{where}: a flange position {d.max() / 1000:.0f} m from the base: the "
                         "file is in mm read as metres; state the length unit mm")
