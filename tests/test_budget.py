"""The verdict's error budget against independent computations (issue 33).

Every figure the budget gives the robot is checked here against a Monte Carlo of the stated DOF
covariance (sample the six DOFs, move the grasp point with the sampled pose, take the spread),
never against the budget's own linear algebra: a wrong sign or a dropped term in the lever arm
``-R [p]x`` changes the sampled spread and fails these tests.
"""

import math

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from cutterpose.budget import (
    COVARIANCE_CAM_ORDER,
    ErrorBudget,
    Tolerance,
    budget_from_dof_cov,
    dof_to_cam_jacobian,
)
from cutterpose.geometry.pose import rotation_from_euler_deg

DOF = np.array([5.0, -8.0, 12.0, 10.0, -5.0, 600.0])
GRASP_MM = np.array([300.0, -50.0, 40.0])
N_MC = 50_000


def correlated_dof_cov(scale: float = 1.0) -> np.ndarray:
    """A DOF covariance (deg, mm) shaped like a monocular pose's: the tilt beta and the shift X
    trade off (the image barely tells them apart), alpha and Y likewise, plus a loose depth."""
    std = scale * np.array([0.05, 0.06, 0.02, 0.15, 0.12, 0.4])
    corr = np.eye(6)
    for i, j, c in ((1, 3, -0.9), (0, 4, 0.85), (2, 5, 0.3), (3, 5, 0.2)):
        corr[i, j] = corr[j, i] = c
    return corr * np.outer(std, std)


def mc_pose_samples(dof, dof_cov, n=N_MC, seed=33):
    """Rotations and translations of ``n`` poses drawn from N(dof, dof_cov) (Euler in deg)."""
    rng = np.random.default_rng(seed)
    s = rng.multivariate_normal(np.asarray(dof, float), dof_cov, size=n)
    return rotation_from_euler_deg(s[:, 0], s[:, 1], s[:, 2]), s[:, 3:]


def mc_figures(dof, dof_cov, grasp_point_mm, k=3.0, n=N_MC, seed=33):
    """Monte Carlo of the budget's figures: (position k-sigma [mm] of the point ``R p + t`` in
    its worst direction, rotation k-sigma [deg] in its worst direction, the (6, 6) covariance of
    (t, w) with ``R_sample = R exp([w]x)``)."""
    Rs, ts = mc_pose_samples(dof, dof_cov, n, seed)
    p = np.asarray(grasp_point_mm, float)
    pos = Rs @ p + ts
    R0 = rotation_from_euler_deg(*np.asarray(dof, float)[:3])
    w = Rotation.from_matrix(np.einsum("ji,njk->nik", R0, Rs)).as_rotvec()
    pos_3s = k * math.sqrt(np.linalg.eigvalsh(np.cov(pos.T))[-1])
    ang_3s = k * math.degrees(math.sqrt(np.linalg.eigvalsh(np.cov(w.T))[-1]))
    return pos_3s, ang_3s, np.cov(np.hstack([ts, w]).T)


def test_grasp_point_figure_matches_monte_carlo_off_the_origin():
    """The position figure at a grasp point 300 mm from the origin is the sampled spread of that
    point under the stated covariance (the lever arm's sign and size matter: a flipped
    ``-R [p]x`` gives 1.2 mm here instead of 0.8 mm)."""
    C = correlated_dof_cov()
    b = budget_from_dof_cov({"noise": C}, DOF, GRASP_MM)
    pos, ang, cov_cam = mc_figures(DOF, C, GRASP_MM)
    assert b.position_3sigma_mm == pytest.approx(pos, rel=0.015)
    assert b.angle_3sigma_deg == pytest.approx(ang, rel=0.015)
    np.testing.assert_allclose(b.covariance_cam, cov_cam, atol=0.01 * np.abs(cov_cam).max())
    np.testing.assert_allclose(b.grasp_point_mm, GRASP_MM)
    # the rotation's share is what moves this figure: at the origin it is the translation's
    pos0, _, _ = mc_figures(DOF, C, np.zeros(3))
    b0 = budget_from_dof_cov({"noise": C}, DOF)
    assert b0.position_3sigma_mm == pytest.approx(pos0, rel=0.015)
    assert b.position_3sigma_mm > 1.1 * b0.position_3sigma_mm


@pytest.mark.parametrize("grasp", [(0.0, 0.0, 200.0), (-150.0, 120.0, 0.0), (0.0, 250.0, -30.0)])
def test_grasp_point_figure_matches_monte_carlo_along_each_axis(grasp):
    """The same at points off the origin along other axes (each column of ``[p]x``)."""
    C = correlated_dof_cov(2.0)
    b = budget_from_dof_cov({"noise": C}, DOF, grasp)
    pos, _, _ = mc_figures(DOF, C, grasp, n=N_MC)
    assert b.position_3sigma_mm == pytest.approx(pos, rel=0.015)


