"""Fuzz tests of the robot pose readers (issue 32): CSV and JSON pose files in every
convention, ROS and ViSP YAML, Yaskawa job files, inline flange poses (CLI and service), with
hostile numbers, ragged rows, wrong types and corrupted text. The property
(:mod:`fuzz_support`): poses or a one-line typed error, within its time."""

import json
import math
import tempfile
from pathlib import Path

import numpy as np
import yaml
from hypothesis import given, settings
from hypothesis import strategies as st

from cutterpose.errors import InputError
from cutterpose.geometry.pose import Pose
from cutterpose.robot.pose_files import read_pose_file, read_pose_set
from cutterpose.robot.poses import (
    CONVENTIONS,
    load_flange_pose,
    parse_pose_row,
    read_poses,
    write_poses,
)
from cutterpose.service.models import parse_flange_pose
from fuzz_support import (
    HOSTILE,
    MemoryBound,
    examples,
    hostile_values,
    json_trees,
    mutated,
    mutated_bytes,
    typed_or_valid,
)

TMP = Path(tempfile.mkdtemp(prefix="cutterpose-fuzz-poses-"))
POSES = [Pose.from_euler(10, -20, 30, 800, -120, 1430), Pose.from_euler(0, 0, 0, 0, 0, 600)]
H = math.sqrt(0.5)


def _valid(convention: str, ext: str) -> bytes:
    p = TMP / f"valid_{convention}{ext}"
    write_poses(p, POSES, convention)
    return p.read_bytes()


VALID = {(c, e): _valid(c, e) for c in CONVENTIONS for e in (".csv", ".json")}
ROS = {"x": 0.1, "y": 0.2, "z": 0.3, "qx": 0, "qy": 0, "qz": H, "qw": H}
ROS_LIST = {"poses": [{"position": {"x": 0.1, "y": 0.2, "z": 0.3},
                       "orientation": {"x": 0, "y": 0, "z": H, "w": H}},
                      {"transform": {"translation": {"x": 1.0, "y": 0, "z": 0},
                                     "rotation": {"x": 0, "y": 0, "z": 0, "w": 1}}}]}
VISP = {"rows": 6, "cols": 1, "data": [[0.1], [0.2], [0.3], [0], [0], [math.pi / 2]]}
JBI = ("/JOB\n//NAME HANDEYE\n//POS\n///NPOS 2,0,0,0,0,0\n///TOOL 0\n///POSTYPE ROBOT\n"
       "///RECTAN\n///RCONF 0,0,0,0,0,0,0,0\nC00000=100.000,200.000,300.000,0.0000,0.0000,"
       "90.0000\nC00001=1012.500,-230.100,845.000,10.0000,20.0000,30.0000\n//INST\nNOP\nEND\n")


def _check(out):
    if isinstance(out, InputError):
        return
    poses = out.poses if hasattr(out, "poses") else out
    for p in poses if isinstance(poses, list) else [poses]:
        assert isinstance(p, Pose) and np.all(np.isfinite(p.R)) and np.all(np.isfinite(p.t_mm))


def _read(reader, data: bytes, name: str, **kw):
    path = TMP / name
    path.write_bytes(data)
    with MemoryBound():
        _check(typed_or_valid(reader, path, **kw))


@settings(max_examples=examples(60))
@given(key=st.sampled_from(sorted(VALID)), data=st.data(),
       stated=st.booleans())
def test_pose_files_in_every_convention_corrupted(key, data, stated):
    convention, ext = key
    bad = data.draw(mutated_bytes(VALID[key]))
    kw = {"convention": convention} if stated else {}
    _read(read_poses, bad, "poses" + ext, **kw)
    _read(read_pose_file, bad, "poses" + ext, **kw)


