"""Distance matching and its continuous refinement (cutterpose.solvers.matching)."""

from __future__ import annotations

import numpy as np
import pytest

from cutterpose.errors import DegenerateInputError, InputError
from cutterpose.geometry.camera import default_camera
from cutterpose.geometry.holder import default_holder
from cutterpose.geometry.pose import Pose, geodesic_deg
from cutterpose.geometry.working_range import MotionRange, PoseOutOfRangeError
from cutterpose.methods import get_method
from cutterpose.solvers.dm import solve_dm, solve_dm_plus
from cutterpose.solvers.matching import (
    PAPER_STEPS,
    TemplateLibrary,
    distance_image,
    distance_match,
    refine_continuous,
)
from cutterpose.solvers.vanishing import initial_pose

CAM = default_camera("synthetic")
HOLDER = default_holder()


def observe(pose: Pose, sigma=0.0, rng=None, shift=0, reverse=False):
    px = CAM.project(pose.apply(HOLDER.points_holder_mm))
    if sigma:
        px = px + rng.normal(0.0, sigma, px.shape)
    px = np.roll(px, shift, axis=0)
    return px[::-1] if reverse else px


POSES = [Pose.from_euler(20, -35, 50, 40, -60, 650), Pose.from_euler(-5, 10, -3, -10, 20, 560),
         Pose.from_euler(45, 30, -55, 70, 80, 520)]


def test_distance_image_is_the_distance_to_the_nearest_corner():
    px = observe(POSES[0])
    dimg = distance_image(px)
    rng = np.random.default_rng(0)
    h, w = dimg.dist_px.shape
    q = rng.uniform([0, 0], [w - 1, h - 1], (500, 2)) + dimg.origin_px
    corners = np.rint(px)
    true = np.linalg.norm(np.rint(q)[:, None] - corners[None], axis=-1).min(axis=1)
    got = dimg.sample(q)
    assert np.all(np.abs(got - true) <= 0.03 * true + 0.05)      # 5x5 chamfer mask
    # outside the region: border value plus the distance to the border
    far = np.array([[dimg.origin_px[0] - 100.0, dimg.origin_px[1] + h / 2]])
    assert dimg.sample(far)[0] >= 100.0


@pytest.mark.parametrize("pose", POSES)
def test_noise_free_dm_lands_on_the_truth(pose):
    px = observe(pose, shift=11, reverse=True)
    est = solve_dm(px, CAM, HOLDER)
    assert est, est.reason
    assert geodesic_deg(pose.R, est.R_cam_holder) < 0.15
    assert np.abs(est.t_cam_holder_mm - pose.t_mm).max() < 0.3


def test_dm_recovers_from_an_initial_pose_several_steps_off():
    pose = POSES[1]
    px = observe(pose)
    start = Pose.from_euler(*(pose.dof[:3] + [6, -7, 4]), *(pose.t_mm + [12, -9, 15]))
    est = distance_match(px, CAM, HOLDER, (start.R, start.t_mm))
    assert geodesic_deg(pose.R, est.R_cam_holder) < 0.15
    assert np.abs(est.t_cam_holder_mm - pose.t_mm).max() < 0.3


def _ml_pose(px, pose):
    """Least squares with the true correspondences, started at the truth: the ML pose."""
    from scipy.optimize import least_squares
    from scipy.spatial.transform import Rotation

    def res(p):
        X = HOLDER.points_holder_mm @ (Rotation.from_rotvec(p[:3]).as_matrix() @ pose.R).T
        return (CAM.project(X + p[3:]) - px).ravel()

    r = least_squares(res, np.r_[0, 0, 0, pose.t_mm], xtol=1e-14, ftol=1e-14, gtol=1e-14,
                      x_scale=np.r_[1e-3, 1e-3, 1e-3, 1, 1, 1])
    return Rotation.from_rotvec(r.x[:3]).as_matrix() @ pose.R, r.x[3:]


def test_dm_plus_is_the_ml_pose_without_correspondences():
    rng = np.random.default_rng(3)
    ml = get_method("opencv-ippe-lm")
    for pose in POSES:
        px_model_order = observe(pose, sigma=1.5, rng=rng)
        R_ml, t_ml = _ml_pose(px_model_order, pose)
        est = solve_dm_plus(np.roll(px_model_order, 7, axis=0)[::-1], CAM, HOLDER)
        assert est, est.reason
        assert geodesic_deg(R_ml, est.R_cam_holder) < 1e-5
        assert np.abs(est.t_cam_holder_mm - t_ml).max() < 1e-4
        # never worse than OpenCV's IPPE + LM with the true correspondences
        ref = ml.solve(px_model_order, CAM, HOLDER)
        assert est.residual_px <= ref.residual_px + 1e-9


