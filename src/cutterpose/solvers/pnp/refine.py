"""Levenberg-Marquardt refinement of a PnP result on the pixel reprojection error (``<solver>+lm``).

The cost is the sum of squared differences between the observed ideal (undistorted) pixels and
the projection of the model through ``K``::

    E(R, t) = sum_i || K pi(R P_i + t) - x_i ||^2,     pi(X) = (X_1/X_3, X_2/X_3)

the maximum-likelihood pose under i.i.d. Gaussian pixel noise (in the ideal image; for a
distorting camera the undistortion is treated as exact). It is minimised by MINPACK's LM
(:func:`scipy.optimize.least_squares`, ``method="lm"``, analytic Jacobian). Parameters: a rotation
vector increment ``w`` about the start rotation and the translation, ``R = Exp(w) R0`` (no gimbal
lock anywhere near the solution) and ``t``. With ``Y_i = Exp(w) R0 P_i`` and ``X_i = Y_i + t``,

    dX_i/dw = -[Y_i]_x J_l(w),   J_l(w) = I + (1 - cos a)/a^2 [w]_x + (a - sin a)/a^3 [w]_x^2

(the left Jacobian of SO(3), ``a = |w|``), and ``dX_i/dt = I``; the pixel Jacobian is
``d(K pi)/dX = [[fx/z, s/z, -(fx x + s y)/z^2], [0, fy/z, -fy y/z^2]]``.

Every candidate of the base solver is refined (so the two planar minima both survive when the base
solver found both), near-duplicates after refinement are merged, and
:func:`~cutterpose.solvers.pnp.base.select` picks by reprojection error again, which keeps the
ambiguity
ratio meaningful. For a planar model one more start is added: the best candidate's plane tilted
to its mirror image about the line of sight to the plane's centroid (the exact ambiguity under
weak perspective, e.g. Schweighofer & Pinz, PAMI 2006), so that the second minimum of the
planar ambiguity is searched for even when the base solver returned a single pose.

Convention:
    ``R_cam_holder``, ``t_cam_holder_mm`` as in :mod:`cutterpose.geometry.pose`; residuals in ideal
    pixels; ``points_px`` observed (distorted) pixels as everywhere.
"""

from __future__ import annotations

import time
from collections.abc import Callable

import numpy as np
from scipy.optimize import least_squares

from ...geometry.se3 import skew
from ..estimate import PoseEstimate
from ..method import CorrespondenceMethod, PoseMethod
from .base import Candidate, is_planar, model_points, plane_frame, select

__all__ = ["LMRefined", "refine_pose", "planar_flip", "with_refinement"]

# merge refined candidates closer than this (same local minimum reached from two starts)
_SAME_ROT = 1e-6     # max |R_a - R_b| entry
_SAME_T_REL = 1e-6   # |t_a - t_b| / |t_b|


