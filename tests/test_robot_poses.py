"""Robot pose conventions (issue 11): hand-computed poses, round trips, ambiguous files, and the
covariance algebra of frame-named transforms."""

from __future__ import annotations

import math

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from cutterpose.errors import InputError
from cutterpose.geometry.pose import Pose, rotation_from_euler_deg
from cutterpose.robot.frames import PoseCov, cov_from_dof, cov_from_own_axes, cov_to_own_axes
from cutterpose.robot.poses import (
    CONVENTIONS,
    load_flange_pose,
    parse_pose_row,
    poses_from_rows,
    poses_to_rows,
    read_poses,
    write_poses,
)


def _axis_rot(axis: int, deg: float) -> np.ndarray:
    """Right-handed rotation about coordinate axis 0, 1 or 2, written out by hand."""
    c, s = math.cos(math.radians(deg)), math.sin(math.radians(deg))
    i, j = [(1, 2), (2, 0), (0, 1)][axis]
    R = np.eye(3)
    R[i, i], R[i, j], R[j, i], R[j, j] = c, -s, s, c
    return R


# hand-computed: a quarter turn about z, with position (100, 200, 300) mm
RZ90 = np.array([[0.0, -1.0, 0.0], [1.0, 0.0, 0.0], [0.0, 0.0, 1.0]])
H = math.sqrt(0.5)
HAND = {  # convention -> (row, units) all meaning R = RZ90, t = (100, 200, 300) mm
    "protocol": ([100, 200, 300, 0, 0, H, H], {}),
    "quat-xyzw": ([0.1, 0.2, 0.3, 0, 0, H, H], {"length_unit": "m"}),
    "quat-wxyz": ([100, 200, 300, H, 0, 0, H], {"length_unit": "mm"}),
    "abb": ([100, 200, 300, H, 0, 0, H], {}),
    "ur": ([0.1, 0.2, 0.3, 0, 0, math.pi / 2], {"length_unit": "m", "angle_unit": "rad"}),
    "rotvec": ([100, 200, 300, 0, 0, 90], {"length_unit": "mm", "angle_unit": "deg"}),
    "kuka": ([100, 200, 300, 90, 0, 0], {}),
    "fanuc": ([100, 200, 300, 0, 0, 90], {}),
    "matrix": ([0, -1, 0, 100, 1, 0, 0, 200, 0, 0, 1, 300, 0, 0, 0, 1], {"length_unit": "mm"}),
}


@pytest.mark.parametrize("conv", sorted(HAND))
def test_each_convention_matches_a_hand_computed_pose(conv):
    row, units = HAND[conv]
    p = poses_from_rows([row], conv, **units)[0]
    np.testing.assert_allclose(p.R, RZ90, atol=1e-12)
    np.testing.assert_allclose(p.t_mm, [100, 200, 300], atol=1e-9)
    assert p.name == "T_base_flange"


def test_kuka_and_fanuc_euler_orders_against_hand_products():
    # KUKA A, B, C = 30, 20, 10: Rz(30) Ry(20) Rx(10); Fanuc W, P, R = 10, 20, 30: the same
    expect = _axis_rot(2, 30) @ _axis_rot(1, 20) @ _axis_rot(0, 10)
    k = poses_from_rows([[0, 0, 0, 30, 20, 10]], "kuka")[0]
    f = poses_from_rows([[0, 0, 0, 10, 20, 30]], "fanuc")[0]
    np.testing.assert_allclose(k.R, expect, atol=1e-12)
    np.testing.assert_allclose(f.R, expect, atol=1e-12)
    # KUKA B alone turns about Y: x goes to (cos B, 0, -sin B)
    b = poses_from_rows([[0, 0, 0, 0, 30, 0]], "kuka")[0]
    np.testing.assert_allclose(b.R[:, 0], [math.cos(math.radians(30)), 0,
                                           -math.sin(math.radians(30))], atol=1e-12)


