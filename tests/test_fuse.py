"""Fusing several views of one holder (cutterpose.robot.fuse)."""

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from cutterpose.errors import InputError
from cutterpose.geometry.pose import Pose
from cutterpose.robot.frames import PoseCov
from cutterpose.robot.fuse import fuse_poses, joint_covariance, sqrt_psd

TRUTH = Pose(Rotation.from_euler("xyz", [3, -5, 40], degrees=True).as_matrix(),
             np.array([1200.0, -300.0, 450.0]), "base", "holder")


def _cov(rng, scale_mm=0.3, scale_rad=2e-3):
    A = rng.normal(size=(6, 6))
    C = A @ A.T / 6 + 0.2 * np.eye(6)
    s = np.array([scale_mm] * 3 + [scale_rad] * 3)
    return C * np.outer(s, s)


def _draw(rng, C, truth=TRUTH):
    d = np.linalg.cholesky(C) @ rng.normal(size=6)
    return Pose(Rotation.from_rotvec(d[3:]).as_matrix() @ truth.R, truth.t_mm + d[:3],
                truth.to_frame, truth.from_frame)


def test_one_view_is_itself():
    rng = np.random.default_rng(0)
    C = _cov(rng)
    p = _draw(rng, C)
    f = fuse_poses([PoseCov(p, C)])
    assert np.allclose(f.fused.pose.matrix, p.matrix, atol=1e-9)
    assert np.allclose(f.fused.cov, C)
    assert f.dof == 0 and f.p_value == 1.0


def test_independent_views_give_the_information_sum_and_chi2():
    rng = np.random.default_rng(1)
    covs = [_cov(rng) for _ in range(3)]
    expect = np.linalg.inv(sum(np.linalg.inv(C) for C in covs))
    chi2s, errs = [], []
    for _ in range(400):
        views = [PoseCov(_draw(rng, C), C) for C in covs]
        f = fuse_poses(views)
        assert np.allclose(f.fused.cov, expect, rtol=1e-9, atol=1e-15)
        chi2s.append(f.chi2)
        d = np.concatenate([f.fused.pose.t_mm - TRUTH.t_mm,
                            Rotation.from_matrix(f.fused.pose.R @ TRUTH.R.T).as_rotvec()])
        errs.append(d @ np.linalg.solve(expect, d))
    # both chi-square: the residuals with 12 degrees of freedom, the error with 6
    assert abs(np.mean(chi2s) - 12) < 1.0
    assert abs(np.mean(errs) - 6) < 0.6


def test_correlated_views_gain_less_and_rho_one_refuses():
    rng = np.random.default_rng(2)
    C = _cov(rng)
    views = [PoseCov(_draw(rng, C), C) for _ in range(3)]
    f0 = fuse_poses(views, rho=0.0)
    f5 = fuse_poses(views, rho=0.5)
    # equal covariances: C / n independent, C (1 + (n - 1) rho) / n equicorrelated
    assert np.allclose(f0.fused.cov, C / 3)
    assert np.allclose(f5.fused.cov, C * 2 / 3)
    with pytest.raises(InputError, match="singular"):
        fuse_poses(views, rho=1.0)
    with pytest.raises(InputError, match=r"\[0, 1\]"):
        fuse_poses(views, rho=1.5)


def test_a_shared_source_is_not_averaged_away():
    rng = np.random.default_rng(3)
    C = _cov(rng)
    Cs = np.diag([0.1, 0.1, 0.1, 1e-4, 1e-4, 1e-4]) ** 2
    views = [PoseCov(_draw(rng, C), C) for _ in range(4)]
    f = fuse_poses(views, shared=[([np.eye(6)] * 4, Cs)])
    assert np.allclose(f.fused.cov, C / 4 + Cs)


def test_disagreeing_views_are_reported():
    rng = np.random.default_rng(4)
    C = _cov(rng)
    views = [PoseCov(_draw(rng, C), C) for _ in range(2)]
    moved = Pose(TRUTH.R, TRUTH.t_mm + [5.0, 0, 0], "base", "holder")
    views.append(PoseCov(_draw(rng, C, moved), C))
    f = fuse_poses(views)
    assert not f.agree and f.p_value < 1e-3
    assert np.argmax(np.abs(f.residuals[:, 0])) == 2


def test_bad_input():
    rng = np.random.default_rng(5)
    C = _cov(rng)
    with pytest.raises(InputError, match="no view"):
        fuse_poses([])
    other = Pose(TRUTH.R, TRUTH.t_mm, "base", "grasp")
    with pytest.raises(InputError, match="different transforms"):
        fuse_poses([PoseCov(TRUTH, C), PoseCov(other, C)])
    with pytest.raises(InputError, match="singular"):
        fuse_poses([PoseCov(TRUTH, C), PoseCov(TRUTH, np.zeros((6, 6)))])


def test_joint_covariance_is_psd_and_sqrt():
    rng = np.random.default_rng(6)
    covs = [_cov(rng) for _ in range(3)]
    S = sqrt_psd(covs[0])
    assert np.allclose(S @ S, covs[0])
    for rho in (0.0, 0.3, 0.9, 1.0):
        Sig = joint_covariance(covs, rho)
        assert np.linalg.eigvalsh(Sig).min() > -1e-12


def test_parts_add_up_to_the_fused_covariance():
    rng = np.random.default_rng(7)
    covs = [_cov(rng) for _ in range(3)]
    ind = [np.diag([0.05] * 3 + [2e-4] * 3) ** 2] * 3
    Cs = np.diag([0.1] * 3 + [1e-4] * 3) ** 2
    views = [PoseCov(_draw(rng, C), C) for C in covs]
    f = fuse_poses(views, rho=0.4, cov_ind=ind, shared=[([np.eye(6)] * 3, Cs)])
    assert np.allclose(sum(f.parts.values()), f.fused.cov, rtol=1e-9, atol=1e-15)
    assert np.allclose(f.parts["shared"], Cs)     # a shared source passes through whole
    assert set(f.parts) == {"measurement", "independent", "shared"}


def test_to_dict_is_json():
    import json
    rng = np.random.default_rng(8)
    C = _cov(rng)
    f = fuse_poses([PoseCov(_draw(rng, C), C) for _ in range(2)])
    d = json.loads(json.dumps(f.to_dict()))
    assert d["views"] == 2 and d["dof"] == 6 and len(d["residuals_mm_deg"]) == 2
    assert d["fused"]["frame_id"] == "base" and d["fused"]["child_frame_id"] == "holder"
