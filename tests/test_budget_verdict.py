"""The verdict on a measurement against its limits, each check at its boundary (issue 33).

One rendered image is measured with a corner method (RPnP); every limit of
:class:`~cutterpose.pipeline.QualityLimits` is then set just above and just below the figure
the measurement itself reports (residual RMS, worst corner, each DOF against the working range,
planar ambiguity, std, the budget's 3-sigma figures), and the verdict must flip there, with the
reason naming the check. The figures are recomputed here from the returned pose and corners
where they can be (the residuals by projecting the holder through ``K``).
"""

from __future__ import annotations

import math
from dataclasses import replace

import numpy as np
import pytest

from cutterpose.budget import Tolerance
from cutterpose.geometry.holder import default_holder
from cutterpose.geometry.pose import Pose
from cutterpose.image import detect_features
from cutterpose.pipeline import measure_features
from cutterpose.render.analytic import render_holder
from cutterpose.verdict import DOF_NAMES, QualityLimits
from test_features import small_camera

HOLDER = default_holder()
TRUE = Pose.from_euler(-2, 3, -4, -6, 5, 590)
#: every check passes: only the limit a test sets can refuse
OPEN = QualityLimits(max_rms_px=100.0, max_corner_residual_px=100.0, max_ambiguity_ratio=1.0,
                     range_half_width_dof=(90.0, 90.0, 180.0, 500.0, 500.0, 1000.0),
                     max_std_dof=(100.0,) * 6, tolerance=Tolerance(100.0, 100.0),
                     edge_break_mm=0.0)
METHOD = "rpnp"  # a PnP: its solve does not depend on the limits; two candidates
UP, DOWN = 1.0 + 1e-6, 1.0 - 1e-6


@pytest.fixture(scope="module")
def case():
    cam = small_camera()
    f = detect_features(render_holder(TRUE, cam, HOLDER, "easy", seed=11).image, cam, HOLDER)
    m = measure_features(f, cam, HOLDER, METHOD, OPEN)
    assert m.ok, m.quality.reason
    return cam, f, m


def _verdict(case, **limits):
    cam, f, _ = case
    return measure_features(f, cam, HOLDER, METHOD, replace(OPEN, **limits)).quality


def _residuals(case):
    """Detected minus projected corners (ideal px) at the returned pose, by hand through K."""
    cam, f, m = case
    X = HOLDER.points_holder_mm @ m.pose.R.T + m.pose.t_mm
    proj = X[:, :2] / X[:, 2:] @ cam.K[:2, :2].T + cam.K[:2, 2]
    det = np.asarray(f.corners_ideal_px, float)
    # match each projected corner with its nearest detection (the model's order)
    d = np.linalg.norm(det[None, :, :] - proj[:, None, :], axis=2)
    return det[np.argmin(d, axis=1)] - proj


def test_residual_rms_limit(case):
    r = _residuals(case)
    rms = math.sqrt(np.mean(np.sum(r ** 2, axis=1)))
    assert case[2].quality.rms_px == pytest.approx(rms, rel=1e-6)
    assert _verdict(case, max_rms_px=rms * UP).ok
    q = _verdict(case, max_rms_px=rms * DOWN)
    assert not q.ok and q.reason == (f"corner residual RMS {rms:.2f} px > {rms * DOWN} px: the "
                                     "corners do not fit the holder model")


def test_worst_corner_limit(case):
    worst = float(np.linalg.norm(_residuals(case), axis=1).max())
    assert _verdict(case, max_corner_residual_px=worst * UP).ok
    q = _verdict(case, max_corner_residual_px=worst * DOWN)
    assert not q.ok and q.reason == (f"a corner is {worst:.2f} px off the model (> "
                                     f"{worst * DOWN} px)")


@pytest.mark.parametrize("k", range(6))
def test_working_range_limit_per_dof(case, k):
    """DOF ``k`` just inside and just outside ``centre +- (half width + tolerance)``, on each
    side; the refusal names the DOF and its value."""
    dof = case[2].pose.dof
    half, tol = 0.5, 0.25
    for side in (+1, -1):
        for margin, ok in ((-1e-6, True), (1e-6, False)):
            centre = list(OPEN.range_center_dof)
            # dof[k] sits `margin` outside centre + side (half + tol)
            centre[k] = dof[k] - side * (half + tol + margin)
            hw, tw = list(OPEN.range_half_width_dof), list(OPEN.range_tolerance_dof)
            hw[k], tw[k] = half, tol
            for j in range(6):  # the other DOFs stay inside
                if j != k:
                    centre[j] = dof[j]
            q = _verdict(case, range_center_dof=tuple(centre), range_half_width_dof=tuple(hw),
                         range_tolerance_dof=tuple(tw))
            assert q.ok is ok, (k, side, margin, q.reason)
            if not ok:
                assert q.reason == f"pose outside the working range: {DOF_NAMES[k]}={dof[k]:.1f}"


