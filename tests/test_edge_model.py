"""The edge model of a broken pocket edge, dm+r (pose + edge radius), its Fisher information
and the error-budget verdict (issue 10, items 2 and 4)."""

from __future__ import annotations

import json

import numpy as np
import pytest

from cutterpose.budget import COVARIANCE_CAM_ORDER, Tolerance
from cutterpose.errors import InputError
from cutterpose.geometry.holder import default_holder
from cutterpose.geometry.pose import Pose, pose_errors
from cutterpose.image import detect_features
from cutterpose.image.edge_model import (
    EdgeLook,
    OffsetTable,
    edge_offsets_mm,
    edge_views,
    model_corners_mm,
)
from cutterpose.methods import get_method
from cutterpose.pipeline import QualityLimits, measure, measure_features
from cutterpose.render.analytic import PRESETS, render_holder
from cutterpose.solvers.edge_radius import RadiusPrior, crlb_pose_radius, fit_pose_radius
from test_budget import mc_figures
from test_features import SCALE, small_camera

HOLDER = default_holder()
# noise-free, texture-free rendering: the edge's shading alone
PLAIN = PRESETS["easy"].with_(texture=0.0, machining_marks=0.0, scratches=0, corrosion=0.0,
                              electrons_per_dn=0, read_noise_dn=0.0)
SMALL = QualityLimits(tolerance=Tolerance(position_mm=1.0 / SCALE, angle_deg=0.3 / SCALE))


def model_px(pose, cam, radius_mm, look=EdgeLook()):
    """Model pixels of the moved edge lines' corners."""
    t = OffsetTable(pose.R, pose.t_mm, cam.K, HOLDER, look)
    P = model_corners_mm(HOLDER, t(radius_mm)[0], t.view.outward)
    X = P @ pose.R.T + pose.t_mm
    return (X @ cam.K.T)[:, :2] / X[:, 2:3], t


def detected_edge_offsets_px(features, pose, cam) -> np.ndarray:
    """Per holder edge, the mean signed distance (px, outwards) of its detected line from the
    projected design corners at its two ends."""
    uv = model_px(pose, cam, 0.0)[0]
    L = np.asarray(features.lines_ideal, float)
    centre = uv.mean(axis=0)
    out = np.empty(len(uv))
    for k in range(len(uv)):
        ends = np.c_[uv[k], uv[(k + 1) % len(uv)]]
        j = int(np.argmin(np.abs(L[:, :2] @ ends + L[:, 2:3]).sum(axis=1)))
        line = L[j] if L[j, :2] @ centre + L[j, 2] < 0 else -L[j]
        out[k] = -float(np.mean(line[:2] @ ends + line[2]))
    return out


def test_sharp_edge_images_on_the_design_edge():
    cam = small_camera(1.0)
    pose = Pose.from_euler(4, -6, 3, 10, -12, 605)
    v = edge_views(pose.R, pose.t_mm, cam.K, HOLDER)
    o = edge_offsets_mm(np.array([0.0, 2.0]), v)
    assert np.nanmax(np.abs(o["w_px"][..., 0])) < 0.05
    # a 2 mm fillet moves the edge by a fraction of a millimetre, in and out by view
    assert np.nanmax(np.abs(o["delta_mm"][..., 1])) > 0.1
    assert np.all(np.abs(o["delta_mm"][..., 1]) < 2.0)