def test_each_part_and_the_sum_against_monte_carlo():
    """Each part's figures are that part's sampled spread; the total is the sum's."""
    C = correlated_dof_cov()
    D = np.diag([0.01, 0.002, 0.03, 0.05, 0.3, 0.02]) ** 2
    b = budget_from_dof_cov({"noise": C, "model": D}, DOF, GRASP_MM, Tolerance(k_sigma=2.0))
    np.testing.assert_allclose(b.dof_cov, C + D)
    for name, cov in (("noise", C), ("model", D)):
        pos, ang, _ = mc_figures(DOF, cov, GRASP_MM, k=2.0, n=N_MC)
        assert b.per_part_3sigma[name][0] == pytest.approx(pos, rel=0.015)
        assert b.per_part_3sigma[name][1] == pytest.approx(ang, rel=0.015)
    pos, ang, _ = mc_figures(DOF, C + D, GRASP_MM, k=2.0, n=N_MC)
    assert b.position_3sigma_mm == pytest.approx(pos, rel=0.015)
    assert b.angle_3sigma_deg == pytest.approx(ang, rel=0.015)


def test_dof_to_cam_jacobian_against_finite_rotation():
    """d(t, w)/d(dof) against a hand-made central difference of ``R^T R(dof + h e_k)``,
    taken through the matrix logarithm's skew part (no rotation-vector library)."""
    dof = np.array([20.0, -35.0, 50.0, 1.0, 2.0, 3.0])
    A = dof_to_cam_jacobian(dof)
    R = rotation_from_euler_deg(*dof[:3])
    h = 1e-3
    for k in range(3):
        e = np.zeros(3)
        e[k] = h
        S = R.T @ (rotation_from_euler_deg(*(dof[:3] + e)) - rotation_from_euler_deg(
            *(dof[:3] - e))) / (2 * h)                 # = [w_k]x, skew to first order
        w = np.array([S[2, 1] - S[1, 2], S[0, 2] - S[2, 0], S[1, 0] - S[0, 1]]) / 2
        np.testing.assert_allclose(A[3:, k], w, atol=1e-7)
        assert np.all(A[:3, k] == 0)
    # a degree of alpha is a turn of pi/180 rad about the holder's x axis at gamma = beta = 0
    np.testing.assert_allclose(dof_to_cam_jacobian([0, 0, 0, 0, 0, 600])[3:, 0],
                               [math.pi / 180, 0, 0], atol=1e-10)
    np.testing.assert_array_equal(A[:3, 3:], np.eye(3))
    np.testing.assert_array_equal(A[3:, 3:], 0)


def test_hand_computed_figures():
    """Hand-computed cases: a pure rotation std about the holder's z axis moves a point on its
    x axis along y by ``|p| sigma``; translations add in quadrature per direction."""
    sig_deg = 0.1
    C = np.diag([0.0, 0.0, sig_deg ** 2, 0.0, 0.0, 0.0])
    b = budget_from_dof_cov({"noise": C}, [0, 0, 0, 0, 0, 600], (200.0, 0.0, 0.0))
    assert b.position_3sigma_mm == pytest.approx(3 * 200 * math.radians(sig_deg), rel=1e-6)
    assert b.angle_3sigma_deg == pytest.approx(3 * sig_deg, rel=1e-6)
    # plus a translation std of 0.2 mm along y: the same direction, quadrature
    C[4, 4] = 0.2 ** 2
    b = budget_from_dof_cov({"noise": C}, [0, 0, 0, 0, 0, 600], (200.0, 0.0, 0.0))
    expect = 3 * math.hypot(0.2, 200 * math.radians(sig_deg))
    assert b.position_3sigma_mm == pytest.approx(expect, rel=1e-6)
    # ... fully anti-correlated with the rotation: they cancel at that point
    s = 200 * math.radians(sig_deg)
    C[2, 4] = C[4, 2] = -sig_deg * s
    C[4, 4] = s ** 2
    b = budget_from_dof_cov({"noise": C}, [0, 0, 0, 0, 0, 600], (200.0, 0.0, 0.0))
    assert b.position_3sigma_mm == pytest.approx(0.0, abs=1e-6)
    # the worst direction, not the mean: std 0.3 mm along z only
    b = budget_from_dof_cov({"t": np.diag([0, 0, 0, 0.1, 0.1, 0.3]) ** 2}, [0, 0, 0, 0, 0, 600])
    assert b.position_3sigma_mm == pytest.approx(0.9, rel=1e-9)
    assert b.angle_3sigma_deg == 0.0
    np.testing.assert_allclose(b.std_dof, [0, 0, 0, 0.1, 0.1, 0.3], atol=1e-15)


