"""Hand-eye calibration in the simulated robot cell (issue 11).

Plate images go through a quarter-resolution Table 1 camera (as in test_calibration.py), so the
accuracy figures here are looser than the full-resolution ones of docs/RESULTS.md
(benchmarks/robot_cell.py).
"""

from __future__ import annotations

import json

import numpy as np
import pytest
from scipy.spatial.transform import Rotation
from typer.testing import CliRunner

from cutterpose.calibration.handeye import (
    calibrate_handeye,
    load_handeye,
    save_handeye,
)
from cutterpose.calibration.handeye_starts import NUMPY_METHODS, numpy_start
from cutterpose.calibration.intrinsics import detect_plate
from cutterpose.cli import app
from cutterpose.errors import DegenerateInputError, HandEyeFileError, InputError
from cutterpose.geometry.pose import Pose, geodesic_deg
from cutterpose.robot.cell import RobotCell


@pytest.fixture(scope="module")
def cell_data(cam_quarter):
    """Ten stations of a random cell: true and reported flange poses, detected circles."""
    cell = RobotCell.random(cam_quarter, seed=3)
    true = cell.plate_stations(10, seed=3)
    reported = cell.report(true, np.random.default_rng(4))
    rng = np.random.default_rng(5)
    pts = np.stack([detect_plate(cell.plate_image(a, rng), cell.plate).points_px for a in true])
    return cell, true, reported, pts


def _err(X: Pose, truth: Pose) -> tuple[float, float]:
    return float(np.linalg.norm(X.t_mm - truth.t_mm)), float(geodesic_deg(X.R, truth.R))


def test_refined_handeye_is_close_to_the_truth(cell_data):
    cell, _, reported, pts = cell_data
    r = calibrate_handeye(reported, pts, cell.camera, cell.plate)
    e_mm, e_deg = _err(r.T_flange_cam, cell.T_flange_cam)
    assert e_mm < 0.15 and e_deg < 0.02, (e_mm, e_deg)
    assert r.ok and r.verdict.startswith("good")
    assert all(s.used for s in r.stations)
    # the stated uncertainty is of the size of the error (neither 10x too small nor too large)
    sd_mm = np.sqrt(np.trace(r.handeye.covariance[:3, :3]))
    assert e_mm < 5 * sd_mm and sd_mm < 0.2
    # base -> plate is found too
    assert _err(r.T_base_plate, cell.T_base_plate)[0] < 0.3


def test_corrupted_station_is_distrusted(cell_data):
    cell, _, reported, pts = cell_data
    bad = list(reported)
    bad[4] = Pose(bad[4].R, bad[4].t_mm + [3.0, 4.0, 0.0], "base", "flange")  # 5 mm off
    r = calibrate_handeye(bad, pts, cell.camera, cell.plate)
    st = r.stations[4]
    assert not st.used and "outlier" in st.distrust and 4.0 < st.position_mm < 6.0
    assert sum(not s.used for s in r.stations) <= 2
    assert _err(r.T_flange_cam, cell.T_flange_cam)[0] < 0.2


def test_degenerate_stations_are_typed_errors(cell_data):
    cell, _, reported, pts = cell_data
    with pytest.raises(DegenerateInputError, match="at least 3 stations"):
        calibrate_handeye(reported[:2], pts[:2], cell.camera, cell.plate)
    # the same orientation everywhere: translations only
    still = [Pose(reported[0].R, a.t_mm, "base", "flange") for a in reported]
    with pytest.raises(DegenerateInputError, match="do not rotate"):
        calibrate_handeye(still, pts, cell.camera, cell.plate)
    # rotations about one axis only
    R0 = reported[0].R
    spin = [Pose(R0 @ Rotation.from_euler("z", 20 * k, degrees=True).as_matrix(), a.t_mm,
                 "base", "flange") for k, a in enumerate(reported)]
    with pytest.raises(DegenerateInputError, match="about one axis"):
        calibrate_handeye(spin, pts, cell.camera, cell.plate)


