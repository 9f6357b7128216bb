"""ASPnP, OPnP and the Macaulay polynomial solver they share."""

from __future__ import annotations

import importlib.util
from pathlib import Path

import numpy as np
import pytest

from cutterpose.errors import DegenerateInputError, InputError
from cutterpose.geometry.camera import default_camera
from cutterpose.geometry.holder import default_holder
from cutterpose.geometry.pose import Pose, pose_errors, rotation_from_euler_deg
from cutterpose.methods import get_method
from cutterpose.solvers.pnp import aspnp, opnp
from cutterpose.solvers.pnp.polysolve import MacaulaySolver, PolySystem, monomials
from test_pnp_linear import assert_no_confident_pose

CAM = default_camera("synthetic")
HOLDER = default_holder()
SOLVERS = {"aspnp": aspnp.solve, "opnp": opnp.solve}


def _poses(rng, n, tilt=None):
    """Protocol poses; ``tilt='fronto'``: alpha, beta within 0.5 deg; ``'strong'``: one of
    them at +-60 deg."""
    out = []
    while len(out) < n:
        a, b, g = rng.uniform(-60, 60, 3)
        if tilt == "fronto":
            a, b = rng.uniform(-0.5, 0.5, 2)
        elif tilt == "strong":
            a = 60.0 * rng.choice([-1, 1])
            b = rng.uniform(-10, 10)
        pose = Pose.from_euler(a, b, g, *rng.uniform(-90, 90, 2), 600 + rng.uniform(-90, 90))
        out.append(pose)
    return out


def _points(rng, planar):
    P = HOLDER.points_holder_mm.copy()
    if not planar:
        P[:, 2] = rng.uniform(-50, 50, len(P))
    return P


def _project(pose, P):
    px = CAM.project(pose.apply(P))
    return px if np.all(CAM.in_image(px)) else None


# ---- the quaternion parameterisation -------------------------------------------------------

def test_rbar_is_scaled_rotation_and_linear_in_mu():
    rng = np.random.default_rng(0)
    q = rng.standard_normal((5, 4))
    Rb = aspnp.rbar(q)
    n2 = np.sum(q ** 2, axis=1)
    R = Rb / n2[:, None, None]
    assert np.allclose(R @ np.swapaxes(R, 1, 2), np.eye(3), atol=1e-12)
    assert np.allclose(np.linalg.det(R), 1.0)
    p = rng.standard_normal((7, 3))
    L = aspnp.l_matrices(p)  # (3, 7, 10)
    for k in range(5):
        assert np.allclose(np.einsum("kim,m->ik", L, aspnp.mu_of(q[k])), p @ Rb[k].T)


# ---- the polynomial solver ------------------------------------------------------------------

def test_macaulay_finds_all_bezout_solutions_of_random_cubics():
    """Random dense cubics in 2 and 3 variables: 9 and 27 distinct roots, each a root."""
    rng = np.random.default_rng(1)
    for k, deg, n_sol in ((2, 7, 9), (3, 8, 27)):
        sup = monomials(k, 3)
        coef = rng.standard_normal((k, len(sup)))
        x, info = MacaulaySolver(sup, deg, n_sol).solve(coef)
        assert x.shape == (n_sol, k)
        assert info["rank_gap"] < 1e-8
        mono = np.prod(x[:, None, :] ** sup[None], axis=-1)
        res = np.abs(mono @ coef.T) / (np.abs(mono) @ np.abs(coef.T))
        assert res.max() < 1e-8
        dist = np.linalg.norm(x[:, None] - x[None], axis=-1) + np.eye(n_sol)
        assert dist.min() > 1e-6  # all distinct: by Bezout these are all the roots


def test_newton_polish_converges_to_root():
    sup = monomials(1, 3)
    coef = np.array([[-6.0, 11.0, -6.0, 1.0]])  # (x-1)(x-2)(x-3)
    x = PolySystem(sup).newton_polish(coef, np.array([[0.9], [2.05], [3.2]]), iterations=8)
    assert np.allclose(x.ravel(), [1, 2, 3], atol=1e-12)


# ---- noise-free recovery --------------------------------------------------------------------