def test_ambiguity_limit(case):
    amb = case[2].quality.ambiguity_ratio
    assert 0.0 < amb < 1.0
    assert _verdict(case, max_ambiguity_ratio=amb * UP).ok
    q = _verdict(case, max_ambiguity_ratio=amb * DOWN)
    assert not q.ok and q.reason == (f"planar ambiguity: a second pose fits almost as well "
                                     f"(ratio {amb:.2f} > {amb * DOWN})")


@pytest.mark.parametrize("k", [0, 5])
def test_std_limit(case, k):
    std = case[2].std_dof
    lim = np.full(6, 100.0)
    lim[k] = std[k] * UP
    assert _verdict(case, max_std_dof=tuple(lim)).ok
    lim[k] = std[k] * DOWN
    q = _verdict(case, max_std_dof=tuple(lim))
    assert not q.ok and q.reason == f"pose too uncertain: std {np.round(std, 3).tolist()}"


def test_budget_tolerance_and_std_agree(case):
    """The std the verdict checks is the budget's; its figures flip the verdict at the
    tolerance."""
    m = case[2]
    b = m.quality.budget
    np.testing.assert_allclose(m.std_dof, np.sqrt(np.diag(b.dof_cov)))
    pos, ang = b.position_3sigma_mm, b.angle_3sigma_deg
    assert _verdict(case, tolerance=Tolerance(pos * UP, ang * UP)).ok
    q = _verdict(case, tolerance=Tolerance(pos * DOWN, ang * UP))
    assert not q.ok and q.reason.startswith(
        f"error budget: position at the grasp point uncertain by {pos:.2f} mm (3 sigma) > "
        f"{pos * DOWN} mm; largest part: ")
    q = _verdict(case, tolerance=Tolerance(pos * UP, ang * DOWN))
    assert not q.ok and q.reason.startswith(f"error budget: rotation uncertain by {ang:.3f} deg")


# ---- the corner methods' budget parts, against a non-linear re-fit ----------------------------
def _project_dof(dof, P, K):
    from cutterpose.geometry.pose import rotation_from_euler_deg

    X = P @ rotation_from_euler_deg(*dof[:3]).T + dof[3:]
    return X[:, :2] / X[:, 2:] @ K[:2, :2].T + K[:2, 2]


def _refit(dof0, P, K, target_px):
    """The least-squares pose of the design corners ``P`` against ``target_px`` (scipy's
    Levenberg-Marquardt with its own finite differences), started at ``dof0``."""
    from scipy.optimize import least_squares

    fit = least_squares(lambda d: (_project_dof(d, P, K) - target_px).ravel(), dof0,
                        method="lm", xtol=1e-14, ftol=1e-14)
    return fit.x


def _moved_corners(holder, offset_mm):
    """Every edge line moved ``offset_mm`` outwards, the corners their intersections (made
    here from the corner list: the lines' normals and homogeneous intersections)."""
    c = holder.corners_mm
    d = np.roll(c, -1, axis=0) - c                               # edge i: corner i -> i + 1
    n = np.column_stack([d[:, 1], -d[:, 0]]) / np.linalg.norm(d, axis=1)[:, None]
    # the pocket is not convex: the winding (signed area) tells outward from inward
    area = 0.5 * np.sum(c[:, 0] * np.roll(c[:, 1], -1) - np.roll(c[:, 0], -1) * c[:, 1])
    n = n if area > 0 else -n
    L = np.column_stack([n, -(np.sum(n * c, axis=1) + offset_mm)])   # n . x + c' = 0
    X = np.cross(np.roll(L, 1, axis=0), L)                       # corner i: edges i-1, i
    xy = X[:, :2] / X[:, 2:]
    return np.column_stack([xy, np.zeros(len(xy))])