@pytest.mark.parametrize("conv", sorted(CONVENTIONS))
@pytest.mark.parametrize("suffix", [".csv", ".json"])
def test_round_trip_through_files(tmp_path, conv, suffix):
    rng = np.random.default_rng(3)
    poses = [Pose(Rotation.random(random_state=k).as_matrix(), rng.uniform(-900, 900, 3),
                  "base", "flange") for k in range(5)]
    units = {} if conv in ("protocol",) else {"length_unit": "m"}
    if CONVENTIONS[conv].needs_angle_unit:
        units["angle_unit"] = "rad"
    if conv in ("kuka", "fanuc", "abb"):
        units = {}
    path = write_poses(tmp_path / f"p{suffix}", poses, conv, **units)
    back = read_poses(path)  # the file states everything itself
    for a, b in zip(poses, back):
        np.testing.assert_allclose(b.R, a.R, atol=1e-12)
        np.testing.assert_allclose(b.t_mm, a.t_mm, atol=1e-9)
    rows = poses_to_rows(back, conv, **units)
    again = poses_from_rows(rows, conv, **units)
    np.testing.assert_allclose(again[2].R, poses[2].R, atol=1e-12)


def test_protocol_file_is_exactly_the_protocol_header(tmp_path):
    p = write_poses(tmp_path / "r.csv", [Pose(RZ90, [1, 2, 3], "base", "flange")])
    lines = p.read_text().splitlines()
    assert lines[0] == "x_mm,y_mm,z_mm,qx,qy,qz,qw"
    assert len(lines) == 2
    np.testing.assert_allclose(read_poses(p)[0].R, RZ90, atol=1e-12)


@pytest.mark.parametrize("text, missing, fix, x_mm", [
    ("x_mm,y_mm,z_mm,a_deg,b_deg,c_deg\n1,2,3,4,5,6\n", "no pose convention.*# convention",
     {"convention": "kuka"}, 1.0),
    ("x,y,z,qx,qy,qz,qw\n1,2,3,0,0,0,1\n", "no length unit", {"length_unit": "mm"}, 1.0),
    ("# convention: ur\n# length_unit: m\nx,y,z,rx,ry,rz\n1,2,3,0,0,1\n", "no angle unit",
     {"angle_unit": "rad"}, 1000.0),
])
def test_ambiguous_file_is_rejected_naming_what_to_add(tmp_path, text, missing, fix, x_mm):
    f = tmp_path / "poses.csv"
    f.write_text(text)
    with pytest.raises(InputError, match=missing):
        read_poses(f)
    assert read_poses(f, **fix)[0].t_mm[0] == x_mm  # stated by the caller instead


def test_contradictions_and_bad_rows_are_errors(tmp_path):
    f = tmp_path / "c.csv"
    f.write_text("# convention: kuka\nx_m,y_m,z_m,a_deg,b_deg,c_deg\n1,2,3,4,5,6\n")
    assert read_poses(f)[0].t_mm[0] == 1000.0  # the header's metres beat KUKA's native mm
    with pytest.raises(InputError, match="the file says"):
        read_poses(f, length_unit="mm")
    bad = tmp_path / "b.csv"
    bad.write_text("x_mm,y_mm,z_mm,qx,qy,qz,qw\n1,2,3,0,0,0,2\n")
    with pytest.raises(InputError, match="norm"):
        read_poses(bad)
    with pytest.raises(InputError, match="7 comma-separated"):
        parse_pose_row("1,2,3")
    with pytest.raises(InputError, match="unknown pose convention"):
        poses_from_rows([[0] * 6], "staubli", "mm", "deg")


def test_json_keyed_poses_and_inline_row(tmp_path):
    f = tmp_path / "p.json"
    f.write_text('{"length_unit": "mm", "poses": [{"x": 1, "y": 2, "z": 3, "qw": 1, "qx": 0, '
                 '"qy": 0, "qz": 0}]}')
    p = load_flange_pose(str(f))
    np.testing.assert_allclose(p.t_mm, [1, 2, 3])
    q = load_flange_pose("100,200,300,0,0,0.7071067811865476,0.7071067811865476")
    np.testing.assert_allclose(q.R, RZ90, atol=1e-12)


