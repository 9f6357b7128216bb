"""Hand-eye calibration with any target (issue 29): a symmetric grid whose point order flips
between stations, and the target's base-frame spread against the robot's stated error."""

from __future__ import annotations

import numpy as np
import pytest

from cutterpose.calibration.handeye import calibrate_handeye
from cutterpose.calibration.handeye_problem import TargetModel
from cutterpose.geometry.pose import geodesic_deg
from cutterpose.robot.cell import RobotCell, perturb_pose


@pytest.fixture(scope="module")
def cell12(cam_quarter):
    cell = RobotCell.random(cam_quarter, seed=6)
    true = cell.plate_stations(12, seed=6)
    rng = np.random.default_rng(1)
    return cell, true, cell.report(true, rng), cell.plate_points(true, rng, 0.03)


def _err(r, cell):
    return (float(np.linalg.norm(r.T_flange_cam.t_mm - cell.T_flange_cam.t_mm)),
            float(geodesic_deg(r.T_flange_cam.R, cell.T_flange_cam.R)))


def test_plain_grid_with_half_the_stations_turned_180_deg(cell12):
    """A grid without orientation mark: the detector's order is reversed on every second
    station. Resolved from the robot motion, the calibration equals the one of the correctly
    ordered points; unresolved, it is ruined."""
    cell, _, reported, pts = cell12
    N = pts.shape[1]
    turned = pts.copy()
    flip = np.arange(len(pts)) % 2 == 1
    turned[flip] = turned[flip][:, ::-1]
    plain = TargetModel(cell.plate.points_mm, [np.arange(N)[::-1].copy()], cell.plate, "plain")
    ref = calibrate_handeye(reported, pts, cell.camera, cell.plate)
    r = calibrate_handeye(reported, turned, cell.camera, plain)
    assert _err(ref, cell)[0] < 0.1
    np.testing.assert_allclose(r.T_flange_cam.t_mm, ref.T_flange_cam.t_mm, atol=1e-6)
    assert geodesic_deg(r.T_flange_cam.R, ref.T_flange_cam.R) < 1e-6
    # the first station keeps the detector's order; exactly the turned ones are re-read
    assert [s.order != "as detected" for s in r.stations] == list(flip)
    assert min(s.order_margin for s in r.stations) > 100
    assert any("read in a turned order" in n for n in r.notes)
    bad = calibrate_handeye(reported, turned, cell.camera, cell.plate)  # order taken as given
    assert _err(bad, cell)[0] > 50 and not bad.ok


def test_plate_spread_against_the_robots_stated_error(cell12):
    cell, true, reported, pts = cell12
    r = calibrate_handeye(reported, pts, cell.camera, cell.plate)
    sp = r.plate_spread
    assert sp["consistent"], sp["verdict"]
    assert 0.5 < sp["position_rms_mm"] / sp["explained_position_rms_mm"] < 1.5
    # a robot 20x worse than stated: flagged, and the estimate of its error is of that size
    rng = np.random.default_rng(9)
    worse = [perturb_pose(p, rng, 0.6, 0.1) for p in true]
    w = calibrate_handeye(worse, pts, cell.camera, cell.plate)
    sw = w.plate_spread
    assert not sw["consistent"] and "explain" in sw["verdict"]
    assert 0.05 < sw["robot_error_estimate_deg"] < 0.2
    assert w.to_dict()["plate_spread"]["verdict"] == sw["verdict"]