def test_no_parts_and_non_finite_parts():
    """No contribution: zero figures; a non-finite one: infinite figures (a refusal)."""
    b = budget_from_dof_cov({}, DOF)
    assert b.position_3sigma_mm == 0.0 and b.angle_3sigma_deg == 0.0 and not b.exceeds(Tolerance())
    bad = correlated_dof_cov()
    bad[5, 5] = np.nan
    b = budget_from_dof_cov({"noise": correlated_dof_cov(), "edge": bad}, DOF)
    assert b.position_3sigma_mm == math.inf and b.angle_3sigma_deg == math.inf
    assert "position" in b.exceeds(Tolerance())


def _budget(pos, ang, per=None):
    return ErrorBudget({}, np.zeros((6, 6)), np.zeros((6, 6)), np.zeros(3), pos, ang,
                       per_part_3sigma=per or {})


@pytest.mark.parametrize("pos, ang, refuses", [
    (1.0, 0.3, ""),                 # at the tolerance: accepted (<=)
    (0.999, 0.299, ""),
    (1.001, 0.1, "position"),
    (0.5, 0.3001, "rotation"),
    (1.5, 0.5, "position"),         # both over: the position is named first
    (math.nan, 0.1, "position"),    # NaN is never within
    (0.1, math.nan, "rotation"),
])
def test_exceeds_at_the_tolerance(pos, ang, refuses):
    why = _budget(pos, ang).exceeds(Tolerance())
    if refuses:
        assert why.startswith(f"error budget: {refuses}")
    else:
        assert why == ""


def test_exceeds_names_the_largest_part_relative_to_the_tolerance():
    """The reason names the part with the largest figures relative to each tolerance
    (position / 1 mm + angle / 0.3 deg), with the figure and the k of the tolerance."""
    per = {"noise": (0.5, 0.05), "model": (0.3, 0.25), "edge": (0.6, 0.0)}
    # relative: noise 0.5 + 0.167 = 0.667, model 0.3 + 0.833 = 1.133, edge 0.6
    why = _budget(1.24, 0.2, per).exceeds(Tolerance(position_mm=1.0, angle_deg=0.3, k_sigma=3))
    assert why == ("error budget: position at the grasp point uncertain by 1.24 mm (3 sigma) "
                   "> 1.0 mm; largest part: model")
    why = _budget(0.2, 0.35, per).exceeds(Tolerance(angle_deg=0.3, k_sigma=2.5))
    assert why == ("error budget: rotation uncertain by 0.350 deg (2.5 sigma) > 0.3 deg; "
                   "largest part: model")
    # with a tighter position tolerance the position-heavy part weighs more
    why = _budget(1.0, 0.1, per).exceeds(Tolerance(position_mm=0.1, angle_deg=3.0))
    assert why.endswith("largest part: edge")
    # no parts to name
    assert _budget(2.0, 0.1).exceeds(Tolerance()).endswith("largest part: ?")


def test_to_dict_reports_the_figures_and_the_covariance():
    C = correlated_dof_cov()
    b = budget_from_dof_cov({"noise": C, "zero": np.zeros((6, 6))}, DOF, GRASP_MM,
                            radius_mm=1.5, radius_std_mm=0.25)
    d = b.to_dict()
    assert d["position_3sigma_mm"] == b.position_3sigma_mm
    assert d["angle_3sigma_deg"] == b.angle_3sigma_deg
    assert d["grasp_point_holder_mm"] == GRASP_MM.tolist()
    assert d["edge_radius_mm"] == 1.5 and d["edge_radius_std_mm"] == 0.25
    np.testing.assert_allclose(list(d["std"].values()), np.sqrt(np.diag(C)))
    assert list(d["std"]) == ["alpha_deg", "beta_deg", "gamma_deg", "X_mm", "Y_mm", "Z_mm"]
    np.testing.assert_allclose(list(d["parts"]["noise"]["std"].values()), np.sqrt(np.diag(C)))
    assert d["parts"]["zero"]["position_3sigma_mm"] == 0.0
    assert d["parts"]["noise"]["position_3sigma_mm"] == b.per_part_3sigma["noise"][0]
    assert d["parts"]["noise"]["angle_3sigma_deg"] == b.per_part_3sigma["noise"][1]
    assert d["covariance_cam"]["order"] == list(COVARIANCE_CAM_ORDER)
    np.testing.assert_allclose(d["covariance_cam"]["matrix"], b.covariance_cam)
    nan = budget_from_dof_cov({"noise": C}, DOF).to_dict()
    assert nan["edge_radius_mm"] is None and nan["edge_radius_std_mm"] is None


