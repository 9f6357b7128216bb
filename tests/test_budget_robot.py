"""The robot's side of the budget against independent computations (issue 33): the grasp
verdict's figures, shares, reasons and hints on hand-computed covariances, the grasp frame of a
holder file in the chain, and the frame Jacobians against finite differences and sampling."""

from __future__ import annotations

import math

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from cutterpose.geometry.holder import default_holder, holder_from_dict
from cutterpose.geometry.pose import Pose, rotation_from_euler_deg
from cutterpose.robot.frames import PoseCov, euler_rate_matrix
from cutterpose.robot.grasp import (
    CUTTER_RADIUS_MM,
    GraspTolerance,
    GraspVerdict,
    grasp_frame,
    judge,
    refusal_hint,
)

HOLDER = default_holder()


def _blocks(pos_var, ang_var):
    C = np.zeros((6, 6))
    C[:3, :3] = np.diag(pos_var)
    C[3:, 3:] = np.diag(ang_var)
    return C


def test_grasp_figures_shares_and_the_boundary():
    """3-sigma figures of the worst direction (hand: sqrt of the largest variance) and each
    source's share of the variance along it; a figure equal to its limit grasps."""
    meas = _blocks([0.04, 0.01, 0.09], [1e-8, 1e-8, 4e-8])     # worst: z, 0.3 mm
    he = _blocks([0.0, 0.0, 0.03], [0.0, 0.0, 0.0])
    rob = _blocks([0.0, 0.0, 0.0], [0.0, 0.0, 1e-8])
    C = meas + he + rob                                          # z: 0.12 mm^2
    parts = {"measurement": meas, "hand-eye": he, "robot": rob}
    p3 = 3 * math.sqrt(0.12)
    a3 = math.degrees(3 * math.sqrt(5e-8))
    v = judge(C, parts, np.eye(3), GraspTolerance(position_mm=p3, angle_deg=a3))
    assert v.verdict == "grasp" and v.ok and v.reason == "" and v.hint == ""
    assert v.position_3sigma_mm == pytest.approx(p3, rel=1e-12)
    assert v.angle_3sigma_deg == pytest.approx(a3, rel=1e-12)
    assert v.shares == {"position": {"measurement": 0.75, "hand-eye": 0.25, "robot": 0.0},
                        "angle": {"measurement": 0.8, "hand-eye": 0.0, "robot": 0.2}}
    d = v.to_dict()
    assert d == {"verdict": "grasp", "reason": "", "hint": "", "position_3sigma_mm": p3,
                 "angle_3sigma_deg": a3, "position_tolerance_mm": p3,
                 "angle_tolerance_deg": a3, "error_shares": v.shares}
    # shares to three digits: 1/3 each
    third = {k: _blocks([0.01, 0, 0], [1e-8, 0, 0]) for k in ("measurement", "hand-eye",
                                                               "robot")}
    v3 = judge(sum(third.values()), third, np.eye(3))
    assert v3.shares["position"] == {"measurement": 0.333, "hand-eye": 0.333, "robot": 0.333}