@st.composite
def rows_text(draw):
    """A CSV pose file: any stated convention and units, rows of hostile numbers, ragged."""
    conv = draw(st.sampled_from(list(CONVENTIONS) + ["nope", ""]))
    head = [f"# convention: {conv}", f"# length_unit: {draw(st.sampled_from(['mm', 'm', 'in']))}",
            f"# angle_unit: {draw(st.sampled_from(['deg', 'rad', 'grad']))}"]
    n_cols = draw(st.integers(0, 18))
    rows = draw(st.lists(st.lists(st.sampled_from(
        ["0", "1", "-1", "nan", "inf", "-inf", "1e308", "1e400", "0.7071", "x", "", "1,5"]),
        min_size=max(n_cols - 2, 0), max_size=n_cols + 2), max_size=5))
    return ("\n".join(head + [",".join(r) for r in rows]) + "\n").encode()


@settings(max_examples=examples(60))
@given(text=rows_text())
def test_csv_rows_with_hostile_numbers_and_ragged_rows(text):
    _read(read_poses, text, "rows.csv")


@settings(max_examples=examples(40))
@given(doc=st.one_of(st.sampled_from([json.loads(VALID[(c, ".json")]) for c in CONVENTIONS])
                     .flatmap(mutated), json_trees))
def test_json_pose_trees(doc):
    _read(read_poses, json.dumps(doc).encode(), "tree.json")


@settings(max_examples=examples(40))
@given(doc=st.one_of(st.sampled_from([ROS, ROS_LIST, VISP]).flatmap(mutated), json_trees),
       name=st.sampled_from(["3.yaml", "pose_fPe_2.yaml", "cell.yml"]))
def test_ros_and_visp_yaml_trees(doc, name):
    try:
        text = yaml.safe_dump(doc).encode()
    except (yaml.YAMLError, RecursionError):
        return
    _read(read_pose_file, text, name)


@settings(max_examples=examples(40))
@given(data=st.data())
def test_yaskawa_job_files_corrupted(data):
    _read(read_pose_file, data.draw(mutated_bytes(JBI.encode())), "CELL.JBI")


@settings(max_examples=examples(60))
@given(row=st.one_of(
    st.text(max_size=60),
    st.lists(st.sampled_from([str(v) for v in HOSTILE[:14]] + ["0.5", "1"]), max_size=9)
    .map(",".join)))
def test_inline_flange_poses(row):
    with MemoryBound():
        _check(typed_or_valid(parse_pose_row, row))
        _check(typed_or_valid(load_flange_pose, row))
        try:                                # the service's query parameter
            out = parse_flange_pose(row)
        except ValueError as e:             # pydantic turns it into a 422
            assert "\n" not in str(e)
        else:
            assert len(out) == 7 and all(math.isfinite(v) for v in out)


@settings(max_examples=examples(30))
@given(value=st.one_of(hostile_values, json_trees))
def test_service_flange_pose_values(value):
    try:
        out = parse_flange_pose(value)
    except ValueError as e:
        assert "\n" not in str(e)
    else:
        assert len(out) == 7 and all(math.isfinite(v) for v in out)


@settings(max_examples=examples(30))
@given(entries=st.lists(st.fixed_dictionaries(
    {"pose": st.sampled_from(["3.yaml", "cal_data.yaml", "missing.yaml", "", "sub", "\x00",
                              "../" * 40 + "x.yaml"]),
     "image": st.one_of(st.none(), st.text(max_size=10))}), min_size=1, max_size=4),
       pose=st.one_of(st.just(ROS), mutated(ROS)))
def test_robot_cal_tools_data_sets(entries, pose):
    """cal_data.yaml naming pose files: missing, empty, a folder, itself (a list that names
    itself once recursed for ever), or a hostile pose."""
    folder = TMP / "dataset"
    (folder / "sub").mkdir(parents=True, exist_ok=True)
    (folder / "3.yaml").write_text(yaml.safe_dump(pose))
    (folder / "cal_data.yaml").write_text(yaml.safe_dump(entries))
    with MemoryBound():
        _check(typed_or_valid(read_pose_set, folder / "cal_data.yaml"))