@pytest.mark.parametrize("method", NUMPY_METHODS)
def test_numpy_starts_are_exact_on_exact_data(method, cam_quarter):
    cell = RobotCell.random(cam_quarter, seed=8)
    A = cell.plate_stations(6, seed=8)
    B = [cell.camera_view(a, cell.T_base_plate) for a in A]
    X, Y = numpy_start(method, A, B)
    assert _err(X, cell.T_flange_cam)[0] < 1e-6 and _err(X, cell.T_flange_cam)[1] < 1e-7
    assert _err(Y, cell.T_base_plate)[0] < 1e-6


def test_handeye_file_round_trip_and_errors(tmp_path, cell_data):
    cell, _, reported, pts = cell_data
    r = calibrate_handeye(reported, pts, cell.camera, cell.plate)
    path = save_handeye(r, tmp_path / "handeye.json")
    he = load_handeye(path)
    np.testing.assert_allclose(he.T_flange_cam.matrix, r.T_flange_cam.matrix)
    np.testing.assert_allclose(he.covariance, r.handeye.covariance)
    assert he.T_flange_cam.name == "T_flange_cam"
    doc = json.loads(path.read_text())
    del doc["covariance"]
    (tmp_path / "bad.json").write_text(json.dumps(doc))
    with pytest.raises(HandEyeFileError, match="covariance"):
        load_handeye(tmp_path / "bad.json")
    doc["covariance"] = np.eye(6).tolist()
    doc["T_flange_cam"][3] = [0, 0, 1, 1]
    (tmp_path / "bad.json").write_text(json.dumps(doc))
    with pytest.raises(HandEyeFileError, match="T_flange_cam"):
        load_handeye(tmp_path / "bad.json")


def test_cli_robot_cell_and_handeye(tmp_path, cam_quarter):
    runner = CliRunner()
    cam_file = tmp_path / "cam.json"
    cam_file.write_text(json.dumps(cam_quarter.to_dict()))
    cell_dir = tmp_path / "cell"
    res = runner.invoke(app, ["render-plate", "--robot-cell", "--count", "6", "--seed", "2",
                              "--camera", str(cam_file), "--out", str(cell_dir)])
    assert res.exit_code == 0, res.output
    assert (cell_dir / "robot_poses.csv").read_text().startswith("x_mm,y_mm,z_mm,qx,qy,qz,qw")
    out = tmp_path / "handeye.json"
    res = runner.invoke(app, ["handeye", str(cell_dir), "--robot-poses",
                              str(cell_dir / "robot_poses.csv"), "--camera", str(cam_file),
                              "--plate", str(cell_dir / "plate.json"), "--out", str(out)])
    assert res.exit_code in (0, 3), res.output
    truth = json.loads((cell_dir / "cell_truth.json").read_text())
    X = load_handeye(out).T_flange_cam
    assert np.linalg.norm(X.t_mm - np.asarray(truth["T_flange_cam"])[:3, 3]) < 0.5
    assert "station" in res.output and "T_flange_cam" in res.output
    # a pose file with one pose too few is refused with a one-line message
    lines = (cell_dir / "robot_poses.csv").read_text().splitlines()
    (tmp_path / "short.csv").write_text("\n".join(lines[:-1]) + "\n")
    res = runner.invoke(app, ["handeye", str(cell_dir), "--robot-poses",
                              str(tmp_path / "short.csv"), "--camera", str(cam_file),
                              "--out", str(out)])
    assert res.exit_code == 2 and "6 images but 5 robot poses" in res.output


def test_cli_render_plate_at_given_poses(tmp_path, cam_quarter):
    from cutterpose.robot.poses import write_poses

    cam_file = tmp_path / "cam.json"
    cam_file.write_text(json.dumps(cam_quarter.to_dict()))
    pose = Pose.from_euler(10, -15, 30, 20, -10, 550, to_frame="cam", from_frame="plate")
    write_poses(tmp_path / "views.csv", [pose], "kuka")
    res = CliRunner().invoke(app, ["render-plate", "--plate-poses", str(tmp_path / "views.csv"),
                                   "--camera", str(cam_file), "--out", str(tmp_path / "p")])
    assert res.exit_code == 0, res.output
    truth = json.loads((tmp_path / "p" / "truth.json").read_text())
    assert len(truth["images"]) == 1
    np.testing.assert_allclose(truth["images"][0]["t_cam_plate_mm"], pose.t_mm, atol=1e-9)


