"""DLT, EPnP, RPnP and their LM refinement (``<solver>+lm``): exactness, invariances, the planar
twin, degenerate input, and the ML refinement against OpenCV's IPPE + LM."""

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from cutterpose.errors import DegenerateInputError, InputError
from cutterpose.experiments.synthetic import generate_trials
from cutterpose.geometry.pose import geodesic_deg, rotation_from_euler_deg
from cutterpose.methods import get_method
from cutterpose.solvers.pnp.base import reprojection_rms
from cutterpose.solvers.pnp.refine import planar_flip, refine_pose

BASE = ["dlt", "epnp", "rpnp"]
ALL = BASE + [f"{b}+lm" for b in BASE]


def _solve(name, px, cam, model):
    return get_method(name).solve(px, cam, model)


def _err(est, R, t):
    return float(geodesic_deg(R, est.R_cam_holder)), float(np.linalg.norm(est.t_cam_holder_mm - t))


def _box_trials(rng, n_trials, n_points=20, half_mm=200.0):
    """Random non-planar sets: points in a +-200 mm box, random rotation, ~600 mm away."""
    out = []
    for _ in range(n_trials):
        P = rng.uniform(-half_mm, half_mm, (n_points, 3))
        R = Rotation.random(random_state=rng).as_matrix()
        t = np.array([0.0, 0.0, 600.0]) + rng.uniform(-90, 90, 3)
        out.append((P, R, t))
    return out


def _project(cam, P, R, t):
    return cam.project(P @ R.T + t)


@pytest.fixture(scope="module")
def planar_trials():
    return generate_trials(200, 0.0, seed=11)


@pytest.mark.parametrize("name", BASE)
def test_noise_free_planar_random(name, planar_trials):
    tr = planar_trials
    worst = np.zeros(2)
    for i in range(len(tr)):
        est = _solve(name, tr.points_px[i], tr.camera, tr.points_holder_mm)
        assert est, est.reason
        worst = np.maximum(worst, _err(est, tr.R_cam_holder[i], tr.t_cam_holder_mm[i]))
    assert worst[0] < 1e-6 and worst[1] < 1e-6, worst


@pytest.mark.parametrize("name", BASE)
def test_noise_free_nonplanar_random(name, cam_syn):
    rng = np.random.default_rng(7)
    worst = np.zeros(2)
    for P, R, t in _box_trials(rng, 200):
        est = _solve(name, _project(cam_syn, P, R, t), cam_syn, P)
        assert est, est.reason
        worst = np.maximum(worst, _err(est, R, t))
    assert worst[0] < 1e-6 and worst[1] < 1e-6, worst


@pytest.mark.parametrize("name", ALL)
def test_noise_free_extreme_tilts(name, cam_syn, holder):
    """Near fronto-parallel (tilt < 1 deg) and 60 deg tilts, planar and in a tilted plane."""
    rng = np.random.default_rng(3)
    P = holder.points_holder_mm
    poses = []
    for _ in range(6):
        a, b = rng.uniform(-0.7, 0.7, 2)
        poses.append((rotation_from_euler_deg(a, b, rng.uniform(-180, 180)),
                      np.array([*rng.uniform(-30, 30, 2), 600.0])))
    for a, b in [(60, 0), (0, -60), (45, 43), (-60, 60)]:
        poses.append((rotation_from_euler_deg(a, b, rng.uniform(-60, 60)),
                      np.array([0.0, 0.0, 650.0])))
    # a planar set in a plane that is not Z = 0 (the AL-S pitfall, notes 3 and 6.2)
    W = rotation_from_euler_deg(35.0, -20.0, 10.0)
    P_tilted = P @ W.T + [10.0, -20.0, 30.0]
    for R, t in poses:
        for model, Rm in ((P, R), (P_tilted, R @ W.T)):
            tm = t - Rm @ (model.mean(axis=0)) + R @ P.mean(axis=0)
            est = _solve(name, _project(cam_syn, model, Rm, tm), cam_syn, model)
            assert est, est.reason
            e = _err(est, Rm, tm)
            assert e[0] < 1e-6 and e[1] < 1e-6, (name, e)


