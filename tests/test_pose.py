import os

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from cutterpose.errors import InputError
from cutterpose.geometry.pose import (
    Pose,
    euler_deg_from_rotation,
    geodesic_deg,
    nearest_rotation,
    pose_errors,
    rotation_from_euler_deg,
    wrap_deg,
)


def _rx(a):
    c, s = np.cos(np.radians(a)), np.sin(np.radians(a))
    return np.array([[1, 0, 0], [0, c, -s], [0, s, c]])


def _ry(a):
    c, s = np.cos(np.radians(a)), np.sin(np.radians(a))
    return np.array([[c, 0, s], [0, 1, 0], [-s, 0, c]])


def _rz(a):
    c, s = np.cos(np.radians(a)), np.sin(np.radians(a))
    return np.array([[c, -s, 0], [s, c, 0], [0, 0, 1]])


@given(st.floats(-179, 179), st.floats(-89, 89), st.floats(-179, 179))
@settings(max_examples=200)
def test_euler_convention_and_round_trip(a, b, g):
    R = rotation_from_euler_deg(a, b, g)
    assert np.allclose(R, _rz(g) @ _ry(b) @ _rx(a), atol=1e-12)
    assert np.allclose(euler_deg_from_rotation(R), [a, b, g], atol=1e-7)


def test_property_tests_draw_the_same_inputs_every_run():
    """The suite's Hypothesis profile (tests/conftest.py) is derandomized: the same test draws
    the same examples in every run, here and in CI's clean clone."""
    from conftest import HYPOTHESIS_PROFILE

    seen = []

    @given(st.floats(-179, 179), st.floats(-89, 89))
    @settings(max_examples=20)
    def draw(a, b):
        seen.append((a, b))

    draw()
    first, seen[:] = list(seen), []
    draw()
    assert HYPOTHESIS_PROFILE == "ci" or not os.environ.get("CI")
    if HYPOTHESIS_PROFILE == "ci":
        assert settings().derandomize and settings().database is None
        assert seen == first and len(set(first)) > 5


def test_nominal_pose_maps_holder_x_to_image_rows(cam_syn, holder):
    p = Pose.nominal()
    px = cam_syn.project(p.apply([[100.0, 0, 0], [0, 100.0, 0]]))
    c = cam_syn.K[:2, 2]
    assert px[0, 0] > c[0] and abs(px[0, 1] - c[1]) < 1e-9  # +X to the right
    assert px[1, 1] > c[1] and abs(px[1, 0] - c[0]) < 1e-9  # +Y downwards


def test_wrap_and_geodesic():
    assert np.allclose(wrap_deg([180, -180, 190, -190, 360, 0.5]), [180, 180, -170, 170, 0, 0.5])
    R1 = rotation_from_euler_deg(10, 20, 30)
    for ang in (1e-7, 0.3, 45, 179.0):
        R2 = R1 @ _rz(ang)
        assert geodesic_deg(R1, R2) == pytest.approx(ang, rel=1e-6, abs=1e-10)


def test_pose_errors_wraps_and_flags():
    Rt = rotation_from_euler_deg([179.5, 0], [0, 0], [0, 0])
    Re = rotation_from_euler_deg([-179.5, 0], [0, 0], [0, 3])
    t = np.array([[0, 0, 600.0], [0, 0, 600.0]])
    te = t + [[0, 0, 0.5], [0, 0, 0]]
    e = pose_errors(Rt, t, Re, te)
    assert e.dof[0, 0] == pytest.approx(1.0)
    assert e.rot_deg[0] == pytest.approx(1.0)
    assert list(e.failed) == [False, True]  # 3 deg rotation error > 2 deg
    e = pose_errors(Rt[:1], t[:1], np.full((1, 3, 3), np.nan), np.full((1, 3), np.nan))
    assert e.failed[0] and np.isnan(e.rot_deg[0])
    e = pose_errors(Rt[:1], t[:1], Rt[:1], t[:1] + [[0, 0, 10.5]])
    assert e.failed[0]


def test_pose_frames_refuse_mismatch():
    a = Pose(np.eye(3), [0, 0, 1], "cam", "holder")
    b = Pose(np.eye(3), [1, 0, 0], "holder", "tool")
    assert (a @ b).from_frame == "tool"
    with pytest.raises(InputError, match="frames"):
        b @ a
    assert np.allclose((a @ a.inverse()).t_mm, 0)
    with pytest.raises(InputError):
        Pose(np.ones((3, 3)), [0, 0, 0])
    with pytest.raises(InputError):
        Pose(np.eye(3), [0, np.nan, 0])


def test_nearest_rotation():
    R = rotation_from_euler_deg(5, -10, 20)
    M = R + 1e-3 * np.random.default_rng(0).normal(size=(3, 3))
    Q = nearest_rotation(M)
    assert np.allclose(Q.T @ Q, np.eye(3)) and np.linalg.det(Q) == pytest.approx(1.0)
    assert geodesic_deg(Q, R) < 0.2


def test_pose_from_plane_homography_recovers_the_pose():
    """Zhang's extrinsics from H ~ K [r1 r2 t], whatever the homography's scale and sign; None
    for a degenerate one."""
    from cutterpose.geometry.pose import pose_from_plane_homography

    K = np.array([[2400.0, 0.0, 2050.0], [0.0, 2400.0, 1500.0], [0.0, 0.0, 1.0]])
    P = Pose.from_euler(4, -7, 20, 15, -8, 640)
    H = K @ np.column_stack([P.R[:, 0], P.R[:, 1], P.t_mm])
    for scale in (1.0, -3e-4, 250.0):
        R, t = pose_from_plane_homography(scale * H, K)
        np.testing.assert_allclose(R, P.R, atol=1e-12)
        np.testing.assert_allclose(t, P.t_mm, atol=1e-9)
    assert pose_from_plane_homography(np.zeros((3, 3)), K) is None
