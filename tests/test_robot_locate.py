"""The holder in the base frame, its covariance, the grasp verdict and the JSON (issue 11)."""

from __future__ import annotations

import json
import math
from types import SimpleNamespace

import cv2
import numpy as np
import pytest
from typer.testing import CliRunner

from cutterpose.calibration.handeye import HandEye, save_handeye
from cutterpose.cli import app
from cutterpose.errors import HolderModelError, InputError
from cutterpose.geometry.camera_files import save_camera
from cutterpose.geometry.holder import default_holder, holder_from_dict
from cutterpose.geometry.pose import Pose, geodesic_deg
from cutterpose.pipeline import Quality, QualityLimits, measure
from cutterpose.render.analytic import render_holder
from cutterpose.robot import GraspTolerance, RobotAccuracy, locate, measurement_covariance
from cutterpose.robot.cell import RobotCell
from cutterpose.robot.poses import write_poses

HOLDER = default_holder()
A = Pose.from_euler(10, -20, 30, 1200, -100, 700, to_frame="base", from_frame="flange")
X = Pose.from_euler(0.5, -1, 90, 80, -40, 150, to_frame="flange", from_frame="cam")
POSE = Pose.from_euler(2, -3, 4, 8, -6, 612)


def _meas(std, ok=True, pose=POSE, reason=""):
    return SimpleNamespace(pose=pose, std_dof=np.asarray(std, float), ok=ok,
                           quality=Quality(ok, reason))


def _he(sd_mm=0.02, sd_rad=5e-5):
    return HandEye(X, Pose(np.eye(3), [1000, 0, 0], "base", "plate"),
                   np.diag([sd_mm ** 2] * 3 + [sd_rad ** 2] * 3))


def test_chain_and_covariance_of_the_grasp(cam_t1):
    m = _meas([0.01, 0.01, 0.01, 0.02, 0.02, 0.05])
    r = locate(m, _he(), A, RobotAccuracy(0.03, 0.005), camera=cam_t1, holder=HOLDER)
    expect = A @ X @ POSE.with_frames("cam", "holder")
    np.testing.assert_allclose(r.T_base_holder.pose.matrix, expect.matrix, atol=1e-9)
    assert r.T_base_grasp.name == "T_base_grasp" and r.T_base_holder.name == "T_base_holder"
    # the measurement's own DOF covariance keeps the reported std on its diagonal
    C = measurement_covariance(m, cam_t1, HOLDER)
    np.testing.assert_allclose(np.sqrt(np.diag(C)), m.std_dof, rtol=1e-12)
    assert abs(C[1, 3] / math.sqrt(C[1, 1] * C[3, 3])) > 0.5  # beta and X are coupled
    # the three sources add up, each positive
    sh = r.grasp.shares["position"]
    assert set(sh) == {"measurement", "hand-eye", "robot"} and abs(sum(sh.values()) - 1) < 1e-6
    assert r.grasp.verdict == "grasp" and r.grasp.position_3sigma_mm < 1.0


def test_depth_uncertainty_asks_to_move_closer(cam_t1):
    r = locate(_meas([0.01, 0.01, 0.01, 0.02, 0.02, 0.6]), _he(), A, camera=cam_t1,
               holder=HOLDER)
    v = r.grasp
    assert v.verdict == "retake" and v.position_3sigma_mm > 1.0
    assert v.reason.startswith("position 3-sigma") and "camera" in v.reason
    assert "closer" in v.hint and v.shares["position"]["measurement"] > 0.9


def test_angle_tolerance_from_the_cutter_radius():
    tol = GraspTolerance()
    assert tol.angle_limit_deg == pytest.approx(math.degrees(1.0 / 216.0))
    assert GraspTolerance(2.0).angle_limit_deg == pytest.approx(2 * tol.angle_limit_deg)


