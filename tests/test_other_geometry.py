"""Holders of another design: the measurement knows only the holder file it is given.

The paper's holder has 20 corners; a cell may hold another design. Nothing in the image stage,
the band fit or the verdict may assume the reference shape: rendered with the holder's own
file and measured with it, a 12-corner and an asymmetric 8-corner pocket come out as
accurately as the reference one (tolerances as for the reference holder's analytic tests).
"""

import json

import numpy as np
import pytest

from cutterpose.geometry.camera import default_camera
from cutterpose.geometry.holder import holder_from_dict
from cutterpose.geometry.pose import Pose, pose_errors
from cutterpose.pipeline import measure
from cutterpose.render.analytic import render_holder

HOLDERS = {
    "cross, 12 corners": {
        "outer_rectangle": {"length_x": 440, "width_y": 260},
        "inner_contour_corners": [[-100, -90], [100, -90], [100, -40], [180, -40], [180, 40],
                                  [100, 40], [100, 90], [-100, 90], [-100, 40], [-180, 40],
                                  [-180, -40], [-100, -40]]},
    "one step, 8 corners": {
        "outer_rectangle": {"length_x": 480, "width_y": 260},
        "inner_contour_corners": [[-150, -80], [150, -80], [150, -30], [200, -30], [200, 40],
                                  [150, 40], [150, 80], [-150, 80]]},
}


@pytest.mark.parametrize("name", list(HOLDERS))
def test_another_holder_design_is_measured_from_its_own_file(name):
    holder = holder_from_dict(HOLDERS[name])
    cam = default_camera("table1")
    truth = Pose.from_euler(-6, 5, -8, -15, 12, 615)
    img = render_holder(truth, cam, holder, "new", seed=2).image
    res = measure(img, cam, holder, method="dm+b")
    assert res.ok, res.quality.reason
    e = pose_errors(truth.R, truth.t_mm, res.pose.R, res.pose.t_mm)
    assert float(np.ravel(e.rot_deg)[0]) < 0.2
    assert float(np.ravel(e.trans_mm)[0]) < 0.3
    # its verdict's figures cover the error it made
    assert float(np.ravel(e.rot_deg)[0]) <= res.quality.budget.angle_3sigma_deg


def test_the_reference_holder_file_does_not_find_another_design():
    """Measured with the wrong holder file, the 8-corner pocket gives no accepted pose."""
    from cutterpose.geometry.holder import default_holder

    cam = default_camera("table1")
    truth = Pose.from_euler(-6, 5, -8, -15, 12, 615)
    img = render_holder(truth, cam, holder_from_dict(HOLDERS["one step, 8 corners"]), "new",
                        seed=2).image
    res = measure(img, cam, default_holder(), method="dm+b")
    assert not res.ok and res.quality.reason


def test_a_holder_with_eight_edges_is_tracked(tmp_path):
    """The tracker needs half the holder's edges (at least 4, two per direction), not 10 of
    the reference's 20: an 8-edge pocket is tracked frame by frame, not measured in full on
    every frame."""
    from dataclasses import replace

    from cutterpose.render.sequence import render_sequence
    from cutterpose.tracking import Tracker, TrackParams, approach_limits
    from test_features import small_camera

    cam = small_camera()
    holder = holder_from_dict(HOLDERS["one step, 8 corners"])
    render_sequence(tmp_path, 6, 640.0, 615.0, cam, holder, settings="easy", seed=4)
    truth = json.loads((tmp_path / "truth.json").read_text())
    tracker = Tracker(cam, holder, "dm+", limits=replace(approach_limits(), edge_break_mm=0.0))
    results = [tracker.update(tmp_path / e["file"]) for e in truth["images"]]
    assert [r.mode for r in results] == ["full"] + ["track"] * 5, \
        [(r.mode, r.fallback_reason) for r in results]
    for r, e in zip(results[1:], truth["images"][1:]):
        assert r.lines_seen == 8
        err = pose_errors(np.array(e["R_cam_holder"]), np.array(e["t_cam_holder_mm"]),
                          r.pose.R, r.pose.t_mm)
        assert float(np.ravel(err.trans_mm)[0]) < 1.0 and float(np.ravel(err.rot_deg)[0]) < 0.3
    tp = TrackParams()
    assert [tp.lines_needed(n) for n in (4, 8, 12, 20, 40)] == [4, 4, 6, 10, 20]
