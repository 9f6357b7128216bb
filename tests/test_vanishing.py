"""Initial pose from vanishing directions and contour area (cutterpose.solvers.vanishing)."""

from __future__ import annotations

import numpy as np
import pytest

from cutterpose.errors import DegenerateInputError, InputError
from cutterpose.geometry.camera import default_camera
from cutterpose.geometry.holder import default_holder
from cutterpose.geometry.pose import Pose, geodesic_deg, rotation_from_euler_deg
from cutterpose.geometry.working_range import MotionRange
from cutterpose.solvers.vanishing import (
    initial_pose,
    initial_pose_paper,
    solve,
    solve_paper,
)

CAM = default_camera("synthetic")
HOLDER = default_holder()


def observe(pose: Pose, sigma=0.0, shift=0, reverse=False, rng=None, camera=CAM):
    px = camera.project(pose.apply(HOLDER.points_holder_mm))
    if sigma:
        px = px + rng.normal(0.0, sigma, px.shape)
    px = np.roll(px, shift, axis=0)
    return px[::-1] if reverse else px


def random_pose(rng, angle=60.0, trans=90.0):
    while True:
        a = rng.uniform(-angle, angle, 3)
        t = rng.uniform(-trans, trans, 3) + [0, 0, 600]
        p = Pose.from_euler(*a, *t)
        if np.all(CAM.in_image(CAM.project(p.apply(HOLDER.points_holder_mm)))):
            return p


@pytest.mark.parametrize("fn", [initial_pose, initial_pose_paper])
def test_noise_free_exact_under_any_start_and_direction(fn):
    rng = np.random.default_rng(1)
    for k in range(8):
        p = random_pose(rng)
        est = fn(observe(p, shift=int(rng.integers(20)), reverse=bool(k % 2)), CAM, HOLDER)
        assert est, est.reason
        assert geodesic_deg(p.R, est.R_cam_holder) < 1e-6
        assert np.abs(est.t_cam_holder_mm - p.t_mm).max() < 1e-6


def test_paper_fronto_parallel_vanishing_points_at_infinity():
    # R = I: every pair of parallel image lines is parallel, the vanishing points are at infinity
    p = Pose.nominal()
    est = initial_pose_paper(observe(p, shift=3), CAM, HOLDER)
    assert est and geodesic_deg(np.eye(3), est.R_cam_holder) < 1e-6
    assert np.abs(est.t_cam_holder_mm - p.t_mm).max() < 1e-6


def test_symmetric_twin_resolved_by_motion_range():
    # the holder maps onto itself under 180 deg about Z: the image cannot tell the two apart,
    # the motion range does
    p = Pose.from_euler(5, -8, 12, 10, -20, 620)
    px = observe(p)
    near = initial_pose(px, CAM, HOLDER)
    assert geodesic_deg(p.R, near.R_cam_holder) < 1e-6
    twin_range = MotionRange(center_dof=(0, 0, 180, 0, 0, 600),
                             half_width_dof=(60, 60, 60, 90, 90, 90))
    far = initial_pose(px, CAM, HOLDER, motion_range=twin_range)
    assert geodesic_deg(p.R @ rotation_from_euler_deg(0, 0, 180), far.R_cam_holder) < 1e-6
    assert np.abs(far.t_cam_holder_mm - p.t_mm).max() < 1e-6   # origin at the symmetry centre


def test_sphere_beats_paper_median_under_noise():
    rng = np.random.default_rng(7)
    err_s, err_p = [], []
    for _ in range(40):
        p = random_pose(rng)
        px = observe(p, sigma=2.0, rng=rng, shift=int(rng.integers(20)))
        err_s.append(geodesic_deg(p.R, solve(px, CAM, HOLDER).R_cam_holder))
        e = solve_paper(px, CAM, HOLDER)
        err_p.append(geodesic_deg(p.R, e.R_cam_holder) if e else 180.0)
    assert np.median(err_s) < 0.6 * np.median(err_p)


def test_through_lens_distortion():
    cam = default_camera("table1")
    p = Pose.from_euler(4, -6, 3, 8, -5, 600)
    est = initial_pose(observe(p, camera=cam, shift=5, reverse=True), cam, HOLDER,
                       motion_range=MotionRange.real())
    assert est and geodesic_deg(p.R, est.R_cam_holder) < 1e-6


def test_out_of_range_is_a_failure_not_a_wrong_pose():
    p = Pose.from_euler(0, 0, 40, 0, 0, 600)       # gamma 40 deg: outside the real +-10 deg
    est = initial_pose(observe(p), CAM, HOLDER, motion_range=MotionRange.real())
    assert not est and "motion range" in est.reason


def test_motion_range_presets_and_excess():
    wide, real = MotionRange.synthetic(), MotionRange.real()
    assert np.allclose(wide.upper, [60, 60, 60, 90, 90, 690])
    assert np.allclose(real.lower, [-10, -10, -10, -20, -20, 580])
    assert real.contains([10, -10, 0, 20, 0, 620])
    assert not real.contains([0, 0, 15, 0, 0, 600])
    assert real.excess([0, 0, 15, 0, 0, 600]) == pytest.approx(0.5)
    assert wide.excess([0, 0, 179, 0, 0, 600]) > 1.5


@pytest.mark.parametrize("fn", [initial_pose, initial_pose_paper])
def test_bad_input_raises_typed_errors(fn):
    px = observe(Pose.nominal())
    with pytest.raises(DegenerateInputError, match="20 corners"):
        fn(px[:12], CAM, HOLDER)
    bad = px.copy()
    bad[4, 1] = np.nan
    with pytest.raises(InputError, match="NaN"):
        fn(bad, CAM, HOLDER)
    line = np.column_stack([np.linspace(100, 900, 20), np.linspace(50, 450, 20)])
    with pytest.raises(DegenerateInputError, match="collinear"):
        fn(line, CAM, HOLDER)
    with pytest.raises(InputError, match="shape"):
        fn(px.ravel(), CAM, HOLDER)
    with pytest.raises(InputError, match="Holder"):
        fn(px, CAM, HOLDER.points_holder_mm)
