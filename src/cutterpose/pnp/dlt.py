"""DLT: the homography for planar points, the 12-unknown projection-matrix DLT otherwise.

Planar points (singular-value test of :func:`~cutterpose.pnp.base.is_planar`) are moved into
their plane frame (``W (P - Pbar)`` has zero third coordinate, notes 6.3), then the homography
``H ~ [r1 r2 t]`` with ``m ~ H (X, Y, 1)^T`` is found by the normalised DLT (Hartley &
Zisserman, 2nd ed., Alg. 4.2): both point sets are centred and scaled to an RMS distance of
``sqrt(2)``, ``h`` is the right singular vector of the ``2n x 9`` system with the least singular
value, and ``H = T_m^-1 H_n T_P``. Since ``m`` is already ``K^-1`` applied, ``[h1 h2]`` is
``lambda [r1 r2]``: the nearest pair of orthonormal columns is its orthogonal polar factor, the
scale ``lambda`` the mean of its two singular values, ``r3 = r1 x r2`` and ``t = h3 / lambda``
(H&Z section 8.8; Zhang 2000, section 3.1). The sign of ``H`` is chosen so that the plane's
centroid (the plane-frame origin) has positive depth.

Non-planar points use the projection-matrix DLT (H&Z Alg. 7.1): ``p`` in R^12 (rows of
``[R | t]`` up to scale), two rows per point, ``x_i = (P_i, 1)``::

    [x_i^T, 0, -u_i x_i^T] p = 0,    [0, x_i^T, -v_i x_i^T] p = 0

with Hartley normalisation of the 3-D points (RMS distance ``sqrt(3)``) and of the image points.
``[A | a] = T_m^-1 P_n T_X``; ``det A = lambda^3 det R`` fixes the sign of ``lambda``,
``R = polar(A)``, ``lambda`` = mean singular value of ``A``, ``t = a / lambda``.

Convention:
    ``P`` (n, 3) object points in mm, ``m`` (n, 2) normalised image coordinates
    ``K^-1 ideal_px``; the pose maps object to camera frame, ``X = R P + t``.

Deviations from the reference code (notes sections 1 and 8):
    * Hartley normalisation of both point sets (the reference has none, so its results under
      noise depend on the units); SVD of the system itself, not an eigenvector of ``D^T D``
      (which squares the condition number).
    * Planar scale from both columns (mean singular value of ``[h1 h2]``), not ``||h1||`` alone.
    * The 3-D DLT is never applied to planar points (its null space is 4-dimensional there).
    * No similarity alignment (AL-S) at the end: ``R`` is the polar factor of ``A`` directly.
    * Planar sets in any plane, not only ``Z = 0``, through the plane frame.
"""

from __future__ import annotations

import numpy as np

from ..errors import DegenerateInputError
from .base import Candidate, is_planar, make_solver, plane_frame

__all__ = ["candidates", "homography_pose", "projection_dlt_pose", "solve"]


def _normalising_transform(x: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Hartley normalisation: ``T`` ((d+1) x (d+1)) and the normalised points ``T x``.

    Centroid to the origin, RMS distance from it ``sqrt(d)``.
    """
    d = x.shape[1]
    c = x.mean(axis=0)
    xc = x - c
    rms = np.sqrt(np.mean(np.sum(xc * xc, axis=1)))
    s = np.sqrt(d) / rms
    T = np.eye(d + 1)
    T[:d, :d] *= s
    T[:d, d] = -s * c
    return T, xc * s


def _polar(A: np.ndarray) -> tuple[np.ndarray, float]:
    """Orthogonal polar factor of ``A`` (3x3 or 3x2) and the mean singular value."""
    U, s, Vt = np.linalg.svd(A, full_matrices=False)
    return U @ Vt, float(s.mean())


def homography_pose(Q2: np.ndarray, m: np.ndarray) -> Candidate:
    """Pose of plane points ``Q2`` (n, 2; plane ``Z = 0``) from the normalised homography."""
    Tq, qn = _normalising_transform(Q2)
    Tm, mn = _normalising_transform(m)
    n = len(m)
    xh = np.column_stack([qn, np.ones(n)])
    A = np.zeros((2 * n, 9))
    A[0::2, 0:3] = xh
    A[0::2, 6:9] = -mn[:, 0:1] * xh
    A[1::2, 3:6] = xh
    A[1::2, 6:9] = -mn[:, 1:2] * xh
    h = np.linalg.svd(A, full_matrices=False)[2][-1]
    H = np.linalg.solve(Tm, h.reshape(3, 3) @ Tq)
    # the plane-frame origin (the centroid) must lie in front: its depth is H[2, 2] / lambda
    if H[2, 2] < 0:
        H = -H
    R12, lam = _polar(H[:, :2])
    R = np.column_stack([R12, np.cross(R12[:, 0], R12[:, 1])])
    return R, H[:, 2] / lam


def projection_dlt_pose(P: np.ndarray, m: np.ndarray) -> Candidate:
    """Pose from the normalised 12-unknown DLT of ``[R | t]`` (non-planar points)."""
    TX, Xn = _normalising_transform(P)
    Tm, mn = _normalising_transform(m)
    n = len(m)
    xh = np.column_stack([Xn, np.ones(n)])
    A = np.zeros((2 * n, 12))
    A[0::2, 0:4] = xh
    A[0::2, 8:12] = -mn[:, 0:1] * xh
    A[1::2, 4:8] = xh
    A[1::2, 8:12] = -mn[:, 1:2] * xh
    p = np.linalg.svd(A, full_matrices=False)[2][-1]
    Pm = np.linalg.solve(Tm, p.reshape(3, 4) @ TX)
    if np.linalg.det(Pm[:, :3]) < 0:
        Pm = -Pm
    R, lam = _polar(Pm[:, :3])
    return R, Pm[:, 3] / lam


def candidates(P: np.ndarray, m: np.ndarray) -> list[Candidate]:
    """The DLT pose (one candidate); see the module docstring."""
    if is_planar(P):
        W, c = plane_frame(P)
        Q = (P - c) @ W.T
        Rp, tp = homography_pose(Q[:, :2], m)
        return [(Rp @ W, tp - Rp @ (W @ c))]
    if len(P) < 6:
        raise DegenerateInputError(f"the DLT of non-planar points needs at least 6 points, got "
                                   f"{len(P)}")
    return [projection_dlt_pose(P, m)]


solve = make_solver("dlt", candidates, min_points=4)
