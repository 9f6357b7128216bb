"""Every target kind rendered through the sensor model, detected and calibrated (issue 29).

No real photographs of light circles, asymmetric grids, chessboards or ChArUco boards are in
the repository; these kinds are rendered by ``render_plate`` (exact perspective and lens
distortion, defocus and sensor noise of the holder renderer) through a 640 x 480 camera with
barrel distortion, which keeps the tests fast.
"""

from __future__ import annotations

import json

import numpy as np
import pytest
from typer.testing import CliRunner

from cutterpose.calibration.plate import render_plate, sample_plate_poses
from cutterpose.calibration.target_calibration import TargetView, calibrate_target
from cutterpose.calibration.targets import target_from_spec
from cutterpose.cli import app
from cutterpose.geometry.camera import OpenCVCamera
from cutterpose.geometry.pose import Pose

CAM = OpenCVCamera(np.array([[620.0, 0, 322.5], [0, 618.0, 236.0], [0, 0, 1]]),
                   np.array([-0.12, 0.08, 0.0, 0.0, 0.0]), (640, 480))


def distances(t):
    x0, x1, y0, y1 = t.bounds_mm
    e = max(x1 - x0, y1 - y0)
    return CAM.focal_px * e / (0.9 * 640), CAM.focal_px * e / (0.5 * 640)


def render_views(spec, count, seed=3):
    t = target_from_spec(spec)
    poses = sample_plate_poses(CAM, count, t, distance_mm=distances(t), seed=seed)
    imgs = [render_plate(CAM, p, t, rng=np.random.default_rng(k)) for k, p in enumerate(poses)]
    return t, poses, imgs


KINDS = [("circles:7x6:20:light", 180), ("circles:6x6:20:origin-dot", 0),
         ("circles:7x5:20:light:origin-dot", 0), ("acircles:4x11:12", 0),
         ("acircles:4x11:12:light", 0), ("chessboard:9x6:20", 0), ("chessboard:8x6:20", 180),
         ("charuco:7x9:20:15:DICT_5X5_100", 0)]


@pytest.mark.parametrize("spec, ambiguity", KINDS)
def test_rendered_kind_is_detected_in_order_and_calibrates(spec, ambiguity):
    # ChArUco corners sit 4-6 px from the markers here, which limits their precision
    # (0.06-0.13 px RMS against 0.03-0.06 px for chessboard corners): more views
    t, poses, imgs = render_views(spec, 8 if spec.startswith("charuco") else 5)
    views = []
    for k, (pose, img) in enumerate(zip(poses, imgs)):
        d = t.detect(img)
        assert d, f"{spec} view {k}: {d.reason}"
        assert d.rotation_ambiguity_deg == ambiguity
        truth = CAM.project(pose.apply(t.points_target_mm[d.ids]))
        err = np.abs(d.points_px - truth).max()
        if ambiguity == 0:  # the order is the target's own: every point at its true image
            assert err < 0.6, f"{spec} view {k}: {err:.2f} px"
        views.append(TargetView(f"v{k}", d.points_px, d.ids, d.rotation_ambiguity_deg))
    # the camera has radial distortion only (with p1, p2 free, ChArUco's 48 noisier corners in
    # 8 views leave cx 2.3 px off, 2.8 sigma: tangential terms trade with the principal point)
    res = calibrate_target(views, t, CAM.image_size_px, model="opencv", coefficients="k1,k2,k3")
    K = res.camera.K
    assert abs(K[0, 0] / CAM.K[0, 0] - 1) < 0.005 and abs(K[1, 1] / CAM.K[1, 1] - 1) < 0.005
    assert np.hypot(K[0, 2] - CAM.K[0, 2], K[1, 2] - CAM.K[1, 2]) < 2.0
    assert res.rms_px < 0.25 and not res.flagged


def test_polarity_matters():
    t, poses, imgs = render_views("circles:6x6:20:light", 1)
    assert t.detect(imgs[0])
    assert not target_from_spec("circles:6x6:20").detect(imgs[0])


def test_charuco_partial_view_gives_the_corners_seen():
    t = target_from_spec("charuco:5x7:24:18:DICT_5X5_100")
    # the board face-on, its left third outside the image
    pose = Pose(np.eye(3), [-175.0, -84.0, 260.0], "cam", "plate")
    img = render_plate(CAM, pose, t, rng=np.random.default_rng(0))
    d = t.detect(img)
    assert d and d.rotation_ambiguity_deg == 0
    assert 6 <= len(d.ids) < t.n_points
    truth = CAM.project(pose.apply(t.points_target_mm[d.ids]))
    assert np.abs(d.points_px - truth).max() < 0.5
    assert np.all(CAM.in_image(truth))


def test_clutter_and_a_tilted_target_near_the_border():
    """Dark discs of the circles' size scattered around the target, the target tilted 50 deg
    with a corner 10 px from the image border: still found, in order."""
    t = target_from_spec("circles:6x6:20:origin-dot")
    from scipy.spatial.transform import Rotation

    R = Rotation.from_euler("xy", [50, 10], degrees=True).as_matrix()
    pose = Pose(R, [-145.0, -40.0, 300.0], "cam", "plate")
    img = render_plate(CAM, pose, t, rng=np.random.default_rng(2)).astype(float)
    truth = CAM.project(pose.apply(t.points_target_mm))
    assert truth[:, 0].min() < 40
    rng = np.random.default_rng(7)
    import cv2

    for _ in range(25):  # clutter away from the target
        c = rng.uniform([0, 0], [640, 480])
        if np.min(np.linalg.norm(truth - c, axis=1)) > 60:
            cv2.circle(img, tuple(int(v) for v in c), int(rng.uniform(4, 9)), 35, -1)
    d = t.detect(np.clip(img, 0, 255).astype(np.uint8))
    assert d, d.reason
    assert np.abs(d.points_px - truth[d.ids]).max() < 0.6 and len(d.ids) == 36


def test_cli_render_plate_any_target_then_calibrate(tmp_path):
    cam_file = tmp_path / "cam.json"
    cam_file.write_text(json.dumps(CAM.to_dict()))
    out = tmp_path / "acircles"
    r = CliRunner().invoke(app, ["render-plate", "--target", "acircles:4x11:12:light",
                                 "--count", "4", "--camera", str(cam_file), "--out", str(out)])
    assert r.exit_code == 0, r.output
    truth = json.loads((out / "truth.json").read_text())
    assert truth["target"] == "acircles:4x11:12:light" and len(truth["images"]) == 4
    r = CliRunner().invoke(app, ["calibrate", str(out), "--target", str(out / "target.yaml"),
                                 "--model", "opencv", "--coefficients", "k1,k2",
                                 "--no-pictures", "--out", str(tmp_path / "cal.yml")])
    assert r.exit_code == 0, r.output
    rep = json.loads((tmp_path / "cal.report.json").read_text())
    assert rep["coefficients"] == ["k1", "k2"] and rep["target"] == "acircles:4x11:12:light"
    fx = rep["camera"]["camera_matrix"][0][0]
    assert abs(fx / CAM.K[0, 0] - 1) < 0.005