def _exp_and_jl(w: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Rodrigues' ``Exp(w)`` and the left Jacobian ``J_l(w)``."""
    a2 = float(w @ w)
    W = skew(w)
    W2 = W @ W
    if a2 < 1e-12:
        # series to second order: exact to double precision below |w| = 1e-6
        return np.eye(3) + W + 0.5 * W2, np.eye(3) + 0.5 * W + W2 / 6.0
    a = np.sqrt(a2)
    s, c = np.sin(a), np.cos(a)
    R = np.eye(3) + (s / a) * W + ((1 - c) / a2) * W2
    J = np.eye(3) + ((1 - c) / a2) * W + ((a - s) / (a2 * a)) * W2
    return R, J


def refine_pose(R0: np.ndarray, t0: np.ndarray, P: np.ndarray, ideal_px: np.ndarray,
                K: np.ndarray, max_nfev: int = 100) -> tuple[np.ndarray, np.ndarray, int]:
    """LM from ``(R0, t0)`` on the ideal-pixel reprojection error; returns ``(R, t, nfev)``.

    Parameters
    ----------
    R0, t0 : start pose (object -> camera), t in the units of ``P``.
    P : (n, 3) object points.
    ideal_px : (n, 2) observed points in ideal (undistorted) pixels.
    K : (3, 3) upper-triangular intrinsics.
    """
    fx, s, cx, fy, cy = K[0, 0], K[0, 1], K[0, 2], K[1, 1], K[1, 2]
    RP0 = P @ R0.T
    obs = ideal_px.ravel()
    n = len(P)

    def project(x):
        R, J = _exp_and_jl(x[:3])
        Y = RP0 @ R.T
        X = Y + x[3:]
        return Y, X, J

    def fun(x):
        _, X, _ = project(x)
        iz = 1.0 / X[:, 2]
        u = (fx * X[:, 0] + s * X[:, 1]) * iz + cx
        v = fy * X[:, 1] * iz + cy
        return np.column_stack([u, v]).ravel() - obs

    def jac(x):
        Y, X, J = project(x)
        iz = 1.0 / X[:, 2]
        dp = np.zeros((n, 2, 3))
        dp[:, 0, 0] = fx * iz
        dp[:, 0, 1] = s * iz
        dp[:, 0, 2] = -(fx * X[:, 0] + s * X[:, 1]) * iz * iz
        dp[:, 1, 1] = fy * iz
        dp[:, 1, 2] = -fy * X[:, 1] * iz * iz
        dXdw = -skew(Y) @ J  # (n, 3, 3)
        out = np.empty((n, 2, 6))
        out[:, :, :3] = dp @ dXdw
        out[:, :, 3:] = dp
        return out.reshape(2 * n, 6)

    x0 = np.concatenate([np.zeros(3), np.asarray(t0, float).reshape(3)])
    res = least_squares(fun, x0, jac=jac, method="lm", x_scale="jac", xtol=1e-12,
                        ftol=1e-12, gtol=1e-12, max_nfev=max_nfev)
    R, _ = _exp_and_jl(res.x[:3])
    return R @ R0, res.x[3:].copy(), int(res.nfev)


def planar_flip(R: np.ndarray, t: np.ndarray, P: np.ndarray) -> Candidate:
    """The other pose of the planar two-fold ambiguity, to first order.

    The plane's normal ``n`` is mirrored about the line of sight ``d`` to its centroid
    (``n' = 2 (n.d) d - n``) by a rotation about the centroid; under weak perspective both poses
    project identically, under full perspective LM takes the result to the second minimum.
    """
    W, c = plane_frame(P)
    n = R @ W[2]
    pc = R @ c + t
    d = pc / np.linalg.norm(pc)
    n2 = 2.0 * (n @ d) * d - n
    axis = np.cross(n, n2)
    sin_a = np.linalg.norm(axis)
    if sin_a < 1e-12:
        return R, t  # fronto-parallel: the two poses coincide
    angle = np.arctan2(sin_a, n @ n2)
    Rf, _ = _exp_and_jl(axis / sin_a * angle)
    R2 = Rf @ R
    return R2, pc - R2 @ c


def with_refinement(base_solve: Callable[..., PoseEstimate], name: str) -> Callable[...,
                                                                                  PoseEstimate]:
    """``<solver>+lm``: the base solver, then LM on every candidate, then re-selection.

    The returned function has the common signature ``solve(points_px, camera, model)``. Input
    errors are raised by the base solver; a failed base estimate is returned as a failure under
    ``name``.
    """

    def solve(points_px, camera, model) -> PoseEstimate:
        t_start = time.perf_counter()
        base = base_solve(points_px, camera, model)
        if not base:
            est = PoseEstimate.failure(name, base.reason, info={"base": dict(base.info)})
            est.time_ms = (time.perf_counter() - t_start) * 1e3
            return est
        P = model_points(model)
        x = np.asarray(points_px, float)
        ideal = camera.undistort_px(x)
        m = camera.normalize_px(x)
        K = camera.K
        starts = list(base.candidates)
        if is_planar(P):
            starts.append(planar_flip(base.R_cam_holder, base.t_cam_holder_mm, P))
        refined: list[Candidate] = []
        nfev = 0
        for R0, t0 in starts:
            R, t, k = refine_pose(R0, t0, P, ideal, K)
            nfev += k
            if any(np.abs(R - Ra).max() < _SAME_ROT
                   and np.linalg.norm(t - ta) < _SAME_T_REL * np.linalg.norm(ta)
                   for Ra, ta in refined):
                continue
            refined.append((R, t))
        est = select(name, refined, P, m, camera.focal_px)
        est.info.update({"base": dict(base.info), "base_residual_px": base.residual_px,
                         "n_starts": len(starts), "nfev": nfev})
        est.time_ms = (time.perf_counter() - t_start) * 1e3
        return est

    solve.__name__ = f"solve_{name.replace('-', '_').replace('+', '_')}"
    solve.__doc__ = f"{name}: ``solve(points_px, camera, model) -> PoseEstimate``."
    return solve


class LMRefined(CorrespondenceMethod):
    """``<method>+lm``: a correspondence method followed by Levenberg-Marquardt on the pixel
    reprojection error (:func:`with_refinement`)."""

    def __init__(self, base: PoseMethod):
        self.base_method = base
        self.name = f"{base.name}+lm"
        self.description = base.description + " + LM refinement"
        self._solve = with_refinement(base.solve, self.name)

    def solve(self, points_px, camera, model) -> PoseEstimate:
        return self._solve(points_px, camera, model)

    def __reduce__(self):
        # the refined solver is a closure: rebuild it from the base method
        return (LMRefined, (self.base_method,))
