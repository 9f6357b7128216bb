"""One pose from several views of the same holder: generalised least squares on SE(3).

A robot that measures a holder from several stations gets several estimates of the same
``T_base_holder``. Their errors are not independent: the hand-eye error is the same in every
view, and part of the image's error belongs to the holder (its wear, chips and slurry look
alike from near viewpoints), not to the view. The fused pose is the generalised least-squares
mean under the joint covariance of all views,

    Sigma = blockdiag(C_i^ind) + rho * S_i S_j^T (i != j, S_i = C_i^meas^(1/2))
            + G_i C_s G_j^T                          (shared sources, every i, j)

with ``C_i^ind`` a view's own covariance (its measurement and the robot's repeatability),
``rho`` the measurement errors' correlation between views (measured on rendered sets of
several views per holder: ``benchmarks/view_fusion.py``), and ``G_i`` the Jacobian of view
i's pose with respect to a source ``s`` all views share (the hand-eye transform). Stacking the
perturbations of the views about the current mean, ``xi = H delta + e`` with ``H`` the stacked
identities, the estimate is ``delta = (H^T Sigma^-1 H)^-1 H^T Sigma^-1 xi``, iterated on the
manifold; its covariance ``(H^T Sigma^-1 H)^-1``. The views' agreement is checked: the
residuals' ``chi2 = r^T Sigma^-1 r`` with ``6 (n - 1)`` degrees of freedom; views that disagree
beyond it are reported (a holder that moved, a view that is wrong), not averaged.

Measured (docs/RESULTS.md section 16, ``benchmarks/view_fusion.py``): on path-traced worn
holders seen from three stations each, the views share a third to 40 % of their error
(intra-class correlation -0.03 to 0.66 per DOF, 0.34 on average; 0.35-0.43 in the budget's
metric), and ``dm+b``'s budget with the generic edge looks is narrower
than the errors (mean squared Mahalanobis distance per DOF 2.7-4.0 instead of 1). Fused with
that budget, the 3-sigma figures cover the error of 5-11 of 16-20 holders (a single view's:
13-18) and a two-view fusion accepted a pose 1.08 mm off on a held-back set. So the
measurement's covariance does not support fusing views into an accepted pose today; nothing
in the measurement or the grasp verdict uses this module. It is the tool to measure that,
and to combine poses whose covariances are right (robot stations, hand-eye as a shared
source).

Convention:
    Poses and covariances as :mod:`cutterpose.robot.frames`: ``T_a_b`` with the perturbation
    ``(dt, dphi)`` in the parent frame's axes, ``t = t_hat + dt``, ``R = Exp(dphi) R_hat``;
    every view's pose has the same frames (e.g. ``T_base_holder``).

References:
    T. Kariya, H. Kurata, *Generalized Least Squares*, Wiley 2004, ch. 2 (GLS with a known
    covariance). T. D. Barfoot, *State Estimation for Robotics*, 2017, 7.3 (averaging poses
    on SE(3) by Gauss-Newton).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.linalg import block_diag
from scipy.spatial.transform import Rotation
from scipy.stats import chi2 as chi2_dist

from ..errors import InputError
from ..geometry.pose import Pose
from .frames import PoseCov

__all__ = ["FusedPose", "fuse_poses", "joint_covariance", "sqrt_psd"]

#: views that disagree beyond this false-alarm rate are reported, not fused
AGREEMENT_ALPHA = 1e-3


def sqrt_psd(C: np.ndarray) -> np.ndarray:
    """The symmetric square root of a positive semi-definite matrix."""
    w, V = np.linalg.eigh(0.5 * (C + C.T))
    return (V * np.sqrt(np.clip(w, 0.0, None))) @ V.T


def joint_covariance(cov_meas: list[np.ndarray], rho: float,
                     cov_ind: list[np.ndarray] | None = None,
                     shared: list[tuple[list[np.ndarray], np.ndarray]] | None = None,
                     split: bool = False):
    """``Sigma`` of the module doc (6n x 6n); with ``split`` its three terms as a dict
    (``measurement``, ``independent``, ``shared``).

    Parameters
    ----------
    cov_meas : per view, the measurement's covariance (parent axes), correlated between views
        by ``rho``.
    rho : in [0, 1]; 0 independent views, 1 the same error in every view.
    cov_ind : per view, a further covariance independent between views (robot repeatability).
    shared : ``(G, C_s)`` per shared source: ``G[i]`` (6 x m) maps the source's perturbation to
        view i's, ``C_s`` (m x m) its covariance.
    """
    if not 0.0 <= rho <= 1.0:
        raise InputError(f"the views' correlation must be in [0, 1], got {rho}")
    n = len(cov_meas)
    S = np.vstack([sqrt_psd(C) for C in cov_meas])                    # (6 n, 6)
    diag = block_diag(*cov_meas)
    on_diag = block_diag(*[np.ones((6, 6))] * n).astype(bool)
    terms = {"measurement": np.where(on_diag, diag, rho * S @ S.T),
             "independent": block_diag(*cov_ind) if cov_ind is not None
             else np.zeros((6 * n, 6 * n)),
             "shared": np.zeros((6 * n, 6 * n))}
    for G, C_s in shared or ():
        Gs = np.vstack(G)
        terms["shared"] += Gs @ C_s @ Gs.T
    terms = {k: 0.5 * (v + v.T) for k, v in terms.items()}
    return terms if split else sum(terms.values())


@dataclass(frozen=True)
class FusedPose:
    """The fused pose with its covariance, and how well the views agree.

    Attributes
    ----------
    fused : the fused pose with its covariance (:class:`PoseCov`).
    views : number of views fused.
    chi2, dof, p_value : the residuals' chi-square, its degrees of freedom ``6 (n - 1)`` and
        the probability of a larger one if the covariances are right (1 for one view).
    residuals : (n, 6) each view's perturbation from the fused pose (mm, deg).
    parts : the fused covariance's share of each term of ``Sigma`` (``measurement``,
        ``independent``, ``shared``): ``W Sigma_k W^T`` with ``W`` the estimator's gain; they
        add up to ``fused.cov``.
    """

    fused: PoseCov
    views: int
    chi2: float
    dof: int
    p_value: float
    residuals: np.ndarray
    parts: dict

    @property
    def agree(self) -> bool:
        """The views agree within their covariances (p >= :data:`AGREEMENT_ALPHA`)."""
        return self.p_value >= AGREEMENT_ALPHA

    @property
    def position_3sigma_mm(self) -> float:
        return self.fused.position_3sigma_mm

    @property
    def angle_3sigma_deg(self) -> float:
        return self.fused.angle_3sigma_deg

    def to_dict(self) -> dict:
        return {"fused": self.fused.to_ros_dict(), "views": self.views, "chi2": self.chi2,
                "dof": self.dof, "p_value": self.p_value, "agree": self.agree,
                "position_3sigma_mm": self.position_3sigma_mm,
                "angle_3sigma_deg": self.angle_3sigma_deg,
                "residuals_mm_deg": self.residuals.tolist()}


def _perturbations(R: np.ndarray, t: np.ndarray, mean: Pose) -> np.ndarray:
    """(6n,) the ``(dt, dphi)`` of poses ``R`` (n, 3, 3), ``t`` (n, 3) from ``mean`` (module
    Convention)."""
    dphi = Rotation.from_matrix(R @ mean.R.T).as_rotvec()
    return np.column_stack([t - mean.t_mm, dphi]).ravel()


def fuse_poses(estimates: list[PoseCov], rho: float = 0.0, *,
               cov_ind: list[np.ndarray] | None = None,
               shared: list[tuple[list[np.ndarray], np.ndarray]] | None = None,
               iterations: int = 10) -> FusedPose:
    """Fuse estimates of one transform (module doc).

    Parameters
    ----------
    estimates : the views' poses (the same frames) with the covariance of their measurement
        part (:class:`PoseCov`, parent axes).
    rho, cov_ind, shared : as :func:`joint_covariance`.

    Raises
    ------
    InputError
        No estimate, poses with different frames, or a joint covariance that is singular
        (views that carry no information).
    """
    if not estimates:
        raise InputError("nothing to fuse: no view has a pose")
    frames = {(e.pose.to_frame, e.pose.from_frame) for e in estimates}
    if len(frames) != 1:
        raise InputError(f"the views estimate different transforms: {sorted(frames)}")
    n = len(estimates)
    covs = [e.cov for e in estimates]   # PoseCov checked them (finite, symmetric, PSD)
    terms = joint_covariance(covs, rho, cov_ind, shared, split=True)
    Sig = sum(terms.values())
    try:
        L = np.linalg.cholesky(Sig)
    except np.linalg.LinAlgError:
        raise InputError("the views' joint covariance is singular: a view without "
                         "uncertainty, or views that are copies of each other (rho = 1)") \
            from None
    H = np.tile(np.eye(6), (n, 1))
    LH = np.linalg.solve(L, H)
    cov = np.linalg.inv(LH.T @ LH)
    # the gain W = cov H^T Sigma^-1: delta = W xi
    W = cov @ np.linalg.solve(L.T, LH).T
    best = int(np.argmin([np.trace(C) for C in covs]))
    mean = estimates[best].pose
    Rs = np.stack([e.pose.R for e in estimates])
    ts = np.stack([e.pose.t_mm for e in estimates])
    for _ in range(iterations):
        xi = _perturbations(Rs, ts, mean)
        delta = W @ xi
        mean = Pose(Rotation.from_rotvec(delta[3:]).as_matrix() @ mean.R,
                    mean.t_mm + delta[:3], mean.to_frame, mean.from_frame)
        if np.linalg.norm(delta[:3]) < 1e-9 and np.linalg.norm(delta[3:]) < 1e-12:
            break
    r = _perturbations(Rs, ts, mean)
    z = np.linalg.solve(L, r)
    chi2 = float(z @ z)
    dof = 6 * (n - 1)
    p = 1.0 if dof == 0 else float(chi2_dist.sf(chi2, dof))
    res = r.reshape(n, 6).copy()
    res[:, 3:] = np.degrees(res[:, 3:])
    parts = {k: W @ v @ W.T for k, v in terms.items()}
    return FusedPose(PoseCov(mean, cov), n, chi2, dof, p, res, parts)