def test_grasp_refusal_reasons_and_hints():
    """Over the limit: the reason gives the figure, the limit, the 3 sigma along the camera's
    axes and the shares; the hint follows the largest source and the weakest camera axis."""
    R_cam_base = np.array([[0.0, 1.0, 0.0], [0.0, 0.0, 1.0], [1.0, 0.0, 0.0]])
    # base x is the camera's z (depth): the measurement's depth dominates
    meas = _blocks([0.25, 0.01, 0.01], [1e-10] * 3)
    parts = {"measurement": meas, "hand-eye": np.zeros((6, 6)), "robot": np.zeros((6, 6))}
    v = judge(meas, parts, R_cam_base)
    assert v.verdict == "retake" and not v.ok
    assert v.reason == ("position 3-sigma 1.5 mm > 1 mm (camera x 0.30, y 0.30, z 1.50 mm; "
                        "measurement 100 %, hand-eye 0 %, robot 0 %)")
    assert v.hint == "move the camera closer to the holder (depth is the weakest direction)"
    # the same along the camera's x: not depth
    v = judge(_blocks([0.01, 0.25, 0.01], [1e-10] * 3), parts | {
        "measurement": _blocks([0.01, 0.25, 0.01], [1e-10] * 3)}, R_cam_base)
    assert v.hint == "move closer, focus, and light the holder's edges evenly"
    # a tilt (camera x axis) from the measurement: the edges
    ang = _blocks([1e-4] * 3, [0.0, 4e-6, 0.0])                 # base y = camera x
    v = judge(ang, parts | {"measurement": ang}, R_cam_base)
    a3 = math.degrees(3 * 2e-3)
    lim = math.degrees(1.0 / CUTTER_RADIUS_MM)
    assert v.reason == (f"angle 3-sigma {a3:.3g} deg > {lim:.3g} deg (camera x "
                        f"{a3:.2f}, y 0.00, z 0.00 deg; measurement 100 %, hand-eye 0 %, "
                        f"robot 0 %)")
    assert v.hint == ("move closer and light the lower edge evenly (the holder's tilt comes "
                      "from its edges)")
    # a turn about the camera's axis (z): not the tilt
    spin = _blocks([1e-4] * 3, [4e-6, 0.0, 0.0])                # base x = camera z
    assert judge(spin, parts | {"measurement": spin}, R_cam_base).hint == \
        "move closer, focus, and light the holder's edges evenly"
    # the hand-eye or the robot dominating, both figures over: both reasons, both hints
    he = _blocks([4.0, 0, 0], [0, 0, 0])
    rob = _blocks([0, 0, 0], [1e-4, 0, 0])
    v = judge(he + rob, {"measurement": np.zeros((6, 6)), "hand-eye": he, "robot": rob},
              np.eye(3))
    assert v.reason.startswith("position 3-sigma 6 mm > 1 mm (") and "; angle 3-sigma " in \
        v.reason
    assert v.hint == ("redo the hand-eye calibration with more stations and more rotation; "
                      "the robot's stated accuracy alone exceeds the tolerance: calibrate the "
                      "robot or widen the tolerance")
    # no usable uncertainty
    bad = np.full((6, 6), np.inf)
    v = judge(bad, {"measurement": bad}, np.eye(3))
    assert v.verdict == "retake" and v.reason == "the pose has no usable uncertainty"
    assert v.hint == "move the camera closer to the holder and retake"
    assert v.position_3sigma_mm == math.inf and v.shares == {"position": {}, "angle": {}}


def test_nan_figures_are_none_in_json():
    d = GraspVerdict("retake", "x").to_dict()
    assert d["position_3sigma_mm"] is None and d["angle_3sigma_deg"] is None
    assert d["angle_tolerance_deg"] == pytest.approx(math.degrees(1.0 / 216.0), rel=1e-12)
    assert GraspTolerance(angle_deg=0.5).angle_limit_deg == 0.5


@pytest.mark.parametrize("reason, hint_starts", [
    ("pose outside the working range: alpha_deg=12.0", "move the robot so that the holder"),
    ("planar AMBIGUITY: a second pose", "tilt the camera by 5-10 deg"),
    ("edges worn", "light the holder's edges evenly from the front"),
    ("corner residual RMS 2.1 px", "light the lower edge and clean"),
    ("a corner is 5 px off the model", "light the lower edge and clean"),
    ("error budget: rotation uncertain by", "move the camera closer to the holder and retake"),
    ("no pose: not solved", "check that the whole holder is in view, lit and in focus"),
])
def test_refusal_hints(reason, hint_starts):
    assert refusal_hint(reason).startswith(hint_starts)