@pytest.mark.parametrize("name", ["dlt+lm", "epnp+lm", "rpnp+lm"])
def test_refined_noise_free(name, planar_trials, cam_syn):
    tr = planar_trials
    for i in range(25):
        est = _solve(name, tr.points_px[i], tr.camera, tr.points_holder_mm)
        e = _err(est, tr.R_cam_holder[i], tr.t_cam_holder_mm[i])
        assert e[0] < 1e-6 and e[1] < 1e-6, e
    rng = np.random.default_rng(8)
    for P, R, t in _box_trials(rng, 10):
        est = _solve(name, _project(cam_syn, P, R, t), cam_syn, P)
        e = _err(est, R, t)
        assert e[0] < 1e-6 and e[1] < 1e-6, e


def _noisy_sets(rng, cam, sigma_px, n_holder, n_box, seed):
    """(object points, noisy pixels) pairs: protocol holder trials, then random 3-D boxes."""
    tr = generate_trials(n_holder, sigma_px, seed=seed)
    sets = [(tr.points_holder_mm, tr.points_px[i]) for i in range(n_holder)]
    sets += [(P, _project(cam, P, R, t) + rng.normal(0, sigma_px, (20, 2)))
             for P, R, t in _box_trials(rng, n_box)]
    return sets


@pytest.mark.parametrize("name", ALL)
def test_permutation_invariance(name, cam_syn):
    rng = np.random.default_rng(21)
    for P, px in _noisy_sets(rng, cam_syn, 2.0, n_holder=5, n_box=3, seed=5):
        perm = rng.permutation(len(P))
        a = _solve(name, px, cam_syn, P)
        b = _solve(name, px[perm], cam_syn, P[perm])
        assert np.abs(a.R_cam_holder - b.R_cam_holder).max() < 1e-8
        assert np.abs(a.t_cam_holder_mm - b.t_cam_holder_mm).max() < 1e-6


@pytest.mark.parametrize("name", ALL)
def test_scale_covariance(name, cam_syn):
    """Scaling the object (and t) by k leaves the image unchanged: R the same, t times k."""
    rng = np.random.default_rng(4)
    for P, px in _noisy_sets(rng, cam_syn, 1.5, n_holder=4, n_box=2, seed=9):
        a = _solve(name, px, cam_syn, P)
        for k in (1e-3, 25.0):
            b = _solve(name, px, cam_syn, k * P)
            assert np.abs(a.R_cam_holder - b.R_cam_holder).max() < 1e-8
            np.testing.assert_allclose(b.t_cam_holder_mm, k * a.t_cam_holder_mm, rtol=1e-8)


@pytest.mark.parametrize("name", ALL)
def test_planar_twin_never_returned(name, planar_trials):
    tr = planar_trials
    P = tr.points_holder_mm
    flip = np.diag([-1.0, -1.0, 1.0])
    for i in range(0, 200, 20):
        est = _solve(name, tr.points_px[i], tr.camera, P)
        R_twin, t_twin = tr.R_cam_holder[i] @ flip, -tr.t_cam_holder_mm[i]
        for R, t in est.candidates:
            assert np.all(P @ R[2] + t[2] > 0)  # every candidate in front of the camera
            assert np.abs(R - R_twin).max() > 1e-3 or np.abs(t - t_twin).max() > 1e-3
        assert 0.0 <= est.ambiguity_ratio <= 1.0 or np.isnan(est.ambiguity_ratio)
        assert np.isfinite(est.residual_px)