# ------------------------------------------------------------------------------------------
def test_covariance_propagation_matches_monte_carlo():
    rng = np.random.default_rng(0)
    A = Pose(Rotation.from_euler("xyz", [20, -40, 70], degrees=True).as_matrix(),
             [800, -200, 400], "base", "flange")
    B = Pose(Rotation.from_euler("xyz", [-5, 10, 95], degrees=True).as_matrix(),
             [50, 80, 150], "flange", "cam")
    # correlated covariances: scaled rows of a random mixing
    La = np.diag([0.05, 0.08, 0.03, 2e-4, 1e-4, 3e-4]) @ (np.eye(6) + 0.4 * rng.normal(size=(6, 6)))
    Lb = np.diag([0.2, 0.1, 0.3, 5e-4, 8e-4, 2e-4]) @ (np.eye(6) + 0.4 * rng.normal(size=(6, 6)))
    Ca, Cb = La @ La.T, Lb @ Lb.T
    pc = PoseCov(A, Ca) @ PoseCov(B, Cb)
    inv = pc.inverse()
    n = 20000
    da = rng.multivariate_normal(np.zeros(6), Ca, n)
    db = rng.multivariate_normal(np.zeros(6), Cb, n)
    Ra = Rotation.from_rotvec(da[:, 3:]).as_matrix() @ A.R
    Rb = Rotation.from_rotvec(db[:, 3:]).as_matrix() @ B.R
    R = Ra @ Rb
    t = np.einsum("nij,nj->ni", Ra, B.t_mm + db[:, :3]) + A.t_mm + da[:, :3]
    d_ac = np.concatenate([t - pc.pose.t_mm,
                           Rotation.from_matrix(R @ pc.pose.R.T).as_rotvec()], axis=1)
    Ri = np.swapaxes(R, 1, 2)
    ti = -np.einsum("nij,nj->ni", Ri, t)
    Tinv = pc.pose.inverse()
    d_inv = np.concatenate([ti - Tinv.t_mm, Rotation.from_matrix(Ri @ Tinv.R.T).as_rotvec()],
                           axis=1)
    sd = np.sqrt(np.diag(pc.cov))
    np.testing.assert_allclose(np.std(d_ac, axis=0), sd, rtol=0.05)
    np.testing.assert_allclose(np.std(d_inv, axis=0), np.sqrt(np.diag(inv.cov)), rtol=0.05)
    corr = np.corrcoef(d_ac.T)
    pred = pc.cov / np.outer(sd, sd)
    assert np.abs(corr - pred).max() < 0.05
    assert pc.name == "T_base_cam" and inv.name == "T_cam_base"


def test_mismatched_frames_are_refused():
    A = PoseCov.exact(Pose(np.eye(3), [0, 0, 0], "base", "flange"))
    C = PoseCov.exact(Pose(np.eye(3), [0, 0, 0], "cam", "holder"))
    with pytest.raises(InputError, match="frames 'flange' and 'cam' differ"):
        A @ C


def test_own_axes_and_dof_covariances():
    P = Pose.from_euler(10, -20, 30, 1, 2, 600)
    C = np.diag([1.0, 2.0, 3.0, 1e-4, 2e-4, 3e-4])
    np.testing.assert_allclose(cov_to_own_axes(P, cov_from_own_axes(P, C)), C, atol=1e-15)
    # the DOF covariance of one angle maps onto the rotation axis it turns about
    rng = np.random.default_rng(1)
    cov_dof = np.diag([0.01, 0.02, 0.03, 0.1, 0.2, 0.3]) ** 2
    c = cov_from_dof(P, cov_dof)
    samples = rng.multivariate_normal(np.zeros(6), cov_dof, 4000)
    e = P.dof[:3] + samples[:, :3]
    phis = Rotation.from_matrix(rotation_from_euler_deg(e[:, 0], e[:, 1], e[:, 2])
                                @ P.R.T).as_rotvec()
    sd = np.sqrt(np.diag(c[3:, 3:]))
    np.testing.assert_allclose(np.cov(phis.T) / np.outer(sd, sd), c[3:, 3:] / np.outer(sd, sd),
                               atol=0.08)


# ---- pose files as controllers, ROS and ViSP write them (issue 29) ---------------------------
def test_yaskawa_and_visp_conventions_against_hand_products():
    # Yaskawa Rx, Ry, Rz = 10, 20, 30: Rz(30) Ry(20) Rx(10) (fixed X, then Y, then Z)
    expect = _axis_rot(2, 30) @ _axis_rot(1, 20) @ _axis_rot(0, 10)
    y = poses_from_rows([[100, 200, 300, 10, 20, 30]], "yaskawa")[0]
    np.testing.assert_allclose(y.R, expect, atol=1e-12)
    np.testing.assert_allclose(y.t_mm, [100, 200, 300])
    # ViSP theta-u in metres and radians: a quarter turn about z
    v = poses_from_rows([[0.1, 0.2, 0.3, 0, 0, math.pi / 2]], "visp")[0]
    np.testing.assert_allclose(v.R, RZ90, atol=1e-12)
    np.testing.assert_allclose(v.t_mm, [100, 200, 300], atol=1e-9)