def test_singular_fit_part_is_a_refusal_not_an_exception():
    """An infinite part (``budget_from_fit`` on a singular information matrix) refuses."""
    b = budget_from_dof_cov({"noise": np.full((6, 6), np.inf)}, DOF)
    assert b.position_3sigma_mm == math.inf and b.angle_3sigma_deg == math.inf
    assert b.per_part_3sigma["noise"] == (math.inf, math.inf)
    assert b.exceeds(Tolerance()).startswith("error budget: position")


def _linear_fit(rng, n=12, weights=None):
    """A linear stand-in for a corner fit: 7 columns (pose and radius) and the per-edge
    Jacobian ``D`` (corner i moves with edges i-1 and i), as :func:`edge_variation_mm` reads
    them."""
    from types import SimpleNamespace

    J = rng.normal(size=(2 * n, 7))
    D = np.zeros((2 * n, n))
    for i in range(n):
        D[2 * i:2 * i + 2, i] = rng.normal(size=2)
        D[2 * i:2 * i + 2, (i - 1) % n] = rng.normal(size=2)
    w = np.ones(n) if weights is None else np.asarray(weights, float)
    return SimpleNamespace(jacobian=J, weights=w), D


@pytest.mark.parametrize("sigma_e, weighted", [(0.5, False), (0.3, True)])
def test_edge_variation_recovers_the_simulated_spread(sigma_e, weighted):
    """Method of moments against a simulation of its own model: per-edge offsets of std
    ``sigma_e`` and corner noise of ``0.3 / sqrt(w)`` px (``w`` the corner's weight), seen
    through the weighted fit's residual projector; the mean of the estimate's square over 1500
    draws is ``sigma_e^2`` (within 8 %); corners of weight 0 carry no residual."""
    from cutterpose.solvers.radius_budget import edge_variation_mm

    rng = np.random.default_rng(5)
    n = 16
    w = np.ones(n)
    if weighted:
        w = rng.choice([0.25, 1.0, 4.0], n)
        w[[3, 9]] = 0.0
    fit, D = _linear_fit(rng, n, w)
    keep = np.repeat(w > 0, 2)
    sw = np.sqrt(np.repeat(w, 2))[keep]
    Jk = fit.jacobian[keep]
    P = Jk @ np.linalg.pinv(sw[:, None] * Jk) * sw[None, :]     # weighted least squares
    est = []
    for _ in range(1500):
        noise = rng.normal(0, 0.3, 2 * n) / np.sqrt(np.maximum(np.repeat(w, 2), 1e-12))
        y = (D @ rng.normal(0, sigma_e, n) + noise)[keep]
        r = np.full(2 * n, 50.0)   # what an unseen corner holds must not matter
        r[keep] = y - P @ y
        fit.residuals_px = r.reshape(n, 2)
        est.append(edge_variation_mm(fit, D))
    assert np.mean(np.square(est)) == pytest.approx(sigma_e ** 2, rel=0.08)


def test_edge_variation_is_zero_for_noise_alone_or_no_spare_residual():
    from cutterpose.solvers.radius_budget import edge_variation_mm

    rng = np.random.default_rng(6)
    fit, D = _linear_fit(rng, 16)
    Q = np.eye(32) - fit.jacobian @ np.linalg.pinv(fit.jacobian)
    est = []
    for _ in range(300):
        fit.residuals_px = (Q @ rng.normal(0, 0.2, 32)).reshape(16, 2)
        est.append(edge_variation_mm(fit, D))
    # noise alone: the estimate is clipped at zero about half the time, small otherwise
    assert 0.3 < np.mean(np.array(est) == 0.0) < 0.7
    assert np.mean(np.square(est)) < 0.01
    # 4 corners, 7 columns: no residual left over the edges' directions
    fit4, D4 = _linear_fit(rng, 4)
    fit4.residuals_px = rng.normal(size=(4, 2))
    assert edge_variation_mm(fit4, D4) == 0.0