def test_refined_finds_planar_ambiguity():
    """Where OpenCV's IPPE + LM has a genuine second minimum, `<solver>+lm` finds it too (from the
    flipped start) with the same ratio, although the base solvers return one pose."""
    tr = generate_trials(30, 2.0, seed=3)
    ref = get_method("opencv-ippe-lm").solve
    solve = get_method("epnp+lm").solve
    n_second = 0
    for i in range(len(tr)):
        b = ref(tr.points_px[i], tr.camera, tr.points_holder_mm)
        if len(b.candidates) < 2 or geodesic_deg(b.candidates[1][0], b.R_cam_holder) < 1.0:
            continue
        n_second += 1
        a = solve(tr.points_px[i], tr.camera, tr.points_holder_mm)
        assert len(a.candidates) == 2
        assert geodesic_deg(a.candidates[1][0], b.candidates[1][0]) < 0.5
        # the same minimum, at least as well converged as OpenCV's
        m = tr.camera.normalize_px(tr.points_px[i])
        e_a = reprojection_rms(*a.candidates[1], tr.points_holder_mm, m)
        e_b = reprojection_rms(*b.candidates[1], tr.points_holder_mm, m)
        assert e_a <= e_b * (1 + 1e-9)
        assert abs(a.ambiguity_ratio - b.ambiguity_ratio) < 0.05
    assert n_second >= 5


def test_planar_flip_is_the_weak_perspective_twin(holder):
    """Far away, the flipped pose projects like the original to first order."""
    P = holder.points_holder_mm
    R = rotation_from_euler_deg(20.0, 10.0, 5.0)
    t = np.array([0.0, 0.0, 60000.0])
    R2, t2 = planar_flip(R, t, P)
    assert geodesic_deg(R, R2) > 10.0
    X, X2 = P @ R.T + t, P @ R2.T + t2
    d = np.abs(X[:, :2] / X[:, 2:] - X2[:, :2] / X2[:, 2:]).max()
    # first order: the discrepancy is of relative size (object size / distance)^2 ~ 1e-5
    assert d < 1e-2 * np.abs(X[:, :2] / X[:, 2:]).max()


def test_refine_pose_converges_from_a_perturbed_start(cam_syn, holder):
    P = holder.points_holder_mm
    R = rotation_from_euler_deg(30.0, -40.0, 100.0)
    t = np.array([20.0, -40.0, 620.0])
    ideal = _project(cam_syn, P, R, t)
    R0 = Rotation.from_rotvec([0.05, -0.04, 0.03]).as_matrix() @ R
    R1, t1, nfev = refine_pose(R0, t + [5.0, -4.0, 20.0], P, ideal, cam_syn.K)
    assert geodesic_deg(R, R1) < 1e-8 and np.linalg.norm(t1 - t) < 1e-7
    assert nfev < 30


def test_refined_matches_opencv_ml(cam_syn):
    """`<solver>+lm` reaches the same ML pose as OpenCV IPPE + LM, and fails no more often."""
    tr = generate_trials(40, 3.0, seed=17)
    ref = get_method("opencv-ippe-lm").solve
    for name in ("dlt+lm", "epnp+lm", "rpnp+lm"):
        solve = get_method(name).solve
        for i in range(len(tr)):
            a = solve(tr.points_px[i], tr.camera, tr.points_holder_mm)
            b = ref(tr.points_px[i], tr.camera, tr.points_holder_mm)
            assert a.residual_px <= b.residual_px * (1 + 1e-9) + 1e-9
            if abs(a.residual_px - b.residual_px) < 1e-9 * b.residual_px:
                # the cost is flat along the valley: OpenCV stops 1e-4 deg short
                assert geodesic_deg(a.R_cam_holder, b.R_cam_holder) < 1e-3


@pytest.mark.parametrize("name", ALL)
def test_degenerate_input(name, cam_syn, holder):
    P = holder.points_holder_mm
    R = rotation_from_euler_deg(10.0, 20.0, 5.0)
    t = np.array([0.0, 0.0, 600.0])
    px = _project(cam_syn, P, R, t)
    with pytest.raises(DegenerateInputError):
        _solve(name, px[:3], cam_syn, P[:3])
    line = np.column_stack([np.linspace(-100, 100, 6), np.zeros(6), np.zeros(6)])
    with pytest.raises(DegenerateInputError):
        _solve(name, _project(cam_syn, line, R, t), cam_syn, line)
    bad = px.copy()
    bad[4, 1] = np.nan
    with pytest.raises(InputError):
        _solve(name, bad, cam_syn, P)
    bad[4, 1] = np.inf
    with pytest.raises(InputError):
        _solve(name, bad, cam_syn, P)
    with pytest.raises(InputError):
        _solve(name, px[:-1], cam_syn, P)
    with pytest.raises(InputError):
        _solve(name, px[:, :1], cam_syn, P)
    with pytest.raises(InputError):
        _solve(name, px, cam_syn, P[:, :2])