def _ros_text(t_m, q_xyzw) -> str:
    return "".join(f"{k}: {v!r}\n" for k, v in zip(("x", "y", "z", "qx", "qy", "qz", "qw"),
                                                    list(t_m) + list(q_xyzw)))


def test_ros_yaml_single_list_and_geometry_msgs_forms(tmp_path):
    from cutterpose.robot.pose_files import read_pose_file

    f = tmp_path / "3.yaml"  # robot_cal_tools' poses/N.yaml
    f.write_text(_ros_text([0.1, 0.2, 0.3], [0, 0, H, H]))
    s = read_pose_file(f)
    assert s.names == ["3"] and s.formats == ["ros-yaml"]
    np.testing.assert_allclose(s.poses[0].R, RZ90, atol=1e-12)
    np.testing.assert_allclose(s.poses[0].t_mm, [100, 200, 300], atol=1e-9)
    lst = tmp_path / "cell.yaml"
    lst.write_text("poses:\n"
                   "  - {position: {x: 0.1, y: 0.2, z: 0.3}, orientation: {x: 0, y: 0, z: "
                   f"{H!r}, w: {H!r}}}}}\n"
                   "  - transform: {translation: {x: 1.0, y: 0, z: 0}, rotation: {x: 0, y: 0, "
                   "z: 0, w: 1}}\n")
    s = read_pose_file(lst)
    assert s.names == ["cell:0", "cell:1"]
    np.testing.assert_allclose(s.poses[0].R, RZ90, atol=1e-12)
    np.testing.assert_allclose(s.poses[1].t_mm, [1000, 0, 0])


def test_visp_pose_vector_file(tmp_path):
    from cutterpose.robot.pose_files import read_pose_file

    f = tmp_path / "pose_fPe_2.yaml"
    f.write_text(f"rows: 6\ncols: 1\ndata:\n  - [0.1]\n  - [0.2]\n  - [0.3]\n  - [0]\n  - [0]\n"
                 f"  - [{math.pi / 2!r}]\n")
    s = read_pose_file(f)
    assert s.formats == ["visp-yaml"]
    np.testing.assert_allclose(s.poses[0].R, RZ90, atol=1e-12)
    np.testing.assert_allclose(s.poses[0].t_mm, [100, 200, 300], atol=1e-9)
    f.write_text("rows: 6\ncols: 1\ndata:\n  - [0.1]\n  - [0.2]\n")
    with pytest.raises(InputError, match="6 one-number rows"):
        read_pose_file(f)


JBI = """/JOB
//NAME HANDEYE
//POS
///NPOS 2,0,0,0,0,0
///TOOL 0
///POSTYPE ROBOT
///RECTAN
///RCONF 0,0,0,0,0,0,0,0
C00000=100.000,200.000,300.000,0.0000,0.0000,90.0000
C00001=1012.500,-230.100,845.000,10.0000,20.0000,30.0000
//INST
///DATE 2026/12/03 12:00
NOP
MOVJ C00000 VJ=10.00
END
"""


def test_yaskawa_job_file_and_its_refusals(tmp_path):
    from cutterpose.robot.pose_files import read_pose_file

    f = tmp_path / "CELL.JBI"
    f.write_text(JBI)
    s = read_pose_file(f)
    assert s.names == ["CELL:C00000", "CELL:C00001"]
    np.testing.assert_allclose(s.poses[0].R, RZ90, atol=1e-12)
    np.testing.assert_allclose(s.poses[1].R, _axis_rot(2, 30) @ _axis_rot(1, 20)
                               @ _axis_rot(0, 10), atol=1e-12)
    f.write_text(JBI.replace("///RECTAN", "///PULSE"))
    with pytest.raises(InputError, match="joint pulses"):
        read_pose_file(f)
    f.write_text(JBI.replace("30.0000\n", "30.0000\n///TOOL 2\n"))
    with pytest.raises(InputError, match="different tools"):
        read_pose_file(f)
    f.write_text(JBI.replace("C00001=1012.500,", "C00001="))
    with pytest.raises(InputError, match="line 10: C00001 has 5 values"):
        read_pose_file(f)
    # a Yaskawa CSV (one station per file works the same)
    c = tmp_path / "y.csv"
    c.write_text("x,y,z,rx,ry,rz\n100,200,300,0,0,90\n")
    np.testing.assert_allclose(read_pose_file(c, "yaskawa").poses[0].R, RZ90, atol=1e-12)