def test_handeye_uncertainty_asks_for_a_new_calibration(cam_t1):
    r = locate(_meas([0.005] * 3 + [0.01] * 3), _he(sd_mm=0.5, sd_rad=0.002), A,
               camera=cam_t1, holder=HOLDER)
    assert r.grasp.verdict == "retake" and "hand-eye" in r.grasp.hint


def test_refused_measurement_is_never_grasp(cam_t1):
    m = _meas([0.001] * 6, ok=False, reason="corner residual RMS 2.1 px > 1.5 px")
    r = locate(m, _he(), A, camera=cam_t1, holder=HOLDER)
    assert r.grasp.verdict == "retake" and "refused" in r.grasp.reason
    assert "lower edge" in r.grasp.hint
    none = locate(_meas([np.nan] * 6, ok=False, pose=None, reason="20 segments not found"),
                  _he(), A, camera=cam_t1, holder=HOLDER)
    assert none.grasp.verdict == "retake" and none.T_base_holder is None
    assert json.loads(json.dumps(none.to_dict()))["T_base_holder"] is None


def test_wrong_frames_are_refused(cam_t1):
    with pytest.raises(InputError, match="T_base_flange"):
        locate(_meas([0.01] * 6), _he(), A.inverse(), camera=cam_t1, holder=HOLDER)


def test_ros_json_fields(cam_t1):
    d = locate(_meas([0.01, 0.01, 0.01, 0.02, 0.02, 0.05]), _he(), A, camera=cam_t1,
               holder=HOLDER).to_dict()
    d = json.loads(json.dumps(d))
    g = d["poses_ros"]["base_grasp"]
    assert (g["frame_id"], g["child_frame_id"]) == ("base", "grasp")
    np.testing.assert_allclose(np.array(g["position_m"]) * 1000, g["position_mm"])
    assert abs(np.linalg.norm(g["orientation_xyzw"]) - 1) < 1e-12
    C_ros = np.array(g["covariance_ros"]).reshape(6, 6)
    C_mm = np.array(g["covariance_mm_rad"]).reshape(6, 6)
    np.testing.assert_allclose(C_ros[:3, :3] * 1e6, C_mm[:3, :3])
    np.testing.assert_allclose(C_ros[3:, 3:], C_mm[3:, 3:])
    np.testing.assert_allclose(np.array(d["T_base_holder"]), np.array(d["T_base_grasp"]))
    assert {"verdict", "reason", "position_3sigma_mm", "angle_3sigma_deg"} <= set(d["grasp"])


def test_holder_file_grasp_frame():
    d = HOLDER.to_dict() | {"grasp_frame": {"position_mm": [0, 0, 40], "euler_deg": [0, 0, 90]}}
    h = holder_from_dict(d)
    assert h.grasp_frame.name == "T_holder_grasp"
    np.testing.assert_allclose(h.grasp_frame.t_mm, [0, 0, 40])
    assert holder_from_dict(h.to_dict()).grasp_frame.t_mm[2] == 40
    with pytest.raises(HolderModelError, match="grasp_frame"):
        holder_from_dict(HOLDER.to_dict() | {"grasp_frame": {"R": 1}})