def test_dlt_nonplanar_needs_six_points(cam_syn):
    rng = np.random.default_rng(0)
    (P, R, t), = _box_trials(rng, 1, n_points=5)
    with pytest.raises(DegenerateInputError, match="6 points"):
        _solve("dlt", _project(cam_syn, P, R, t), cam_syn, P)


def _behind(cam, P, R, t):
    """Exact normalised projections of points that lie behind the camera (z < 0)."""
    X = P @ R.T + t
    assert np.all(X[:, 2] < 0)
    m = X[:, :2] / X[:, 2:]
    K = cam.K
    return m @ K[:2, :2].T + K[:2, 2]


@pytest.mark.parametrize("name", ["dlt", "epnp", "dlt+lm", "epnp+lm"])
def test_nonplanar_points_behind_camera_give_no_pose(name, cam_syn):
    """Points behind the camera: no rotation explains the image; a falsy estimate, not an error."""
    rng = np.random.default_rng(31)
    for P, R, t in _box_trials(rng, 5):
        t = t * [1.0, 1.0, -1.0]
        est = _solve(name, _behind(cam_syn, P, R, t), cam_syn, P)
        assert not est
        assert "in front" in est.reason


@pytest.mark.parametrize("name", ["rpnp", "rpnp+lm"])
def test_rpnp_points_behind_camera_no_consistent_pose(name, cam_syn):
    """RPnP returns either nothing or a pose that does not explain the image (module docstring)."""
    rng = np.random.default_rng(31)
    for P, R, t in _box_trials(rng, 5):
        t = t * [1.0, 1.0, -1.0]
        px = _behind(cam_syn, P, R, t)
        est = _solve(name, px, cam_syn, P)
        assert_no_confident_pose(est, cam_syn, P, px, 10.0)


def assert_no_confident_pose(est, cam, P, px, min_residual_px):
    """Either no pose, with the reason, or a pose in front of the camera whose residual, as the
    estimate states it, is its actual reprojection RMS (recomputed here through ``K``) and
    large: the verdict's residual check then refuses it."""
    if not est:
        assert est.reason and est.R_cam_holder is None
        return
    X = P @ est.R_cam_holder.T + est.t_cam_holder_mm
    assert np.all(X[:, 2] > 0)
    q = X[:, :2] / X[:, 2:] @ cam.K[:2, :2].T + cam.K[:2, 2]
    rms = float(np.sqrt(np.mean(np.sum((q - px) ** 2, axis=1))))
    assert est.residual_px == pytest.approx(rms, rel=1e-6)
    assert rms > min_residual_px


@pytest.mark.parametrize("name", BASE)
def test_planar_points_behind_camera_give_the_twin(name, cam_syn, holder):
    """For a planar model the mirror image of points behind the camera is the twin in front."""
    P = holder.points_holder_mm
    R = rotation_from_euler_deg(20.0, -10.0, 30.0)
    t = np.array([10.0, 5.0, -600.0])
    est = _solve(name, _behind(cam_syn, P, R, t), cam_syn, P)
    e = _err(est, R @ np.diag([-1.0, -1.0, 1.0]), -t)
    assert e[0] < 1e-6 and e[1] < 1e-6


# --- speed rewrites (issue 3): the fast paths compute what the plain formulas compute ---------