def test_folder_of_station_files_pairs_by_number(tmp_path):
    from cutterpose.robot.pose_files import pair_with_images, read_pose_set

    for k in (0, 2, 10):
        (tmp_path / f"{k}.yaml").write_text(_ros_text([0.5 + k / 1000, 0, 0.8], [0, 0, 0, 1]))
    s = read_pose_set(tmp_path)
    assert s.names == ["0", "2", "10"]  # natural order, not 0, 10, 2
    np.testing.assert_allclose([p.t_mm[0] for p in s.poses], [500, 502, 510])
    # images sorted by name (0, 10, 2) get their own station's pose
    assert pair_with_images(["0.png", "10.png", "2.png"], s.names) == [0, 2, 1]
    assert pair_with_images(["image-1.png", "image-2.png"],
                            ["pose_fPe_2", "pose_fPe_1"]) == [1, 0]
    assert pair_with_images(["a.png", "b.png"], ["p", "q"]) == [0, 1]  # no numbers: in order
    with pytest.raises(InputError, match="3 images but 2 robot poses"):
        pair_with_images(["a.png", "b.png", "c.png"], ["p", "q"])


@pytest.mark.parametrize("name, text, match", [
    ("r.csv", "# convention: kuka\nx,y,z,a,b,c\n1,2,3,4,5,6\n1,2,3,4,5\n", "row 2 has 5 values"),
    ("q.yaml", "x: 0.1\ny: 0\nz: 0\nqx: 0\nqy: 0\nqz: 0\nqw: 2\n", "norm"),
    ("m.yaml", "x: 0.1\ny: 0\nz: 0\nqx: 0\nqy: 0\nqz: 0\n", "missing 'qw'"),
    ("s.yaml", "x: 0.1\ny: zero\nz: 0\nqx: 0\nqy: 0\nqz: 0\nqw: 1\n", "'y' is not a number"),
    ("b.yaml", "x: [0.1\n", "not valid YAML"),
    ("d.csv", "# convention: ur\n# length_unit: m\n# angle_unit: rad\nx,y,z,rx,ry,rz\n"
     "1,0,0,0,0,90\n", "degrees read as radians"),
    ("e.json", "[1, 2]", "no pose convention"),
])
def test_malformed_pose_files_are_one_line_errors(tmp_path, name, text, match):
    from cutterpose.robot.pose_files import read_pose_set

    f = tmp_path / name
    f.write_text(text)
    with pytest.raises(InputError, match=match) as e:
        read_pose_set(f)
    assert "\n" not in str(e.value)


def test_flange_positions_in_the_wrong_unit_are_refused():
    from cutterpose.robot.pose_files import check_flange_units

    metres_as_mm = [Pose(np.eye(3), [0.7, 0.0, 0.85], "base", "flange")]
    with pytest.raises(InputError, match="metres read as mm"):
        check_flange_units(metres_as_mm)
    mm_as_metres = [Pose(np.eye(3), [700e3, 0.0, 850e3], "base", "flange")]
    with pytest.raises(InputError, match="mm read as metres"):
        check_flange_units(mm_as_metres)
    check_flange_units([Pose(np.eye(3), [700.0, 0.0, 850.0], "base", "flange")])


def test_robot_cal_tools_data_set_file_names_poses_after_their_images():
    from pathlib import Path

    from cutterpose.robot.pose_files import pair_with_images, read_pose_set

    data = Path(__file__).parent / "data" / "real" / "rct_10x10"
    s = read_pose_set(data / "cal_data.yaml")
    folder = read_pose_set(data / "poses")
    assert sorted(s.names, key=int) == [str(k) for k in range(15)]
    for name, p in zip(s.names, s.poses):
        q = folder.poses[folder.names.index(name)]
        np.testing.assert_allclose(p.t_mm, q.t_mm)
        np.testing.assert_allclose(p.R, q.R)
    # metres read as such: the flange ~0.7-1 m from the base
    assert 500 < np.linalg.norm(s.poses[0].t_mm) < 1500
    images = sorted(f"{k}.png" for k in range(15))  # 0, 1, 10, 11, ..., 2, ...
    assert [s.names[j] + ".png" for j in pair_with_images(images, s.names)] == images