# ---- maximum likelihood under plate and robot noise (simulated centres, no rendering) -------
def _own_error(X: Pose, truth: Pose) -> np.ndarray:
    """(dt [mm], dphi [rad] about the cam frame's own axes): PROTOCOL's covariance order."""
    return np.concatenate([X.t_mm - truth.t_mm,
                           Rotation.from_matrix(truth.R.T @ X.R).as_rotvec()])


def test_ml_refinements_recover_the_truth_without_noise(cam_quarter):
    from cutterpose.calibration.handeye import bundle_adjust_handeye

    cell = RobotCell.random(cam_quarter, seed=6)
    true = cell.plate_stations(10, seed=6)
    pts = cell.plate_points(true)
    r = calibrate_handeye(true, pts, cell.camera, cell.plate)
    assert _err(r.T_flange_cam, cell.T_flange_cam)[0] < 1e-4
    assert _err(r.T_flange_cam, cell.T_flange_cam)[1] < 1e-5
    # the bundle adjustment from a start 0.5 mm / 0.1 deg off
    X0 = Pose(Rotation.from_euler("xyz", [0.1, -0.05, 0.05], degrees=True).as_matrix()
              @ cell.T_flange_cam.R, cell.T_flange_cam.t_mm + [0.3, -0.3, 0.3], "flange", "cam")
    ba = bundle_adjust_handeye(true, pts, cell.camera, X0, cell.T_base_plate, plate=cell.plate,
                               sigma_px=0.02, repeatability_mm=0.03, repeatability_deg=0.005)
    assert _err(ba.T_flange_cam, cell.T_flange_cam)[0] < 1e-4
    assert _err(ba.T_flange_cam, cell.T_flange_cam)[1] < 1e-5
    assert _err(ba.T_base_plate, cell.T_base_plate)[0] < 1e-4
    assert np.abs(ba.flange_corrections).max() < 1e-5
    # the calibration's bundle option gives the same transform; an unknown option is refused
    rb = calibrate_handeye(true, pts, cell.camera, cell.plate, refinement="bundle")
    assert _err(rb.T_flange_cam, cell.T_flange_cam)[0] < 1e-4
    with pytest.raises(InputError, match="refinement"):
        calibrate_handeye(true, pts, cell.camera, cell.plate, refinement="fancy")


def test_ml_covariance_matches_monte_carlo(cam_quarter):
    """Fixed stations, robot noise 0.03 mm / 0.005 deg and plate noise redrawn: the stated
    covariance of T_flange_cam matches the scatter of the estimates (normalised squared error
    ~ chi-square with 6 dof), and the explicit bundle adjustment agrees with the refinement."""
    from cutterpose.calibration.handeye import bundle_adjust_handeye

    cell = RobotCell.random(cam_quarter, seed=2)
    true = cell.plate_stations(10, seed=2)
    rng = np.random.default_rng(7)
    errs, nees, covs = [], [], []
    for k in range(30):
        reported = cell.report(true, rng)
        pts = cell.plate_points(true, rng, 0.03)
        r = calibrate_handeye(reported, pts, cell.camera, cell.plate)
        e = _own_error(r.T_flange_cam, cell.T_flange_cam)
        errs.append(e)
        covs.append(r.handeye.covariance)
        nees.append(e @ np.linalg.solve(r.handeye.covariance, e))
        if k == 0:
            ba = bundle_adjust_handeye(reported, pts, cell.camera, *r.starts["park-numpy"],
                                       plate=cell.plate, sigma_px=r.sigma_px,
                                       repeatability_mm=0.03, repeatability_deg=0.005)
            sd = np.sqrt(np.diag(r.handeye.covariance))
            np.testing.assert_allclose(_own_error(ba.T_flange_cam, r.T_flange_cam), 0,
                                       atol=0.05 * sd.max())
            np.testing.assert_allclose(np.sqrt(np.diag(ba.cov_flange_cam)), sd, rtol=0.02)
    E, C = np.array(errs), np.mean(covs, axis=0)
    assert 3.8 < np.mean(nees) < 8.5, np.mean(nees)  # E = 6; 30 draws: sd 0.63
    emp = E.T @ E / len(E)
    for blk in (slice(0, 3), slice(3, 6)):
        ratio = np.trace(emp[blk, blk]) / np.trace(C[blk, blk])
        assert 0.5 < ratio < 1.8, ratio