def test_model_cache_follows_the_array_contents(cam_syn, holder):
    """Per-model caches are keyed on the points' bytes: a different (or edited) model array with
    the same shape never reuses another model's plane frame / control points."""
    from cutterpose.solvers.pnp.base import model_cache

    P = holder.points_holder_mm
    R = rotation_from_euler_deg(10.0, -20.0, 5.0)
    t = np.array([3.0, -4.0, 600.0])
    Q = P.copy()
    Q[:, :2] *= 1.5  # same shape, different holder
    for name in BASE:
        for model in (P, Q, P):  # the second P hits the cache filled by the first
            est = _solve(name, _project(cam_syn, model, R, t), cam_syn, model)
            assert _err(est, R, t)[0] < 1e-6
    assert model_cache(P) is model_cache(P.copy()) and model_cache(Q) is not model_cache(P)
    # a model that failed a check is not remembered as valid
    line = np.column_stack([np.linspace(-100, 100, 6), np.zeros(6), np.zeros(6)])
    for _ in range(2):
        with pytest.raises(DegenerateInputError):
            _solve("dlt", _project(cam_syn, line, R, t), cam_syn, line)


def test_linear_algebra_helpers_match_numpy():
    from cutterpose.solvers.pnp.base import (
        align_rigid_many,
        image_weights,
        kron_normal,
        smallest_eigvecs,
        svd_small,
    )

    rng = np.random.default_rng(3)
    n, m = 20, rng.normal(size=(20, 2))
    a = rng.normal(size=(n, 4))
    O = (a[:, :, None] * a[:, None, :]).reshape(n, 16)
    B = np.zeros((n, 2, 3))
    B[:, 0, 0] = B[:, 1, 1] = 1.0
    B[:, :, 2] = -m
    for coord_outer in (True, False):  # rows kron(B_i, a_i) resp. kron(a_i, B_i)
        rows = [np.kron(B[i], a[i][None]) if coord_outer else np.kron(a[i][None], B[i])
                for i in range(n)]
        A = np.vstack(rows)
        np.testing.assert_allclose(kron_normal(O, m, coord_outer), A.T @ A, rtol=1e-12,
                                   atol=1e-12)
        np.testing.assert_array_equal(kron_normal(O, None, coord_outer, E=image_weights(m)),
                                      kron_normal(O, m, coord_outer))
    S = rng.normal(size=(12, 12))
    S = S @ S.T
    V = smallest_eigvecs(S, 3)
    w, E = np.linalg.eigh(S)
    np.testing.assert_allclose(np.abs(V.T @ E[:, :3]), np.eye(3), atol=1e-10)
    M = rng.normal(size=(6, 10))
    np.testing.assert_allclose(svd_small(M)[1], np.linalg.svd(M)[1], rtol=1e-12)
    P = rng.normal(size=(n, 3)) * 50
    for planar in (False, True):
        if planar:
            P[:, 2] = 0.0
        Rs = Rotation.random(3, random_state=rng).as_matrix()
        Xs = P @ Rs.transpose(0, 2, 1) + rng.normal(size=(3, 1, 3)) * 100
        Xs += rng.normal(size=Xs.shape) * 0.1
        for (R, t), X in zip(align_rigid_many(P, Xs), Xs, strict=True):
            S = (X - X.mean(0)).T @ (P - P.mean(0))
            U, _, Vt = np.linalg.svd(S)
            R0 = U @ np.diag([1, 1, np.sign(np.linalg.det(U) * np.linalg.det(Vt))]) @ Vt
            np.testing.assert_allclose(R, R0, atol=1e-12)
            np.testing.assert_allclose(t, X.mean(0) - R0 @ P.mean(0), atol=1e-9)


def _rpnp_plain_cost_derivative(P, cos, i1, i2):
    """G = sum_i f_i f_i' with the quartics' coefficients written out (notes section 3 step 4)."""
    c12 = cos[i1, i2]
    s12_2 = 1.0 - c12**2
    D12 = np.sum((P[i1] - P[i2]) ** 2)
    G = np.zeros(8)
    for i in range(len(P)):
        if i in (i1, i2):
            continue
        c1i, c2i = cos[i1, i], cos[i2, i]
        A1 = np.sum((P[i] - P[i1]) ** 2) / D12
        A6 = (np.sum((P[i] - P[i2]) ** 2) - D12 - np.sum((P[i] - P[i1]) ** 2)) / (2 * D12)
        A2 = A1 * s12_2 - (1 - c1i**2)
        A3 = c1i * c2i - c12
        A4 = c12 * c2i - c1i
        A7 = s12_2 - c1i**2 + c12 * c1i * c2i + A6 * s12_2
        g = [A6**2 - A1 * c2i**2, 2 * (A3 * A6 - A1 * A4 * c2i),
             A3**2 + 2 * A6 * A7 - A1 * A4**2 - A2 * c2i**2, 2 * (A3 * A7 - A2 * A4 * c2i),
             A7**2 - A2 * A4**2]
        G += np.polymul(g, np.polyder(g))
    return G