def test_dm_plus_cannot_shrink_to_a_point():
    # start far behind the truth: the nearest-corner cost would be least with every model
    # corner on one detected corner; the one-to-one assignment forbids it
    pose = POSES[0]
    px = observe(pose)
    start = Pose.from_euler(*pose.dof[:3], *(pose.t_mm + [0, 0, 3000]))
    from cutterpose.solvers.estimate import PoseEstimate
    est = refine_continuous(PoseEstimate("dm", start.R, start.t_mm), px, CAM, HOLDER,
                            MotionRange(), slack=100.0)
    assert len(set(est.assignment)) == HOLDER.n_corners
    assert est.t_cam_holder_mm[2] < 1500


def test_template_library_matches_the_on_the_fly_search(tmp_path):
    pose = Pose.from_euler(3, -4, 2, 6, -7, 604)
    px = observe(pose)
    small = MotionRange(center_dof=(0, 0, 0, 0, 0, 600), half_width_dof=(5, 5, 5, 10, 10, 10))
    assert TemplateLibrary.grid_size(MotionRange.real(), PAPER_STEPS[0]) == 5 ** 3 * 9 ** 3
    with pytest.raises(InputError, match="templates"):
        TemplateLibrary.build(CAM, HOLDER, MotionRange.synthetic())
    lib = TemplateLibrary.build(CAM, HOLDER, small)
    assert lib.templates_px.shape == (3 ** 3 * 5 ** 3, 20, 2)
    lib.save(tmp_path / "lib.npz")
    lib = TemplateLibrary.load(tmp_path / "lib.npz")
    init = initial_pose(px, CAM, HOLDER, motion_range=small)
    a = distance_match(px, CAM, HOLDER, init, motion_range=small, library=lib)
    b = distance_match(px, CAM, HOLDER, init, motion_range=small)
    for est in (a, b):
        assert geodesic_deg(pose.R, est.R_cam_holder) < 0.15
        assert np.abs(est.t_cam_holder_mm - pose.t_mm).max() < 0.3


def test_initial_pose_outside_the_motion_range_raises():
    px = observe(Pose.nominal())
    bad = Pose.from_euler(0, 0, 45, 0, 0, 600)
    with pytest.raises(PoseOutOfRangeError, match="outside the motion range"):
        distance_match(px, CAM, HOLDER, (bad.R, bad.t_mm), motion_range=MotionRange.real())


@pytest.mark.parametrize("fn", [solve_dm, solve_dm_plus])
def test_bad_input_raises_typed_errors(fn):
    px = observe(Pose.nominal())
    with pytest.raises(DegenerateInputError, match="20 corners"):
        fn(px[:19], CAM, HOLDER)
    bad = px.copy()
    bad[0, 0] = np.inf
    with pytest.raises(InputError, match="NaN or inf"):
        fn(bad, CAM, HOLDER)
    line = np.column_stack([np.linspace(100, 900, 20), np.full(20, 300.0)])
    with pytest.raises(DegenerateInputError, match="collinear"):
        fn(line, CAM, HOLDER)


def test_dm_and_dm_plus_through_lens_distortion():
    # the distance image is in observed pixels, templates go through the division model; dm+
    # works on ideal pixels
    cam = default_camera("table1")
    rng = np.random.default_rng(5)
    pose = Pose.from_euler(4, -6, 3, 8, -5, 610)
    px = cam.project(pose.apply(HOLDER.points_holder_mm)) + rng.normal(0, 0.3, (20, 2))
    px = np.roll(px, 4, axis=0)[::-1]
    init = initial_pose(px, cam, HOLDER, motion_range=MotionRange.real())
    dm = distance_match(px, cam, HOLDER, init, motion_range=MotionRange.real())
    dmp = distance_match(px, cam, HOLDER, init, motion_range=MotionRange.real(), refine=True)
    assert geodesic_deg(pose.R, dm.R_cam_holder) < 0.3
    assert np.abs(dm.t_cam_holder_mm - pose.t_mm).max() < 1.0
    assert geodesic_deg(pose.R, dmp.R_cam_holder) < 0.1
    assert np.abs(dmp.t_cam_holder_mm - pose.t_mm).max() < 0.4   # 0.9 mm if distortion ignored
    assert dmp.residual_px < 0.4


def test_dm_paper_uses_the_papers_initial_pose():
    """``dm-paper`` is the paper as written: its initial pose (image-plane vanishing points)
    then distance matching; on clean corners it lands on the 0.1 grid like ``dm``."""
    from cutterpose.methods import get_method

    cam = default_camera("table1")
    truth = Pose.from_euler(3, -5, 2, 10, -8, 610)
    px = cam.project(truth.apply(HOLDER.points_holder_mm))
    est = get_method("dm-paper").solve(px, cam, HOLDER)
    assert est and est.method == "dm-paper"
    assert np.all(np.abs(est.pose.dof - truth.dof) < 0.2)
    paper_init = get_method("initial-paper").solve(px, cam, HOLDER)
    assert np.allclose(est.info["initial_dof"], paper_init.pose.dof)