def test_holder_file_grasp_frame_is_used_in_the_chain(cam_t1):
    """A holder file's grasp frame is ``T_holder_grasp``: the robot gets
    ``T_base_holder @ T_holder_grasp`` and the covariance moved to that point."""
    from types import SimpleNamespace

    from cutterpose.calibration.handeye import HandEye
    from cutterpose.pipeline import Quality
    from cutterpose.robot import locate

    h = holder_from_dict(HOLDER.to_dict() | {"grasp_frame": {"position_mm": [150, 0, 40],
                                                             "euler_deg": [0, 0, 90]}})
    T_hg = grasp_frame(h)
    assert T_hg.name == "T_holder_grasp"
    np.testing.assert_allclose(T_hg.t_mm, [150, 0, 40])
    np.testing.assert_allclose(T_hg.R, rotation_from_euler_deg(0, 0, 90), atol=1e-12)
    ident = grasp_frame(HOLDER)
    assert ident.name == "T_holder_grasp" and np.all(ident.R == np.eye(3)) and \
        np.all(ident.t_mm == 0)
    A = Pose.from_euler(10, -20, 30, 1200, -100, 700, to_frame="base", from_frame="flange")
    X = Pose.from_euler(0.5, -1, 90, 80, -40, 150, to_frame="flange", from_frame="cam")
    pose = Pose.from_euler(2, -3, 4, 8, -6, 612)
    m = SimpleNamespace(pose=pose, std_dof=np.array([0.02, 0.02, 0.02, 0.05, 0.05, 0.1]),
                        ok=True, quality=Quality(True, ""))
    he = HandEye(X, Pose(np.eye(3), [1000, 0, 0], "base", "plate"), np.zeros((6, 6)))
    r0 = locate(m, he, A, camera=cam_t1, holder=HOLDER)
    r = locate(m, he, A, camera=cam_t1, holder=h)
    expect = A @ X @ pose.with_frames("cam", "holder") @ T_hg
    np.testing.assert_allclose(r.T_base_grasp.pose.matrix, expect.matrix, atol=1e-9)
    # 150 mm off the origin the rotation's uncertainty adds to the position's
    assert r.grasp.position_3sigma_mm > 1.05 * r0.grasp.position_3sigma_mm


def test_euler_rate_matrix_against_finite_differences():
    """``dR R^T`` of the Euler angles by central differences: W's columns, rad per deg."""
    e = np.array([15.0, -25.0, 40.0])
    W = euler_rate_matrix(*e)
    R = rotation_from_euler_deg(*e)
    h = 1e-4
    for k in range(3):
        dk = np.eye(3)[k] * h
        S = (rotation_from_euler_deg(*(e + dk)) - rotation_from_euler_deg(*(e - dk))) \
            / (2 * h) @ R.T
        np.testing.assert_allclose(W[:, k], [S[2, 1], S[0, 2], S[1, 0]], atol=1e-9)


def test_inverse_covariance_against_sampling():
    """The inverse's full covariance, cross terms included, against sampled inverses."""
    rng = np.random.default_rng(8)
    T = Pose(Rotation.from_euler("xyz", [30, -20, 60], degrees=True).as_matrix(),
             [400, -250, 900], "base", "cam")
    L = np.diag([0.3, 0.2, 0.5, 1e-3, 2e-3, 1.5e-3]) @ (np.eye(6) + 0.5 * rng.normal(size=(6, 6)))
    pc = PoseCov(T, L @ L.T)
    n = 40000
    d = rng.multivariate_normal(np.zeros(6), pc.cov, n)
    R = Rotation.from_rotvec(d[:, 3:]).as_matrix() @ T.R
    t = T.t_mm + d[:, :3]
    Ri = np.swapaxes(R, 1, 2)
    ti = -np.einsum("nij,nj->ni", Ri, t)
    Ti = T.inverse()
    di = np.concatenate([ti - Ti.t_mm, Rotation.from_matrix(Ri @ Ti.R.T).as_rotvec()], axis=1)
    C = np.cov(di.T)
    inv = pc.inverse().cov
    s = np.sqrt(np.diag(inv))
    np.testing.assert_allclose(np.sqrt(np.diag(C)), s, rtol=0.03)
    assert np.abs(C / np.outer(s, s) - inv / np.outer(s, s)).max() < 0.03


def test_measurement_covariance_uses_a_given_one_and_refuses_without_a_pose(cam_t1):
    """A measurement that carries its DOF covariance (``cov_dof``) gives it unchanged; one
    without a pose, or without a finite std, gives none; otherwise the std with the
    correlations of ``(J^T J)^-1`` (the diagonal is the std's square)."""
    from types import SimpleNamespace

    from cutterpose.robot import measurement_covariance

    pose = Pose.from_euler(2, -3, 4, 8, -6, 612)
    C = np.diag([1e-4, 2e-4, 3e-4, 0.01, 0.02, 0.05])
    C[1, 3] = C[3, 1] = 1e-3
    m = SimpleNamespace(pose=pose, std_dof=np.full(6, np.nan), cov_dof=C.tolist())
    got = measurement_covariance(m, cam_t1, HOLDER)
    assert got.dtype == float and np.array_equal(got, C)
    std = np.array([0.01, 0.01, 0.01, 0.02, 0.02, 0.05])
    assert measurement_covariance(SimpleNamespace(pose=None, std_dof=std), cam_t1,
                                  HOLDER) is None
    assert measurement_covariance(SimpleNamespace(pose=pose, std_dof=std * np.nan), cam_t1,
                                  HOLDER) is None
    got = measurement_covariance(SimpleNamespace(pose=pose, std_dof=list(std)), cam_t1, HOLDER)
    np.testing.assert_allclose(np.sqrt(np.diag(got)), std, rtol=1e-12)