def test_radius_profile_cov_hand_computed():
    """Two radii on the profile: the fitted one (cost c0) and one whose pose is off by ``d`` at
    cost ``c0 + delta``: the spread is ``w / (1 + w) d d^T``, ``w = exp(-delta / (2 s^2))``,
    ``s^2 = c0 / (2 N - 7)`` with N the seen corners."""
    from types import SimpleNamespace

    from cutterpose.solvers.radius_budget import radius_profile_cov

    dof = np.array([1.0, 2.0, 3.0, 4.0, 5.0, 600.0])
    d = np.array([0.1, -0.2, 0.0, 0.3, 0.0, -1.5])
    weights = np.array([1.0] * 10 + [0.0] * 2)         # N = 10 seen: s^2 = c0 / 13
    c0, delta = 26.0, 3.0
    fit = SimpleNamespace(dof=dof, weights=weights,
                          profile=[(1.0, c0, dof.copy()), (2.0, c0 + delta, dof + d)])
    w = math.exp(-delta / (2 * c0 / 13))
    np.testing.assert_allclose(radius_profile_cov(fit), w / (1 + w) * np.outer(d, d),
                               rtol=1e-12)
    # the order of the profile does not matter; no profile: no spread
    fit.profile = fit.profile[::-1]
    np.testing.assert_allclose(radius_profile_cov(fit), w / (1 + w) * np.outer(d, d),
                               rtol=1e-12)
    # few seen corners (2N - 7 = 1) and small costs (s^2 < 1: no floor but 1e-12)
    fit = SimpleNamespace(dof=dof, weights=np.array([1.0] * 4 + [0.0] * 8),
                          profile=[(1.0, 0.02, dof.copy()), (2.0, 0.05, dof + d)])
    w = math.exp(-0.03 / (2 * 0.02 / 1))
    np.testing.assert_allclose(radius_profile_cov(fit), w / (1 + w) * np.outer(d, d),
                               rtol=1e-12)
    fit.profile = []
    assert np.all(radius_profile_cov(fit) == 0) and radius_profile_cov(fit).shape == (6, 6)


def test_band_budget_takes_the_grasp_point_radius_and_inlier_residuals():
    """``dm+b``'s budget: its covariance parts at the limits' grasp point (Monte Carlo of the
    parts' sum there), the band's radius, and as residuals each inlier segment's signed
    distance along its edge normal (weights > 0.5)."""
    from types import SimpleNamespace

    from cutterpose.solvers.edge_band import band_budget
    from cutterpose.verdict import QualityLimits

    C = correlated_dof_cov()
    n = np.array([[1.0, 0.0], [0.0, -1.0], [0.6, 0.8], [-0.8, 0.6]])
    band = SimpleNamespace(cov_parts={"noise": C}, radius_mm=1.25,
                           weights=np.array([1.0, 0.5, 0.9, 0.2]),
                           residuals_px=np.array([0.3, -2.0, -0.5, 4.0]),
                           fit=SimpleNamespace(profiles=SimpleNamespace(normals_ideal=n)))
    limits = QualityLimits(grasp_point_mm=tuple(GRASP_MM), tolerance=Tolerance(0.9, 0.2))
    budget, r = band_budget(band, DOF, limits)
    np.testing.assert_allclose(r, [[0.3, 0.0], [-0.3, -0.4]])
    assert budget.radius_mm == 1.25
    np.testing.assert_allclose(budget.grasp_point_mm, GRASP_MM)
    pos, ang, _ = mc_figures(DOF, C, GRASP_MM)
    assert budget.position_3sigma_mm == pytest.approx(pos, rel=0.015)
    assert budget.angle_3sigma_deg == pytest.approx(ang, rel=0.015)
    assert budget.exceeds(limits.tolerance)   # 0.9 mm is under this point's figure


def test_lever_arm_entries_by_hand():
    """Each entry of ``[p]x`` by hand: a pure turn about x or y leaves the origin where it is;
    at ``p = (0, 200, 0)`` a turn ``w`` about x moves the point by ``200 w`` along z, which a
    translation along z fully correlated with it cancels (and doubles when anti-correlated)."""
    s = 0.05                                                 # deg
    for k in (0, 1, 2):
        C = np.zeros((6, 6))
        C[k, k] = s ** 2
        b = budget_from_dof_cov({"n": C}, [0, 0, 0, 0, 0, 600])
        assert b.position_3sigma_mm == pytest.approx(0.0, abs=1e-12)
    lever = 200 * math.radians(s)                           # mm of z per sigma of alpha
    for rho, expect in ((-1.0, 0.0), (1.0, 2 * lever)):
        C = np.zeros((6, 6))
        C[0, 0], C[5, 5] = s ** 2, lever ** 2
        C[0, 5] = C[5, 0] = rho * s * lever
        b = budget_from_dof_cov({"n": C}, [0, 0, 0, 0, 0, 600], (0.0, 200.0, 0.0))
        assert b.position_3sigma_mm == pytest.approx(3 * expect, abs=1e-9)
