"""Hand-eye calibration as a bundle adjustment: the robot's per-station errors as unknowns.

:func:`bundle_adjust_handeye` solves the maximum-likelihood problem of
:mod:`cutterpose.calibration.handeye` with the 6 errors of every reported flange pose as explicit
unknowns under a Gaussian prior (``calibrate_handeye(..., refinement="bundle")``).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from scipy.optimize import least_squares
from scipy.spatial.transform import Rotation

from ..errors import DegenerateInputError, InputError
from ..geometry.camera import Camera
from ..geometry.pose import Pose
from .handeye_problem import (
    HandEyeProblem,
    TargetModel,
    compose_xy,
    cov_left_to_own,
    predicted_bias,
)

__all__ = ["BundleResult", "bundle_adjust_handeye"]


@dataclass
class BundleResult:
    """Result of :func:`bundle_adjust_handeye`.

    ``cov_flange_cam`` / ``cov_base_plate``: 6x6 (x, y, z [mm], rotation [rad] about the
    frame's own axes, PROTOCOL.md), marginalised over the station corrections.
    ``flange_corrections``: (n, 6) estimated errors of the reported flange poses (translation
    [mm], rotation [rad] about the base axes; ``true = Exp(dphi) R_reported``,
    ``t_reported + dt``). ``cost``: half the sum of squared whitened residuals.
    """

    T_flange_cam: Pose
    T_base_plate: Pose
    cov_flange_cam: np.ndarray
    cov_base_plate: np.ndarray
    flange_corrections: np.ndarray
    cost: float
    nfev: int



def _ba_sparsity(n: int, N: int):
    """Which parameters each residual depends on: a station's 2N image rows on the 12 global
    parameters and its own 6 corrections, its 6 prior rows on those 6 only."""
    from scipy.sparse import lil_matrix

    S = lil_matrix((n * (2 * N + 6), 12 + 6 * n), dtype=np.int8)
    for i in range(n):
        rows = slice(i * 2 * N, (i + 1) * 2 * N)
        S[rows, :12] = 1
        S[rows, 12 + 6 * i: 18 + 6 * i] = 1
        S[n * 2 * N + 6 * i: n * 2 * N + 6 * i + 6, 12 + 6 * i: 18 + 6 * i] = 1
    return S.tocsr()


def bundle_adjust_handeye(T_base_flange: list[Pose], points_px, camera: Camera,
                          X0: Pose, Y0: Pose, *, plate=None,
                          sigma_px: float, repeatability_mm: float,
                          repeatability_deg: float, bias_px=None, loss: str = "soft_l1",
                          f_scale: float = 3.0, used=None) -> BundleResult:
    """Maximum-likelihood hand-eye calibration under plate *and* robot noise (bundle
    adjustment).

    Unknowns: ``X = T_flange_cam``, ``Y = T_base_plate`` and, per station, the 6 corrections
    ``d_i = (dt_i, dphi_i)`` of the reported flange pose (``T_base_flange_true = (Exp(dphi_i)
    R_i, t_i + dt_i)``, the noise model of :class:`cutterpose.robot.cell.RobotCell`). Cost:
    ``sum_i rho(|proj(X^-1 A_i(d_i)^-1 Y) - obs_i|^2 / sigma_px^2) + d_i^T C_robot^-1 d_i``,
    ``rho`` the robust loss on the image residuals only (the prior is Gaussian), solved by
    ``scipy.optimize.least_squares`` with the block-sparse Jacobian (``jac_sparsity``: a
    station's rows touch the 12 global parameters and its own 6). The covariance is the
    inverse of the full Gauss-Newton information (12 + 6n), its ``X`` and ``Y`` blocks
    (= the Schur complement over the corrections, i.e. marginalised), scaled by the reduced
    chi-square when that exceeds 1. Triggs et al., "Bundle adjustment -- a modern synthesis"
    (2000), sections 6 and 8 (gauge-free priors and marginalisation); Koide & Menegatti 2019.

    Parameters
    ----------
    T_base_flange : the n reported flange poses.
    points_px : (n, N, 2) observed circle centres.
    X0, Y0 : starts (e.g. a linear method's).
    sigma_px : the plate's detection noise (1 sigma per coordinate).
    repeatability_mm, repeatability_deg : the robot's reporting noise (1 sigma per axis).
    bias_px : (n, N, 2) perspective bias of the centres to remove (default: predicted at the
        plate poses of the start, and again at the solution for a second solve).
    used : boolean mask of the stations to use (default all).

    Returns
    -------
    BundleResult

    Raises
    ------
    InputError
        Non-positive noise levels or an unknown loss.
    DegenerateInputError
        Singular information (stations too alike).
    """
    target = TargetModel.of(plate)
    A = list(T_base_flange)
    obs = np.asarray(points_px, float)
    if bias_px is None:
        # the circle centres' perspective bias, predicted at the start's plate poses, then
        # once more at the solution (a start 1 mm off moves it by ~1e-3 px)
        first = bundle_adjust_handeye(
            A, obs, camera, X0, Y0, plate=target, sigma_px=sigma_px,
            repeatability_mm=repeatability_mm, repeatability_deg=repeatability_deg,
            bias_px=predicted_bias(camera, target, A, X0, Y0), loss=loss, f_scale=f_scale,
            used=used)
        X0, Y0 = first.T_flange_cam, first.T_base_plate
        bias_px = predicted_bias(camera, target, A, X0, Y0)
    bias = np.asarray(bias_px, float)
    used = np.ones(len(A), bool) if used is None else np.asarray(used, bool)
    A = [a for a, u in zip(A, used) if u]
    obs, bias = obs[used], bias[used]
    n, N = len(A), target.n_points
    rep_rad = math.radians(repeatability_deg)
    if sigma_px <= 0 or repeatability_mm <= 0 or rep_rad <= 0:
        raise InputError("bundle adjustment needs positive pixel noise and robot repeatability")
    prob = HandEyeProblem(camera, target.points_mm, A, obs, bias, sigma_px, repeatability_mm,
                          rep_rad)
    prior_sd = np.array([repeatability_mm] * 3 + [rep_rad] * 3)

    def unpack(x):
        X, Y = compose_xy(X0, Y0, x[:12])
        d = x[12:].reshape(n, 6)
        RA = np.einsum("nij,njk->nik", Rotation.from_rotvec(d[:, 3:]).as_matrix(), prob.RA)
        return X, Y, d, RA, prob.tA + d[:, :3]

    w_img = np.ones(n * 2 * N)  # IRLS weights of the image rows (the prior stays quadratic)

    def fun(x):
        X, Y, d, RA, tA = unpack(x)
        r_img = ((prob.project(X, Y, RA, tA) - prob.obs)
                 * prob.seen[..., None]).ravel() / sigma_px
        return np.concatenate([w_img * r_img, (d / prior_sd).ravel()])

    def solve(x):
        return least_squares(fun, x, jac_sparsity=_ba_sparsity(n, N), method="trf",
                             x_scale="jac", xtol=1e-12, ftol=1e-12, gtol=1e-12, max_nfev=100,
                             tr_solver="lsmr", tr_options={"atol": 1e-12, "btol": 1e-12})

    x = np.concatenate([np.zeros(3), X0.t_mm, np.zeros(3), Y0.t_mm, np.zeros(6 * n)])
    nfev = 0
    if loss == "soft_l1":
        # robust loss on the image residuals only: least_squares' ``loss`` would act on the
        # prior rows too and let a station's correction swallow a gross robot error, so the
        # soft-L1 M-estimator is reached by reweighting, rho'(z) = (1 + z)^-1/2, z = (r/f)^2
        for _ in range(4):
            res = solve(x)
            x, nfev = res.x, nfev + res.nfev
            r = res.fun[: n * 2 * N] / w_img
            w_img = (1.0 + (r / f_scale) ** 2) ** -0.25
    elif loss != "linear":
        raise InputError(f"unknown loss {loss!r} (soft_l1 or linear)")
    w_img = np.ones(n * 2 * N)
    res = solve(x)
    nfev += res.nfev
    X, Y, d, _, _ = unpack(res.x)
    J = res.jac.toarray() if hasattr(res.jac, "toarray") else res.jac
    dof = max(len(res.fun) - 12 - 6 * n, 1)
    s2 = max(float(np.sum(res.fun ** 2)) / dof, 1.0)
    try:
        # 12 x 12 of the inverse information = the Schur complement over the corrections
        H = J.T @ J
        cov12 = s2 * np.linalg.inv(H)[:12, :12]
    except np.linalg.LinAlgError:
        raise DegenerateInputError("hand-eye bundle adjustment is singular") from None
    order = [3, 4, 5, 0, 1, 2]
    covX = cov_left_to_own(X, cov12[np.ix_(order, order)])
    covY = cov_left_to_own(Y, cov12[np.ix_([o + 6 for o in order], [o + 6 for o in order])])
    corr = np.zeros((len(used), 6))
    corr[used] = d
    return BundleResult(X, Y, covX, covY, corr, float(res.cost), nfev)