@pytest.mark.parametrize("shape,radius,pose", [
    ("round", 4.0, Pose.from_euler(2, -3, 4, 8, -6, 612)),
    ("chamfer", 4.0, Pose.from_euler(3, 4, -2, 5, 8, 605)),
])
def test_model_predicts_where_the_rendered_broken_edge_is_detected(shape, radius, pose):
    """The analytic renderer's ray-traced fillet / chamfer, detected by the line refinement:
    per edge the detected line lies where the model says (a few edges near a rival rise or a
    corner blend may not)."""
    cam = small_camera(SCALE)
    r = render_holder(pose, cam, HOLDER, PLAIN.with_(edge_radius_mm=radius, edge_shape=shape),
                      seed=3)
    assert len(r.edge_radius_mm) == HOLDER.n_corners
    f = detect_features(r.image, cam, HOLDER)
    measured = detected_edge_offsets_px(f, pose, cam)
    look = EdgeLook(shape=shape)
    w = edge_offsets_mm(np.array([radius]), edge_views(pose.R, pose.t_mm, cam.K, HOLDER, look),
                        look)["w_px"][..., 0]
    predicted = 0.5 * (w[:, 1] + np.roll(w[:, 0], -1))
    err = np.abs(measured - predicted)
    assert np.median(err) < 0.1
    assert np.mean(err < 0.3) >= 0.75
    # the model explains the offsets: far better than assuming the design edge
    assert np.median(err) < 0.5 * np.median(np.abs(measured))


def test_fit_recovers_radius_and_design_pose_from_model_corners():
    cam = small_camera(1.0)
    pose = Pose.from_euler(3, -4, 5, 10, -8, 610)
    rng = np.random.default_rng(0)
    for r_true in (0.0, 3.0):
        uv, table = model_px(pose, cam, r_true)
        fit = fit_pose_radius(pose.dof + [0.1, -0.1, 0.05, 0.5, -0.5, 2.0],
                              uv + 0.02 * rng.standard_normal(uv.shape), cam, HOLDER,
                              table=table)
        assert abs(fit.radius_mm - r_true) < 0.15
        assert np.all(np.abs(fit.dof - pose.dof) < [0.02, 0.02, 0.01, 0.02, 0.02, 0.15])


def test_crlb_matches_monte_carlo_of_the_estimator():
    """At r = 3 mm the offset is near the wall: r and Z correlate at -0.997 and the Z bound
    with r free is ~10x the one with r known; the estimator's spread follows the bound."""
    cam = small_camera(1.0)
    pose = Pose.nominal()
    sigma, r_true = 0.05, 3.0
    uv, table = model_px(pose, cam, r_true)
    rng = np.random.default_rng(1)
    est = np.array([
        np.r_[(f := fit_pose_radius(pose.dof, uv + sigma * rng.standard_normal(uv.shape), cam,
                                    HOLDER, table=table)).dof, f.radius_mm]
        for _ in range(60)])
    bound = crlb_pose_radius(pose, cam, HOLDER, r_true, sigma, prior=RadiusPrior())
    mc = est.std(axis=0)
    assert 0.8 < mc[5] / bound["std_free"][5] < 1.4
    assert 0.8 < mc[6] / bound["std_free"][6] < 1.4
    assert bound["std_free"][5] > 5 * bound["std_known"][5]
    assert np.corrcoef(est[:, 5], est[:, 6])[0, 1] < -0.95
    assert bound["corr_r"][5] < -0.95


def test_dm_plus_r_removes_the_depth_bias_of_a_rounded_edge():
    cam = small_camera(0.5)
    pose = Pose.from_euler(2, -3, 4, 8, -6, 612)
    r = render_holder(pose, cam, HOLDER, PLAIN.with_(edge_radius_mm=2.0), seed=5)
    f = detect_features(r.image, cam, HOLDER)
    plain = measure_features(f, cam, HOLDER, "dm+")
    joint = measure_features(f, cam, HOLDER, "dm+r")
    dz_plain = plain.pose.dof[5] - pose.dof[5]
    dz_joint = joint.pose.dof[5] - pose.dof[5]
    assert abs(dz_plain) > 0.3          # the edge images off the design edge: a depth bias
    assert abs(dz_joint) < 0.4 * abs(dz_plain)
    rot = [pose_errors(pose.R, pose.t_mm, m.pose.R, m.pose.t_mm).rot_deg[0]
           for m in (plain, joint)]
    assert rot[1] < 0.5 * rot[0]
    assert abs(joint.edge_radius_mm - 2.0) < 0.5
    assert joint.quality.rms_px < 0.5 * plain.quality.rms_px
    assert np.isnan(plain.edge_radius_mm)