@pytest.mark.parametrize("offset_mm, unseen", [(0.2, ()), (0.3, (0, 5, 11))])
def test_edge_break_effect_is_the_refit_shift(cam_t1, offset_mm, unseen):
    """The pose shift a corner fit suffers when every edge is seen ``offset_mm`` outside the
    design edge: the linearised figure equals a non-linear re-fit to the moved corners'
    image (over the seen corners)."""
    from cutterpose.solvers.corners import edge_break_effect

    pose = Pose.from_euler(4, -6, 8, 12, -9, 620)
    seen = np.ones(HOLDER.n_corners, bool)
    seen[list(unseen)] = False
    target = _project_dof(pose.dof, _moved_corners(HOLDER, offset_mm), cam_t1.K)
    shift = _refit(pose.dof, HOLDER.points_holder_mm[seen], cam_t1.K, target[seen]) - pose.dof
    got = edge_break_effect(pose, cam_t1, HOLDER, seen, offset_mm)
    assert abs(shift[5]) > 0.5                                   # mostly depth
    np.testing.assert_allclose(got, shift, rtol=0.02, atol=2e-3 * np.abs(shift).max())


def test_fit_offset_and_pose_std_against_a_refit(cam_t1):
    """``fit_offset``: the step from a pose to the corners' least-squares pose (a non-linear
    re-fit here); ``pose_std``: ``s^2 (J^T J)^-1`` with a finite-difference Jacobian and
    ``s^2 = |r|^2 / (2n - 6)``."""
    from cutterpose.solvers.corners import fit_offset, pose_std

    rng = np.random.default_rng(3)
    truth = Pose.from_euler(3, 5, -7, -10, 6, 610)
    P = HOLDER.points_holder_mm
    corners = _project_dof(truth.dof, P, cam_t1.K) + rng.normal(0, 0.3, (len(P), 2))
    corners[7] = np.nan                                          # one corner not seen
    seen = np.isfinite(corners).all(axis=1)
    ls = _refit(truth.dof, P[seen], cam_t1.K, corners[seen])
    near = Pose.from_euler(*(ls + [0.03, -0.02, 0.01, 0.2, -0.1, 0.5]))
    step = fit_offset(near, corners, cam_t1, HOLDER, order="holder")
    np.testing.assert_allclose(near.dof + step, ls, atol=2e-3)
    std, r = pose_std(Pose.from_euler(*ls), corners, cam_t1, HOLDER, order="holder")
    r_hand = corners[seen] - _project_dof(ls, P[seen], cam_t1.K)
    np.testing.assert_allclose(r, r_hand, atol=1e-6)
    h = np.array([1e-5] * 3 + [1e-4] * 3)
    J = np.column_stack([(_project_dof(ls + h[k] * np.eye(6)[k], P[seen], cam_t1.K)
                          - _project_dof(ls - h[k] * np.eye(6)[k], P[seen], cam_t1.K)).ravel()
                         / (2 * h[k]) for k in range(6)])
    s2 = np.sum(r_hand ** 2) / (r_hand.size - 6)
    np.testing.assert_allclose(std, np.sqrt(np.diag(s2 * np.linalg.inv(J.T @ J))), rtol=1e-4)
    # fewer than 4 corners: no step
    few = np.full_like(corners, np.nan)
    few[:3] = corners[:3]
    assert np.all(np.isnan(fit_offset(near, few, cam_t1, HOLDER, order="holder")))