def _rpnp_plain_recover(t, b, m, Pa, i1, i2):
    """Camera-frame points for the root t by the explicit 2n x 5 least squares in (c, s, T),
    then T refitted for the normalised (c, s)."""
    from cutterpose.solvers.pnp.rpnp import _complete_frame

    ax = (b[i1] @ b[i2] + t) * b[i2] - b[i1]
    R_x = _complete_frame(ax / np.linalg.norm(ax))
    zero = np.zeros(len(Pa))
    # X = F0 + c Fc + s Fs + T
    terms = [np.column_stack(v) @ R_x.T for v in ([Pa[:, 0], zero, zero],
                                                  [zero, Pa[:, 1], Pa[:, 2]],
                                                  [zero, -Pa[:, 2], Pa[:, 1]])]
    rows = []
    for k in (0, 1):  # u X3 - X1 = 0, v X3 - X2 = 0
        cols = [m[:, k] * F[:, 2] - F[:, k] for F in terms]
        e = np.zeros((len(m), 3))
        e[:, k], e[:, 2] = -1.0, m[:, k]
        rows.append(np.column_stack([cols[1], cols[2], e, -cols[0]]))
    A = np.vstack(rows)
    z = np.linalg.lstsq(A[:, :5], A[:, 5], rcond=None)[0]
    th = np.arctan2(z[1], z[0])
    c, s = np.cos(th), np.sin(th)
    T = np.linalg.lstsq(A[:, 2:5], A[:, 5] - A[:, :2] @ [c, s], rcond=None)[0]
    Xt = Pa @ (R_x @ np.array([[1, 0, 0], [0, c, -s], [0, s, c]])).T + T
    return b * (np.linalg.norm(Xt, axis=1) * np.sign(Xt[:, 2]))[:, None]


def test_rpnp_steps_match_the_plain_formulas():
    """RPnP's regrouped polynomial, its root filter on Python floats and the linear step from
    moments (T eliminated) compute what the notes' coefficients, np.roots and the explicit
    2n x 5 least squares compute."""
    from cutterpose.solvers.pnp import rpnp
    from cutterpose.solvers.pnp.base import image_weights

    tr = generate_trials(30, 2.0, seed=5)
    cases = [(tr.points_holder_mm, tr.camera.normalize_px(px)) for px in tr.points_px]
    rng = np.random.default_rng(5)
    for P, R, t in _box_trials(rng, 10):
        X = P @ R.T + t
        cases.append((P, X[:, :2] / X[:, 2:] + rng.normal(0, 1e-3, (len(P), 2))))
    n_multi = 0
    for P, m in cases:
        n = len(P)
        b = np.column_stack([m, np.ones(n)])
        b /= np.linalg.norm(b, axis=1)[:, None]
        cos = b @ b.T
        i1, i2 = divmod(int(np.argmin(cos)), n)
        if tuple(m[i1]) > tuple(m[i2]):
            i1, i2 = i2, i1
        pair = rpnp._pair_model(P, i1, i2)
        G = rpnp._cost_derivative(cos, pair, i1, i2)
        G0 = _rpnp_plain_cost_derivative(P, cos, i1, i2)
        np.testing.assert_allclose(G, G0, rtol=0, atol=1e-12 * np.abs(G0).max())
        r = np.roots(G)
        r = r.real[np.abs(r.imag) <= 1e-3 * np.abs(r.real).max()]
        ts = rpnp._minima(G)
        np.testing.assert_allclose(sorted(ts), np.sort(r[np.polyval(np.polyder(G), r) > 0]),
                                   rtol=1e-9)
        n_multi += len(ts) > 1
        Nm, L = rpnp._eliminate_translation(pair.O, image_weights(m))
        for t in ts:
            X = rpnp._recover_one(t, float(cos[i1, i2]), b[i1].tolist(), b[i2].tolist(), b,
                                  pair.Pa1, Nm, L)
            X0 = _rpnp_plain_recover(t, b, m, pair.Pa1[:, :3], i1, i2)
            np.testing.assert_allclose(X, X0, rtol=0, atol=1e-9 * np.abs(X0).max())
    assert n_multi > 0  # the planar two-fold minima are among the cases


