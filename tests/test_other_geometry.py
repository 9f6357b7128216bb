"""Holders of another design: the measurement knows only the holder file it is given.

The paper's holder has 20 corners; a cell may hold another design. Nothing in the image stage,
the band fit or the verdict may assume the reference shape: rendered with the holder's own
file and measured with it, a 12-corner and an asymmetric 8-corner pocket come out as
accurately as the reference one (tolerances as for the reference holder's analytic tests).
"""

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
