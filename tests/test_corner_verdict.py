"""The corner methods' verdict on a broken pocket edge (issue 10, item 4): ``dm``, ``dm+`` and
the PnP baselines see the broken edge, not the design edge, so a break they cannot measure is
a systematic part of their error budget (``QualityLimits.edge_break_mm``)."""

from __future__ import annotations

import numpy as np
import pytest

from cutterpose.errors import InputError
from cutterpose.geometry.camera import default_camera
from cutterpose.geometry.holder import default_holder
from cutterpose.geometry.pose import Pose, pose_errors
from cutterpose.image.edge_model import model_corners_mm
from cutterpose.methods import get_method
from cutterpose.pipeline import (
    UNKNOWN_EDGE_BREAK_MM,
    QualityLimits,
    edge_break_effect,
    fit_offset,
    measure,
)
from cutterpose.render.analytic import render_holder
from test_features import small_camera

HOLDER = default_holder()
POSE = Pose.from_euler(6, -5, 3, 12, -9, 612)


def test_edge_break_effect_is_the_refit_of_moved_corners():
    """The linear shift equals a PnP fit to the corners of edges seen 0.5 mm outside the
    design edge, and it is the size the issue warns of: the pocket looks closer."""
    cam = default_camera("table1")
    o = HOLDER.edge_normals
    outward = np.stack([np.roll(o, 1, axis=0), o], axis=1)
    moved = model_corners_mm(HOLDER, np.full((HOLDER.n_corners, 2), 0.5), outward)
    px = cam.project(POSE.apply(moved))
    est = get_method("opencv-ippe-lm").solve(px, cam, HOLDER.points_holder_mm)
    fitted = Pose(est.R_cam_holder, est.t_cam_holder_mm).dof - POSE.dof
    pred = edge_break_effect(POSE, cam, HOLDER, np.ones(HOLDER.n_corners, bool), 0.5)
    # (linearised: the tilts agree to ~7 %, the depth to 0.1 %)
    np.testing.assert_allclose(pred, fitted, rtol=0.1, atol=5e-3)
    assert pred[5] < -2.0                       # 0.5 mm all round: > 2 mm closer at 612 mm
    # half the corners: a different fit, still the same sign and size
    half = np.arange(HOLDER.n_corners) < 10
    assert edge_break_effect(POSE, cam, HOLDER, half, 0.5)[5] < -1.0


def test_a_break_not_measured_refuses_the_corner_pose_and_says_why():
    """A new holder's break (analytic 'new': fillets of 0.5-1.5 mm): dm+ is refused with the
    reason while the break is unknown; declared, its 3-sigma depth covers the error, and
    dm+b, which measures the break, carries no such part."""
    cam = small_camera(0.5)
    r = render_holder(POSE, cam, HOLDER, "new", seed=3)
    m = measure(r.image, cam, HOLDER, "dm+")
    assert m.pose is not None and not m.ok
    assert "broken edge" in m.quality.reason and "dm+b" in m.quality.reason
    assert "edge break" in m.quality.budget.parts
    d = m.to_dict()["quality"]["budget"]["parts"]["edge break"]
    assert d["position_3sigma_mm"] > 1.0
    err = pose_errors(POSE.R, POSE.t_mm, m.pose.R, m.pose.t_mm).dof[0]
    declared = measure(r.image, cam, HOLDER, "dm+", limits=QualityLimits(edge_break_mm=1.5))
    assert abs(err[5]) <= 3 * declared.std_dof[5]
    sharp = measure(r.image, cam, HOLDER, "dm+", limits=QualityLimits(edge_break_mm=0.0))
    assert "edge break" not in sharp.quality.budget.parts
    assert sharp.std_dof[5] < declared.std_dof[5] / 3


def test_edge_break_limits_are_validated():
    assert QualityLimits().assumed_edge_break_mm == UNKNOWN_EDGE_BREAK_MM
    assert QualityLimits(edge_break_mm=0).assumed_edge_break_mm == 0.0
    assert QualityLimits(edge_break_mm=np.float32(0.5)).assumed_edge_break_mm == 0.5
    for bad in (-0.1, float("nan"), float("inf"), "1", True):
        with pytest.raises(InputError, match="edge_break_mm"):
            QualityLimits(edge_break_mm=bad)


def test_a_pose_off_the_corners_fit_carries_its_offset():
    """dm's search or a linear PnP leaves its pose off the corners' least-squares pose: the
    step to it is the budget's 'method' part (zero at the least-squares pose itself)."""
    cam = default_camera("table1")
    corners = cam.undistort_px(cam.project(POSE.apply(HOLDER.points_holder_mm)))
    assert np.abs(fit_offset(POSE, corners, cam, HOLDER, "holder")).max() < 1e-6
    moved = Pose.from_euler(*(POSE.dof + [0.05, -0.03, 0.01, 0.2, -0.1, 0.5]))
    step = fit_offset(moved, corners, cam, HOLDER, "holder")
    np.testing.assert_allclose(step, POSE.dof - moved.dof, atol=2e-3)
    few = np.full_like(corners, np.nan)
    few[:3] = corners[:3]
    assert np.all(np.isnan(fit_offset(POSE, few, cam, HOLDER, "holder")))