def test_corner_budget_parts_are_the_effects_they_name(case):
    """The corner methods' budget holds exactly: ``noise`` ``s^2 (J^T J)^-1`` (finite-
    difference J), ``method`` the step to the least-squares pose as 1 sigma of 2/3 of it,
    ``wear`` the squared wear shifts, ``edge break`` the outer product of the shift of a
    uniform outward offset of a third of the assumed break; no break part for a sharp edge."""
    from cutterpose.solvers.corners import (
        corner_budget,
        edge_break_effect,
        edge_wear_effect,
        fit_offset,
    )

    cam, f, m = case
    pose = m.pose
    limits = replace(OPEN, edge_break_mm=None,                 # unknown: 1.5 mm assumed
                     grasp_point_mm=(300.0, 0.0, 0.0), tolerance=Tolerance(100, 100, 2.0))
    b = corner_budget(m.estimate, f, cam, HOLDER, limits)
    assert set(b.parts) == {"noise", "method", "wear", "edge break"}
    np.testing.assert_array_equal(b.grasp_point_mm, [300.0, 0.0, 0.0])
    np.testing.assert_allclose(b.residuals_px, _residuals(case), atol=1e-9)
    from test_budget import mc_figures
    pos, _, _ = mc_figures(pose.dof, b.dof_cov, (300.0, 0.0, 0.0), k=2.0)
    assert b.position_3sigma_mm == pytest.approx(pos, rel=0.015)
    step = fit_offset(pose, f.corners_ideal_px, cam, HOLDER, order=f.order)
    assert np.abs(step).max() > 1e-4                            # RPnP is not the LS pose
    np.testing.assert_allclose(b.parts["method"], 4.0 / 9.0 * np.outer(step, step),
                               rtol=1e-9, atol=1e-15)
    bias, _ = edge_wear_effect(pose, f, cam, HOLDER)
    assert np.any(bias > 0)
    np.testing.assert_allclose(b.parts["wear"], np.diag(bias ** 2), rtol=1e-12)
    seen = np.isfinite(_residuals(case)).all(axis=1)
    s = edge_break_effect(pose, cam, HOLDER, seen, 0.5)
    np.testing.assert_allclose(b.parts["edge break"], np.outer(s, s), rtol=1e-6,
                               atol=1e-12 * np.abs(s).max() ** 2)
    r = _residuals(case)
    P = HOLDER.points_holder_mm
    h = np.array([1e-5] * 3 + [1e-4] * 3)
    J = np.column_stack([(_project_dof(pose.dof + h[k] * np.eye(6)[k], P, cam.K)
                          - _project_dof(pose.dof - h[k] * np.eye(6)[k], P, cam.K)).ravel()
                         / (2 * h[k]) for k in range(6)])
    np.testing.assert_allclose(b.parts["noise"],
                               np.sum(r ** 2) / (r.size - 6) * np.linalg.inv(J.T @ J),
                               rtol=1e-4, atol=1e-12)
    sharp = corner_budget(m.estimate, f, cam, HOLDER, replace(OPEN, edge_break_mm=0.0))
    assert "edge break" not in sharp.parts
    small = corner_budget(m.estimate, f, cam, HOLDER, replace(OPEN, edge_break_mm=0.6))
    s = edge_break_effect(pose, cam, HOLDER, seen, 0.2)
    np.testing.assert_allclose(small.parts["edge break"], np.outer(s, s), rtol=1e-6,
                               atol=1e-12 * np.abs(s).max() ** 2)


def test_no_pose_or_no_budget_is_refused_with_the_reason(case):
    """No estimate, a failed one, or a pose without a budget: refused, saying why; and the
    verdict's JSON gives each figure (NaN as null)."""
    import json

    from cutterpose.solvers.estimate import PoseEstimate
    from cutterpose.verdict import Quality, verdict

    q = verdict(None, None, OPEN, ambiguity=0.4)
    assert (q.ok, q.reason, q.ambiguity_ratio) == (False, "no pose: not solved", 0.4)
    q = verdict(PoseEstimate.failure("rpnp", "too few corners"), None, OPEN)
    assert (q.ok, q.reason) == (False, "no pose: too few corners")
    m = case[2]
    q = verdict(m.estimate, None, OPEN)
    assert (q.ok, q.reason) == (False, "no pose: no error budget")
    ok = verdict(m.estimate, m.quality.budget, OPEN, ambiguity=0.25, edge_offset_px=0.05)
    assert ok.ok and ok.reason == "" and ok.edge_offset_px == 0.05 and ok.note == ""
    d = json.loads(json.dumps(Quality(False, "x", 0.5, np.nan, np.array([0.1, 0, 0, 0, 0, 2.0]),
                                      0.3, "n").to_dict()))
    assert d == {"ok": False, "reason": "x", "rms_residual_px": 0.5, "ambiguity_ratio": None,
                 "note": "n", "edge_offset_px": 0.3,
                 "edge_bias": {"alpha_deg": 0.1, "beta_deg": 0.0, "gamma_deg": 0.0,
                               "X_mm": 0.0, "Y_mm": 0.0, "Z_mm": 2.0}, "budget": None}
    d = Quality(True, "", np.inf, 0.2, None, np.nan, budget=m.quality.budget).to_dict()
    assert d["rms_residual_px"] is None and d["ambiguity_ratio"] == 0.2
    assert d["edge_bias"] is None and d["edge_offset_px"] is None
    assert d["budget"] == m.quality.budget.to_dict()