def test_select_single_candidate_fast_path():
    """One candidate takes a shortcut through select; the same candidate as lists takes the
    general path: the same estimate, failures included."""
    from cutterpose.solvers.pnp.base import select

    tr = generate_trials(10, 1.0, seed=2)
    P, f = tr.points_holder_mm, tr.camera.focal_px
    for i in range(len(tr)):
        m = tr.camera.normalize_px(tr.points_px[i])
        R, t = tr.R_cam_holder[i], tr.t_cam_holder_mm[i]
        for cand in [(R, t), (R, t * [1, 1, -1]), (1.01 * R, t), (R, t + [np.nan, 0, 0]),
                     (R, t + [0, 0, np.inf]), (np.full((3, 3), np.inf), t)]:
            with np.errstate(invalid="ignore"):  # the inf rotation
                fast = select("x", [cand], P, m, f)
                plain = select("x", [(cand[0].tolist(), cand[1].tolist())], P, m, f)
            assert bool(fast) == bool(plain) and fast.reason == plain.reason
            assert fast.info == plain.info and np.isnan(fast.ambiguity_ratio)
            if plain:
                np.testing.assert_array_equal(fast.R_cam_holder, plain.R_cam_holder)
                np.testing.assert_array_equal(fast.t_cam_holder_mm, plain.t_cam_holder_mm)
                assert fast.residual_px == pytest.approx(plain.residual_px, rel=1e-12)
                assert len(fast.candidates) == 1
                assert fast.R_cam_holder is not cand[0]  # the estimate owns its arrays


def test_pinhole_normalize_px_matches_the_generic_formula(cam_syn):
    from cutterpose.geometry.camera import Camera, PinholeCamera

    cam = PinholeCamera(1800.0, 1750.0, 1020.5, 760.25, (2048, 1536), skew=0.7)
    px = np.random.default_rng(1).uniform(0, 2000, (7, 5, 2))
    np.testing.assert_array_equal(cam.normalize_px(px), Camera.normalize_px(cam, px))
    assert cam.focal_px == Camera.focal_px.fget(cam)
    cam.fx = 1900.0  # fields may change: nothing is cached
    np.testing.assert_array_equal(cam.normalize_px(px), Camera.normalize_px(cam, px))


def test_epnp_gate_and_second_solution(monkeypatch):
    """EPnP builds N >= 3 only above the 5 px gate (for the camera's own focal length); its
    second candidate, when present, is a different pose (no false ambiguity from a neighbour
    of the best); forcing N = 3 everywhere changes the pose by no more than rounding."""
    from cutterpose.solvers.pnp import epnp

    calls = []
    orig = epnp._hypotheses

    def spy(*a, **k):
        calls.append(1)
        return orig(*a, **k)

    monkeypatch.setattr(epnp, "_hypotheses", spy)
    tr = generate_trials(40, 1.0, seed=21)
    P, cam = tr.points_holder_mm, tr.camera
    for i in range(len(tr)):
        est = epnp.solve(tr.points_px[i], cam, P)
        assert est
        for R, _ in est.candidates[1:]:
            assert geodesic_deg(R, est.R_cam_holder) > 1.0
        m = cam.normalize_px(tr.points_px[i])
        # a gate of 0 px builds N = 3 too: the refined best is the same solution
        R0, t0 = epnp.candidates(P, m, f_px=np.inf)[0]
        assert geodesic_deg(R0, est.R_cam_holder) < 1e-6
        assert np.linalg.norm(t0 - est.t_cam_holder_mm) < 1e-6
    assert len(calls) == len(tr)  # only the f_px = inf calls crossed the gate at 1 px
    # at 5 px most trials cross it (E_mean ~ 1.25 sigma)
    tr5 = generate_trials(20, 5.0, seed=21)
    calls.clear()
    for i in range(len(tr5)):
        epnp.candidates(tr5.points_holder_mm, tr5.camera.normalize_px(tr5.points_px[i]),
                        f_px=tr5.camera.focal_px)
    assert len(calls) >= 10