def test_budget_in_json_covariance_and_grasp_point():
    cam = small_camera(SCALE)
    pose = Pose.from_euler(-2, 3, -4, -6, 5, 590)
    r = render_holder(pose, cam, HOLDER, "new", seed=11)
    f = detect_features(r.image, cam, HOLDER)
    m = measure_features(f, cam, HOLDER, "dm+r", SMALL)
    assert m.ok, m.quality.reason
    assert m.estimate.info["edge_shape"] == "round"      # the preset's fillet, not a chamfer
    d = json.loads(json.dumps(m.to_dict()))
    b = d["quality"]["budget"]
    assert set(b["parts"]) == {"noise", "radius", "model", "edge_variation"}
    assert b["covariance_cam"]["order"] == list(COVARIANCE_CAM_ORDER)
    assert {"ok", "reason", "rms_residual_px", "edge_bias", "note"} <= set(d["quality"])
    C = m.covariance_cam
    assert C.shape == (6, 6) and np.allclose(C, C.T) and np.linalg.eigvalsh(C).min() > -1e-12
    e = pose_errors(pose.R, pose.t_mm, m.pose.R, m.pose.t_mm)
    assert e.trans_mm[0] < b["position_3sigma_mm"]
    # a grasp point 300 mm away from the origin: the rotation's uncertainty adds to the position
    far = measure_features(f, cam, HOLDER, "dm+r",
                           QualityLimits(tolerance=SMALL.tolerance,
                                         grasp_point_mm=(300.0, 0.0, 0.0)))
    bf = far.quality.budget
    assert bf.position_3sigma_mm > m.quality.budget.position_3sigma_mm
    # ... by exactly the spread of that point under the stated covariance (Monte Carlo)
    pos, ang, _ = mc_figures(far.pose.dof, bf.dof_cov, (300.0, 0.0, 0.0), n=50_000)
    assert bf.position_3sigma_mm == pytest.approx(pos, rel=0.015)
    assert bf.angle_3sigma_deg == pytest.approx(ang, rel=0.015)


def test_verdict_refuses_over_budget_with_the_reason():
    cam = small_camera(SCALE)
    pose = Pose.from_euler(-2, 3, -4, -6, 5, 590)
    r = render_holder(pose, cam, HOLDER, "new", seed=11)
    f = detect_features(r.image, cam, HOLDER)
    tight = QualityLimits(tolerance=Tolerance(position_mm=0.01, angle_deg=10.0))
    m = measure_features(f, cam, HOLDER, "dm+r", tight)
    assert not m.ok and "error budget" in m.quality.reason and "grasp point" in m.quality.reason
    assert m.pose is not None and m.quality.budget.position_3sigma_mm > 0.01


def test_paper_chain_stays_selectable_without_edge_model():
    assert get_method("dm+r").needs_correspondences is False
    cam = small_camera(SCALE)
    pose = Pose.from_euler(-2, 3, -4, -6, 5, 590)
    r = render_holder(pose, cam, HOLDER, "easy", seed=11)
    f = detect_features(r.image, cam, HOLDER)
    m = measure_features(f, cam, HOLDER, "dm", SMALL)
    assert m.method == "dm" and m.estimate.radius_fit is None
    # the corners see the broken edge: a break not declared is in the budget
    assert set(m.quality.budget.parts) == {"noise", "method", "wear", "edge break"}


def test_bad_edge_look_and_radius_are_refused():
    with pytest.raises(InputError):
        EdgeLook(shape="bevel")
    with pytest.raises(InputError):
        EdgeLook(blur_sigma_px=-1.0)
    cam = small_camera(1.0)
    v = edge_views(np.eye(3), [0, 0, 600.0], cam.K, HOLDER)
    with pytest.raises(InputError):
        edge_offsets_mm(np.array([-1.0]), v)
    with pytest.raises(InputError):
        RadiusPrior(std_mm=0.0)
    with pytest.raises(InputError):
        measure(np.zeros((8, 8), np.uint8), cam, HOLDER, grasp_point_mm=(1.0, 2.0))
