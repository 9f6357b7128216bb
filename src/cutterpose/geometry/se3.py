"""SE(3) and SO(3) helpers: the cross-product matrix, the exponential map and its inverse.

Twists ``xi = (omega [rad], rho [mm])`` with ``Exp(xi) = (Exp(omega), V(omega) rho)`` where
``V = J_l`` is the left Jacobian of SO(3) (T. Barfoot, *State Estimation for Robotics*, 2017,
sec. 7.1). Rotations from and to rotation vectors go through SciPy's
:class:`~scipy.spatial.transform.Rotation`; what SciPy has no function for (``V``, the twist
of a rigid motion) is written here.

Examples
--------
>>> import numpy as np
>>> skew([1.0, 2.0, 3.0]) @ np.array([4.0, 5.0, 6.0])      # [v]x w = v x w
array([-3.,  6., -3.])
>>> R, t_mm = se3_exp(np.array([0.0, 0.0, np.pi / 2, 10.0, 0.0, 0.0]))
>>> np.round(R @ [1.0, 0.0, 0.0], 12) + 0.0
array([0., 1., 0.])
>>> np.allclose(se3_log(R, t_mm), [0.0, 0.0, np.pi / 2, 10.0, 0.0, 0.0])
True
"""

from __future__ import annotations

import math

import numpy as np
from scipy.spatial.transform import Rotation

from .pose import Pose

__all__ = ["skew", "left_jacobian", "se3_exp", "se3_log", "relative", "compose"]


def skew(v) -> np.ndarray:
    """``[v]x``, the 3 x 3 matrix of ``v x .``, for one vector (3,) or many (..., 3)."""
    v = np.asarray(v, float)
    z = np.zeros(v.shape[:-1])
    return np.stack([np.stack([z, -v[..., 2], v[..., 1]], -1),
                     np.stack([v[..., 2], z, -v[..., 0]], -1),
                     np.stack([-v[..., 1], v[..., 0], z], -1)], -2)


def left_jacobian(w: np.ndarray) -> np.ndarray:
    """``V(w) = I + (1 - cos a)/a^2 [w]x + (a - sin a)/a^3 [w]x^2``, the left Jacobian of
    SO(3) at the rotation vector ``w`` (its series to second order below ``|w| = 1e-6``)."""
    a2 = float(w @ w)
    W = skew(w)
    if a2 < 1e-12:
        return np.eye(3) + 0.5 * W + (W @ W) / 6.0
    a = math.sqrt(a2)
    return np.eye(3) + ((1 - math.cos(a)) / a2) * W + ((a - math.sin(a)) / (a2 * a)) * (W @ W)


def se3_exp(xi: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """``Exp`` of a twist ``(omega [rad], rho [mm])`` -> ``(R, t_mm)``."""
    xi = np.asarray(xi, float)
    w = xi[:3]
    return Rotation.from_rotvec(w).as_matrix(), left_jacobian(w) @ xi[3:]


def se3_log(R: np.ndarray, t_mm: np.ndarray) -> np.ndarray:
    """``Log`` of ``(R, t_mm)`` -> twist ``(omega [rad], rho [mm])``."""
    w = Rotation.from_matrix(R).as_rotvec()
    return np.concatenate([w, np.linalg.solve(left_jacobian(w), np.asarray(t_mm, float))])


def relative(a: Pose, b: Pose) -> tuple[np.ndarray, np.ndarray]:
    """``a b^{-1}`` as ``(R, t_mm)``: the motion that takes pose ``b`` to pose ``a``."""
    R = a.R @ b.R.T
    return R, a.t_mm - R @ b.t_mm


def compose(R: np.ndarray, t_mm: np.ndarray, pose: Pose) -> Pose:
    """``(R, t_mm) pose``, re-orthonormalised (products of many rotations drift by ~1e-16
    per step)."""
    Rn = R @ pose.R
    u, _, vt = np.linalg.svd(Rn)
    return Pose(u @ vt, R @ pose.t_mm + t_mm)