@pytest.mark.parametrize("name", list(SOLVERS))
@pytest.mark.parametrize("planar", [True, False])
@pytest.mark.parametrize("tilt", [None, "fronto", "strong"])
def test_noise_free_recovers_pose(name, planar, tilt):
    rng = np.random.default_rng([len(name), int(planar), [None, "fronto", "strong"].index(tilt)])
    n_done = 0
    for pose in _poses(rng, 12, tilt):
        P = _points(rng, planar)
        px = _project(pose, P)
        if px is None:
            continue
        est = SOLVERS[name](px, CAM, P)
        assert est, est.reason
        e = pose_errors(pose.R, pose.t_mm, est.R_cam_holder, est.t_cam_holder_mm)
        assert e.rot_deg[0] < 1e-6 and e.trans_mm[0] < 1e-6
        assert np.all(np.isfinite(est.R_cam_holder)) and np.isfinite(est.residual_px)
        assert est.info["n_stationary"] >= 1
        n_done += 1
    assert n_done >= 6


@pytest.mark.parametrize("name", list(SOLVERS))
def test_registry_and_info(name):
    rng = np.random.default_rng(5)
    pose = _poses(rng, 1)[0]
    px = CAM.project(pose.apply(HOLDER.points_holder_mm))
    est = get_method(name).solve(px + rng.normal(0, 1.0, px.shape), CAM, HOLDER)
    assert est and est.method == name
    e = pose_errors(pose.R, pose.t_mm, est.R_cam_holder, est.t_cam_holder_mm)
    assert e.rot_deg[0] < 1.0 and e.trans_mm[0] < 5.0
    assert est.info["n_stationary"] >= len(est.candidates) >= 1
    key = "n_minima" if name == "opnp" else "n_minima_case1"
    assert est.info[key] >= 1


def test_planar_twin_is_never_returned():
    """``(R diag(-1,-1,1), -t)`` projects the holder identically; ASPnP finds it as a
    stationary point, the depth test must drop it."""
    rng = np.random.default_rng(7)
    for pose in _poses(rng, 5):
        px = CAM.project(pose.apply(HOLDER.points_holder_mm))
        for solve in SOLVERS.values():
            est = solve(px, CAM, HOLDER)
            for R, t in est.candidates:
                assert np.all(HOLDER.points_holder_mm @ R[2] + t[2] > 0)


def test_opnp_candidates_are_minima_and_stationary():
    rng = np.random.default_rng(8)
    pose = _poses(rng, 1)[0]
    P = HOLDER.points_holder_mm
    m = CAM.normalize_px(CAM.project(pose.apply(P)) + rng.normal(0, 2.0, (20, 2)))
    Pn, _, _ = aspnp.normalise_object(P)
    sp = opnp.stationary_points(Pn, m)
    coef = opnp.gradient_coefficients(sp["G"])
    grad = opnp.SYSTEM.evaluate(coef, sp["q"])
    assert np.abs(grad).max() < 1e-10 * np.abs(coef).max()
    H = opnp.SYSTEM.jacobian(coef, sp["q"][sp["minimum"]])
    assert np.all(np.linalg.eigvalsh(H)[:, 0] > 0)


@pytest.mark.parametrize("name", list(SOLVERS))
def test_scale_and_permutation_invariance(name):
    rng = np.random.default_rng(9)
    pose = _poses(rng, 1)[0]
    P = _points(rng, planar=False)
    px = CAM.project(pose.apply(P)) + rng.normal(0, 1.0, (20, 2))
    est = SOLVERS[name](px, CAM, P)
    est_k = SOLVERS[name](px, CAM, 1e-3 * P)  # metres
    assert np.allclose(est_k.R_cam_holder, est.R_cam_holder, atol=1e-9)
    assert np.allclose(1e3 * est_k.t_cam_holder_mm, est.t_cam_holder_mm, atol=1e-6)
    perm = rng.permutation(20)
    est_p = SOLVERS[name](px[perm], CAM, P[perm])
    assert np.allclose(est_p.R_cam_holder, est.R_cam_holder, atol=1e-9)