def test_epnp_steps_match_the_plain_formulas():
    """EPnP's normal matrix gathered from ``E^T O`` is kron_normal's bit for bit; the hypothesis
    scores from one stacked product, the pose from the control points alone and the planar
    Newton's quadratic-convergence stop give what the plain formulas on the points give."""
    from cutterpose.solvers.pnp import epnp
    from cutterpose.solvers.pnp.base import align_rigid, kron_normal

    tr = generate_trials(20, 2.0, seed=7)
    cases = [(tr.points_holder_mm, tr.camera.normalize_px(px)) for px in tr.points_px]
    rng = np.random.default_rng(7)
    for P, R, t in _box_trials(rng, 10, n_points=12):
        X = P @ R.T + t
        cases.append((P, X[:, :2] / X[:, 2:] + rng.normal(0, 1e-3, (len(P), 2))))
    for P, m in cases:
        md = epnp._model(P)
        n, kp = len(P), md.k + 1
        N = epnp._normal_matrix(md.O, md.ones, m, kp)
        N0 = kron_normal(md.O, m, coord_outer=False)
        assert N.tobytes() == N0.tobytes()  # signed zeros included: LAPACK sees the same matrix
        Wf = epnp._kernel(md.O, md.ones, m, kp).T
        alphas = md.A3[:n]
        hyps = [list(rng.normal(size=kp)) for _ in range(3)]
        e, sc, zbar = epnp._score(hyps, Wf, md, m)
        for h, beta in enumerate(hyps):
            c = (np.array(beta) @ Wf).reshape(kp, 3)
            X = alphas @ c
            e0 = np.mean(np.linalg.norm(X[:, :2] / X[:, 2:] - m, axis=1))
            dc = np.linalg.norm(X - X.mean(0), axis=1)
            sc0 = dc @ np.linalg.norm(P - P.mean(0), axis=1) / (dc @ dc)
            np.testing.assert_allclose([e[h], sc[h], zbar[h]], [e0, sc0, X[:, 2].mean()],
                                       rtol=1e-12, atol=1e-14 * abs(X[:, 2]).max())
            R, t = epnp._align_control(md.SaXt @ c, md.Pbar)
            R0, t0 = align_rigid(P, X)
            np.testing.assert_allclose(R, R0, atol=1e-12)
            np.testing.assert_allclose(t, t0, atol=1e-12 * np.abs(t0).max())
        if md.planar:  # Newton from the N = 2 hypothesis, against 8 plain iterations
            D = md.Dm3 @ Wf.T
            dl = (D.transpose(0, 2, 1) @ D).tolist()
            beta = epnp._hypotheses_low(dl, md.rhol, kp)[1]
            G = [(d[0][0], d[0][1], d[0][2], d[1][1], d[1][2], d[2][2]) for d in dl]
            b, conv = epnp._newton_planar(beta, G, md.rhol)
            b0 = np.array(beta)
            Gm = [np.array([[g[0], g[1], g[2]], [g[1], g[3], g[4]], [g[2], g[4], g[5]]])
                  for g in G]
            for _ in range(8):
                J = 2.0 * np.array([Gp @ b0 for Gp in Gm])
                r = np.array(md.rhol) - [b0 @ Gp @ b0 for Gp in Gm]
                b0 = b0 + np.linalg.solve(J, r)
            assert conv
            np.testing.assert_allclose(b, b0, rtol=0, atol=1e-13 * np.linalg.norm(b0))
