"""cutterpose measure: bad input gives a message and a non-zero exit code, never a traceback."""

from __future__ import annotations

import json

import cv2
import numpy as np
import pytest
from typer.testing import CliRunner

from cutterpose.cli import app
from cutterpose.geometry.camera_files import save_camera
from cutterpose.geometry.holder import default_holder
from cutterpose.geometry.pose import Pose
from cutterpose.render.analytic import render_holder
from test_features import small_camera

runner = CliRunner()


@pytest.fixture(scope="module")
def files(tmp_path_factory):
    d = tmp_path_factory.mktemp("measure")
    cam = small_camera()
    save_camera(cam, d / "cam.json")
    good = render_holder(Pose.from_euler(1, 2, -3, 4, -5, 605), cam, default_holder(), "easy",
                         seed=2).image
    cv2.imwrite(str(d / "good.png"), good)
    h, w = good.shape
    cv2.imwrite(str(d / "wrong_size.png"), good[:, : w - 8])
    cv2.imwrite(str(d / "black.png"), np.zeros_like(good))
    cv2.imwrite(str(d / "saturated.png"), np.full_like(good, 255))
    rng = np.random.default_rng(0)
    cv2.imwrite(str(d / "no_holder.png"), cv2.GaussianBlur(
        rng.integers(0, 256, good.shape, dtype=np.uint8), (0, 0), 3))
    half = np.roll(good, -int(0.42 * w), axis=1)
    half[:, -int(0.42 * w):] = 20
    cv2.imwrite(str(d / "half_out.png"), half)
    (d / "text.png").write_text("not an image")
    data = (d / "good.png").read_bytes()
    (d / "truncated.png").write_bytes(data[: len(data) // 2])
    return d


def _run(*args):
    return runner.invoke(app, ["measure", *map(str, args)])


@pytest.mark.parametrize("name,words", [
    ("missing.png", "not found"), ("text.png", "not a readable image"),
    ("truncated.png", "image"), ("wrong_size.png", "camera model"), ("black.png", "black"),
    ("saturated.png", "saturated"), ("no_holder.png", "refused"), ("half_out.png", "refused"),
])
def test_bad_input_clear_message_nonzero_exit(files, name, words):
    res = _run(files / name, "--camera", files / "cam.json", "--method", "opencv-ippe-lm",
               "--json")
    assert res.exit_code != 0
    assert res.exception is None or isinstance(res.exception, SystemExit)
    assert "Traceback" not in res.output
    assert words in res.output
    if res.stdout.strip():  # --json: a refused pose is never marked good
        assert json.loads(res.stdout.strip())["quality"]["ok"] is False


def test_json_and_overlay(files, tmp_path):
    res = _run(files / "good.png", "--camera", files / "cam.json", "--method", "opencv-ippe-lm",
               "--edge-break-mm", "0", "--json", "--overlay", tmp_path / "o.png")
    assert res.exit_code == 0, res.output
    d = json.loads(res.stdout.strip())
    assert d["quality"]["ok"] is True
    assert set(d["pose"]) >= {"alpha_deg", "X_mm", "R_cam_holder", "frames"}
    assert len(d["corners_px"]) == 20 and d["std"]["Z_mm"] > 0
    assert cv2.imread(str(tmp_path / "o.png")) is not None


def test_edge_shape_option_reaches_the_verdict(tmp_path):
    """With dm+r (corners only), --edge-shape unknown makes the budget carry the chamfer's
    unseen depth: the same clean image accepted as round is refused, with the budget's reason;
    dm+b (the default) measures the band and accepts it with the shape unknown (the default);
    a bad value is an error."""
    from cutterpose.geometry.camera import default_camera
    from cutterpose.geometry.pose import Pose
    from cutterpose.render.analytic import render_holder

    img = render_holder(Pose.from_euler(2, -3, 4, 8, -6, 612), default_camera("table1"),
                        seed=7).image
    cv2.imwrite(str(tmp_path / "h.png"), img)
    ok = runner.invoke(app, ["measure", str(tmp_path / "h.png"), "--method", "dm+r",
                             "--edge-shape", "round"])
    unknown = runner.invoke(app, ["measure", str(tmp_path / "h.png"), "--method", "dm+r"])
    assert ok.exit_code == 0, ok.output
    assert unknown.exit_code == 3 and "error budget" in unknown.output
    band = runner.invoke(app, ["measure", str(tmp_path / "h.png")])
    assert band.exit_code == 0, band.output
    bad = runner.invoke(app, ["measure", str(tmp_path / "h.png"), "--edge-shape", "oval"])
    assert bad.exit_code == 2 and "edge_shape" in bad.output


def test_corners_option_adds_the_corners_to_dm_plus_b(tmp_path):
    """dm+b (the default) starts from the pocket outline and reports no corners; --corners
    detects them anyway and leaves the pose as it was."""
    from cutterpose.geometry.camera import default_camera

    img = render_holder(Pose.from_euler(2, -3, 4, 8, -6, 612), default_camera("table1"),
                        seed=7).image
    cv2.imwrite(str(tmp_path / "h.png"), img)
    plain = runner.invoke(app, ["measure", str(tmp_path / "h.png"), "--json"])
    more = runner.invoke(app, ["measure", str(tmp_path / "h.png"), "--json", "--corners"])
    assert plain.exit_code == 0 and more.exit_code == 0, (plain.output, more.output)
    a, b = json.loads(plain.stdout.strip()), json.loads(more.stdout.strip())
    assert a["corners_px"] == [] and len(b["corners_px"]) == 20
    assert a["features"]["segmentation"] == "outline"
    assert a["pose"]["R_cam_holder"] == b["pose"]["R_cam_holder"]
    assert a["pose"]["t_cam_holder_mm"] == b["pose"]["t_cam_holder_mm"]


def test_budget_tolerance_options_set_the_measurements_own_verdict(tmp_path):
    """--budget-tol-deg / --budget-tol-mm move the line the error budget is held to: the same
    image accepted at the defaults is refused, with the figure, under a tighter angle; a
    non-positive tolerance is an input error."""
    from cutterpose.geometry.camera import default_camera

    img = render_holder(Pose.from_euler(2, -3, 4, 8, -6, 612), default_camera("table1"),
                        seed=7).image
    cv2.imwrite(str(tmp_path / "h.png"), img)
    plain = runner.invoke(app, ["measure", str(tmp_path / "h.png"), "--json"])
    assert plain.exit_code == 0, plain.output
    angle = json.loads(plain.output)["quality"]["budget"]["angle_3sigma_deg"]
    tight = runner.invoke(app, ["measure", str(tmp_path / "h.png"), "--budget-tol-deg",
                                f"{0.5 * angle:.4f}"])
    assert tight.exit_code == 3 and "rotation uncertain" in tight.output
    assert f"> {0.5 * angle:.4f}".rstrip("0") in tight.output
    for opt in ("--budget-tol-mm", "--budget-tol-deg"):
        bad = runner.invoke(app, ["measure", str(tmp_path / "h.png"), opt, "0"])
        assert bad.exit_code != 0 and opt in bad.output and "Traceback" not in bad.output


def test_distance_option_measures_at_another_station(tmp_path):
    """A station 720 mm from the holder: with the default (the paper's 600 mm) the holder is
    not measured; --distance-mm 720 finds it at that size and centres the working range
    there; a bad distance is an input error."""
    from cutterpose.geometry.camera import default_camera
    from cutterpose.geometry.pose import pose_errors

    truth = Pose.from_euler(2, -3, 4, 8, -6, 725)
    img = render_holder(truth, default_camera("table1"), seed=7).image
    cv2.imwrite(str(tmp_path / "h.png"), img)
    plain = runner.invoke(app, ["measure", str(tmp_path / "h.png"), "--json"])
    assert plain.exit_code == 3, plain.output
    far = runner.invoke(app, ["measure", str(tmp_path / "h.png"), "--json", "--distance-mm",
                              "720"])
    assert far.exit_code == 0, far.output
    doc = json.loads(far.output)
    p, b = doc["pose"], doc["quality"]["budget"]
    e = pose_errors(truth.R, truth.t_mm, np.array(p["R_cam_holder"]),
                    np.array(p["t_cam_holder_mm"]))
    # within the robot's 1 mm and within the measurement's own 3-sigma figures
    assert float(np.ravel(e.trans_mm)[0]) <= min(1.0, b["position_3sigma_mm"])
    assert float(np.ravel(e.rot_deg)[0]) <= b["angle_3sigma_deg"]
    bad = runner.invoke(app, ["measure", str(tmp_path / "h.png"), "--distance-mm", "-5"])
    assert bad.exit_code == 2 and "station distance" in bad.output