def test_four_points_minimal():
    rng = np.random.default_rng(10)
    P = HOLDER.points_holder_mm[[0, 5, 10, 15]]
    for pose in _poses(rng, 3):
        px = CAM.project(pose.apply(P))
        for solve in SOLVERS.values():
            est = solve(px, CAM, P)
            assert est
            e = pose_errors(pose.R, pose.t_mm, est.R_cam_holder, est.t_cam_holder_mm)
            assert e.rot_deg[0] < 1e-6 and e.trans_mm[0] < 1e-6


# ---- degenerate input -----------------------------------------------------------------------

@pytest.mark.parametrize("name", list(SOLVERS))
def test_degenerate_input_raises_typed_errors(name):
    solve = SOLVERS[name]
    P = HOLDER.points_holder_mm
    px = CAM.project(Pose.nominal().apply(P))
    with pytest.raises(DegenerateInputError, match="at least 4"):
        solve(px[:3], CAM, P[:3])
    line = np.column_stack([np.linspace(-50, 50, 8), np.zeros(8), np.zeros(8)])
    with pytest.raises(DegenerateInputError, match="collinear"):
        solve(CAM.project(Pose.nominal().apply(line)), CAM, line)
    for bad in (np.nan, np.inf):
        x = px.copy()
        x[3, 1] = bad
        with pytest.raises(InputError, match="NaN or inf"):
            solve(x, CAM, P)
    with pytest.raises(InputError, match="correspond"):
        solve(px[:10], CAM, P)
    with pytest.raises(InputError, match="shape"):
        solve(px.ravel(), CAM, P)


@pytest.mark.parametrize("name", list(SOLVERS))
def test_points_behind_camera_give_no_confident_pose(name):
    """Image points of a non-planar set seen from behind (all depths < 0) have no exact pose in
    front: the solver must not return one (falsy, or a large residual)."""
    rng = np.random.default_rng(11)
    P = _points(rng, planar=False)
    R = rotation_from_euler_deg(10, -20, 30)
    X = P @ R.T + np.array([0.0, 0.0, -600.0])
    m = X[:, :2] / X[:, 2:]
    px = m * CAM.focal_px + np.array(CAM.K[:2, 2])
    est = SOLVERS[name](px, CAM, P)
    assert_no_confident_pose(est, CAM, P, px, 1.0)
    for Rc, t in est.candidates:
        assert np.all(P @ Rc[2] + t[2] > 0)


# ---- the multi-start proof check (benchmarks/check_stationary.py) on a few instances ---------

def test_global_minimum_never_above_multistart():
    path = Path(__file__).resolve().parents[1] / "benchmarks" / "check_stationary.py"
    spec = importlib.util.spec_from_file_location("check_stationary", path)
    cs = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(cs)
    out = cs.run_check(n_instances=30, n_starts=12, seed=123)
    assert set(out) == {"opnp", "aspnp-case1", "aspnp-case2"}
    for name, o in out.items():
        assert o["n"] == 30
        assert o["worse"] == 0, (name, o)
        assert o["missed_instances"] == 0, (name, o)


@pytest.mark.parametrize("name", list(SOLVERS))
def test_half_turns_exercise_every_aspnp_case(name):
    """180 deg about x, y, z lie in ASPnP's cases 2, 3, 4 (a = 0); 179.99 deg about (1,1,1) is
    case 1 with huge (b, c, d). Both solvers must recover them exactly."""
    rng = np.random.default_rng(12)
    P = rng.uniform(-100, 100, (20, 3))
    t = np.array([0.0, 0.0, 600.0])
    for axis, ang in (((1, 0, 0), 180.0), ((0, 1, 0), 180.0), ((0, 0, 1), 180.0),
                      ((1, 1, 1), 179.99)):
        ax = np.array(axis, float) / np.linalg.norm(axis)
        q = np.r_[np.cos(np.radians(ang) / 2), np.sin(np.radians(ang) / 2) * ax]
        R = aspnp.rbar(q)
        est = SOLVERS[name](CAM.project(P @ R.T + t), CAM, P)
        e = pose_errors(R, t, est.R_cam_holder, est.t_cam_holder_mm)
        assert e.rot_deg[0] < 1e-6 and e.trans_mm[0] < 1e-6