def test_covariance_checks_and_messages():
    """A covariance must be a finite 6x6 PSD matrix; its tolerance on negative eigenvalues is
    relative to the matrix's scale (1e-9 of its largest entry, at least 1e-9)."""
    from cutterpose.errors import InputError
    from cutterpose.robot.frames import cov_from_own_axes

    T = Pose(np.eye(3), [0, 0, 0], "base", "cam")
    with pytest.raises(InputError, match=r"^covariance of T_base_cam must be a finite 6x6"):
        PoseCov(T, np.eye(5))
    with pytest.raises(InputError, match=r"^covariance must be a finite 6x6 matrix, got shape "
                                         r"\(6, 6\)"):
        cov_from_own_axes(T, np.full((6, 6), np.nan))
    with pytest.raises(InputError, match=r"^covariance of T_base_cam is not positive semi"):
        PoseCov(T, np.diag([1.0, 1, 1, 1, 1, -0.5]))
    big = np.diag([1e6] * 5 + [-1e-4])                         # -1e-4 > -1e-9 * 1e6: round-off
    np.testing.assert_array_equal(PoseCov(T, big).cov, big)
    with pytest.raises(InputError, match="not positive semi-definite"):
        PoseCov(T, np.diag([0.5] * 5 + [-1.5e-9]))              # scale < 1: 1e-9 absolute
    PoseCov(T, np.diag([0.5] * 5 + [-0.5e-9]))


def test_ros_dict_keys_and_quaternion_sign():
    """The ROS form: w >= 0 always (q and -q are the same turn), the keys the ROS message is
    filled from."""
    for deg in (10.0, 190.0, 350.0, -170.0):
        R = _turn_z(deg)
        d = PoseCov(Pose(R, [1000.0, -20.0, 5.0], "base", "grasp"),
                    np.diag([0.01, 0.01, 0.04, 1e-6, 1e-6, 4e-6])).to_ros_dict()
        q = np.array(d["orientation_xyzw"])
        assert q[3] >= 0
        np.testing.assert_allclose(Rotation.from_quat(q).as_matrix(), R, atol=1e-12)
    assert set(d) == {"frame_id", "child_frame_id", "position_m", "position_mm",
                      "orientation_xyzw", "covariance_ros", "covariance_units",
                      "covariance_mm_rad", "position_3sigma_mm", "angle_3sigma_deg"}
    assert d["covariance_units"].startswith("ROS: m^2, m*rad, rad^2; order x, y, z, rot x")
    assert d["position_3sigma_mm"] == pytest.approx(0.6)
    assert d["angle_3sigma_deg"] == pytest.approx(math.degrees(6e-3))
    # w == 0 exactly (a half turn): kept as it is
    d = PoseCov.exact(Pose(_turn_z(180.0), [0, 0, 0], "base", "grasp")).to_ros_dict()
    assert d["orientation_xyzw"][3] == pytest.approx(0.0, abs=1e-15)


def _turn_z(deg):
    return Rotation.from_euler("z", deg, degrees=True).as_matrix()


def test_no_usable_uncertainty_in_the_angle_alone():
    """A finite position block but a non-finite rotation block: still no usable uncertainty,
    with the tolerance and both figures reported."""
    C = _blocks([0.01] * 3, [1e-8] * 3)
    C[3:, 3:] = np.nan
    v = judge(C, {"measurement": C}, np.eye(3), GraspTolerance(position_mm=2.0))
    assert v.verdict == "retake" and v.reason == "the pose has no usable uncertainty"
    assert v.position_3sigma_mm == pytest.approx(0.3) and v.angle_3sigma_deg == math.inf
    assert v.tolerance == GraspTolerance(position_mm=2.0)
    ok = judge(_blocks([0.01] * 3, [1e-10] * 3), {}, np.eye(3), GraspTolerance(position_mm=2.0))
    assert ok.ok and ok.tolerance.position_mm == 2.0
    assert ok.angle_3sigma_deg == pytest.approx(math.degrees(3e-5))