def test_measure_in_the_base_frame_end_to_end(tmp_path, cam_quarter):
    """A rendered holder at a known base pose, seen from a station of the simulated cell."""
    cell = RobotCell(cam_quarter)
    T_bh = Pose(np.column_stack([[0, 1.0, 0], [0, 0, 1.0], [1.0, 0, 0]]), [1500, 100, 800],
                "base", "holder")
    true_A = cell.holder_stations(T_bh, 1, seed=1)[0]
    rep = cell.report([true_A], np.random.default_rng(0))[0]
    img = render_holder(cell.camera_view(true_A, T_bh), cam_quarter, HOLDER, "easy", seed=3)
    he = HandEye(cell.T_flange_cam, cell.T_base_plate, np.diag([0.02 ** 2] * 3 + [4e-5 ** 2] * 3))
    # a quarter-resolution camera cannot resolve the edge's band (1 px per mm): the frames are
    # what this test is about, so the corner method
    m = measure(img.image, cam_quarter, HOLDER, method="dm+", handeye=he, T_base_flange=rep,
                robot_accuracy=RobotAccuracy(0.03, 0.005), limits=QualityLimits(edge_break_mm=0))
    assert m.ok, m.quality.reason
    err = np.linalg.norm(m.robot.T_base_grasp.pose.t_mm - T_bh.t_mm)
    assert err < 3.0 and geodesic_deg(m.robot.T_base_holder.pose.R, T_bh.R) < 0.5
    assert "T_base_grasp" in m.to_dict()
    # the same through the command line, flange pose inline
    save_camera(cam_quarter, tmp_path / "cam.json")
    save_handeye(he, tmp_path / "he.json")
    cv2.imwrite(str(tmp_path / "img.png"), img.image)
    row = ",".join(str(v) for v in write_poses(tmp_path / "a.csv", [rep]).read_text()
                   .splitlines()[1].split(","))
    res = CliRunner().invoke(app, ["measure", str(tmp_path / "img.png"), "--camera",
                                   str(tmp_path / "cam.json"), "--handeye",
                                   str(tmp_path / "he.json"), "--flange-pose", row, "--json",
                                   "--method", "dm+", "--edge-break-mm", "0"])
    assert res.exit_code in (0, 4), res.output
    d = json.loads(res.output.splitlines()[0])
    np.testing.assert_allclose(np.array(d["T_base_holder"])[:3, 3],
                               m.robot.T_base_holder.pose.t_mm, atol=1e-6)
    assert d["grasp"]["verdict"] in ("grasp", "retake")
    res = CliRunner().invoke(app, ["measure", str(tmp_path / "img.png"), "--camera",
                                   str(tmp_path / "cam.json"), "--handeye",
                                   str(tmp_path / "he.json")])
    assert res.exit_code == 2 and "--flange-pose" in res.output


def test_render_set_from_robot_stations(tmp_path, cam_quarter):
    """render-set --flange-poses: one image per station of a holder at a known base pose,
    truth.json holding T_cam_holder = T_flange_cam^-1 T_base_flange^-1 T_base_holder."""
    cell = RobotCell(cam_quarter)
    T_bh = Pose(np.column_stack([[0, 1.0, 0], [0, 0, 1.0], [1.0, 0, 0]]), [1500, 100, 800],
                "base", "holder")
    stations = cell.holder_stations(T_bh, 3, seed=2)
    he = HandEye(cell.T_flange_cam, cell.T_base_plate, np.diag([0.02 ** 2] * 3 + [4e-5 ** 2] * 3))
    save_camera(cam_quarter, tmp_path / "cam.json")
    save_handeye(he, tmp_path / "he.json")
    write_poses(tmp_path / "stations.csv", stations)
    write_poses(tmp_path / "holder.csv", [T_bh])
    out = tmp_path / "set"
    res = CliRunner().invoke(app, ["render-set", "--out", str(out), "--camera",
                                   str(tmp_path / "cam.json"), "--preset", "easy",
                                   "--flange-poses", str(tmp_path / "stations.csv"),
                                   "--handeye", str(tmp_path / "he.json"),
                                   "--holder-base-pose", str(tmp_path / "holder.csv")])
    assert res.exit_code == 0, res.output
    truth = json.loads((out / "truth.json").read_text())
    assert len(truth["images"]) == 3
    for e, A in zip(truth["images"], stations):
        want = cell.T_flange_cam.inverse() @ A.inverse() @ T_bh
        np.testing.assert_allclose(e["t_cam_holder_mm"], want.t_mm, atol=1e-6)
        assert (out / e["file"]).is_file()
    res = CliRunner().invoke(app, ["render-set", "--out", str(out), "--flange-poses",
                                   str(tmp_path / "stations.csv")])
    assert res.exit_code == 2 and "--handeye" in res.output
