"""DLT: the homography for planar points, the 12-unknown projection-matrix DLT otherwise.

Planar points (singular-value test of :func:`~cutterpose.solvers.pnp.base.is_planar`) are moved into
their plane frame (``W (P - Pbar)`` has zero third coordinate, notes 6.3), then the homography
``H ~ [r1 r2 t]`` with ``m ~ H (X, Y, 1)^T`` is found by the normalised DLT (Hartley &
Zisserman, 2nd ed., Alg. 4.2): both point sets are centred and scaled to an RMS distance of
``sqrt(2)``, ``h`` is the right singular vector of the ``2n x 9`` system with the least singular
value (computed as the least eigenvector of its 9x9 normal matrix, see below), and
``H = T_m^-1 H_n T_P``. Since ``m`` is already ``K^-1`` applied, ``[h1 h2]`` is
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
      noise depend on the units). The null vector is the eigenvector of the least eigenvalue of
      ``A^T A``, built from its Kronecker structure (speed, issue 3): after the normalisation the
      system is well conditioned, and this agrees with the SVD of ``A`` to ~1e-12 deg on the
      holder (notes, speed section). Without the normalisation, squaring the condition number
      would cost accuracy.
    * Planar scale from both columns (mean singular value of ``[h1 h2]``), not ``||h1||`` alone.
    * The 3-D DLT is never applied to planar points (its null space is 4-dimensional there).
    * No similarity alignment (AL-S) at the end: ``R`` is the polar factor of ``A`` directly.
    * Planar sets in any plane, not only ``Z = 0``, through the plane frame.
"""

from __future__ import annotations

import numpy as np

from ...errors import DegenerateInputError
from ..method import CorrespondenceMethod
from .base import (
    Candidate,
    is_planar,
    kron_normal,
    make_solver,
    model_cache,
    plane_frame,
    smallest_eigvecs,
)

__all__ = ["Dlt", "candidates", "homography_pose", "projection_dlt_pose", "solve"]


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


def _polar2(M: np.ndarray) -> tuple[np.ndarray, float]:
    """:func:`_polar` of a 3x2 matrix in closed form: with ``G = M^T M``, ``d = sqrt(det G)``
    and ``tau = sqrt(tr G + 2 d)``, ``G^(-1/2) = adj(G + d I) / (d tau)`` and the mean singular
    value is ``tau / 2``. Plain floats: an SVD costs more than all of this."""
    (a0, b0), (a1, b1), (a2, b2) = M.tolist()
    ga = a0 * a0 + a1 * a1 + a2 * a2
    gb = a0 * b0 + a1 * b1 + a2 * b2
    gc = b0 * b0 + b1 * b1 + b2 * b2
    det = ga * gc - gb * gb
    if not det > 1e-12 * (ga + gc) ** 2:  # (near) rank-deficient or not finite: the SVD
        return _polar(M)
    d = det**0.5
    tau = (ga + gc + 2.0 * d) ** 0.5
    k = 1.0 / (d * tau)
    p00, p01, p11 = (gc + d) * k, -gb * k, (ga + d) * k
    return np.array([[a0 * p00 + b0 * p01, a0 * p01 + b0 * p11],
                     [a1 * p00 + b1 * p01, a1 * p01 + b1 * p11],
                     [a2 * p00 + b2 * p01, a2 * p01 + b2 * p11]]), 0.5 * tau


def _image_normalisation(m: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """:func:`_normalising_transform` of the image points, returned as ``T^-1`` (closed form)
    and the normalised points."""
    n = len(m)
    c = m.sum(axis=0) / n  # mean, without its overhead
    mc = m - c
    s = np.sqrt(2.0) / np.sqrt(np.sum(mc * mc) / n)
    cx, cy = c.tolist()
    Tinv = np.array([[1.0 / s, 0.0, cx], [0.0, 1.0 / s, cy], [0.0, 0.0, 1.0]])
    return Tinv, mc * s


def _outer_rows(X: np.ndarray) -> np.ndarray:
    """(n, d*d) outer products of the rows of X (model-only: cached)."""
    O = (X[:, :, None] * X[:, None, :]).reshape(len(X), -1)
    O.flags.writeable = False
    return O


def _homography_model(Q2: np.ndarray):
    Tq, qn = _normalising_transform(Q2)
    return Tq, _outer_rows(np.column_stack([qn, np.ones(len(qn))]))


def homography_pose(Q2: np.ndarray, m: np.ndarray, model=None) -> Candidate:
    """Pose of plane points ``Q2`` (n, 2; plane ``Z = 0``) from the normalised homography.

    ``h`` is the eigenvector of the least eigenvalue of ``A^T A`` (built from its structure,
    :func:`~cutterpose.solvers.pnp.base.kron_normal`): the same null vector as the SVD of ``A``, and
    after Hartley normalisation ``A`` is well conditioned, so squaring its condition number
    costs nothing measurable (notes, speed section). ``model`` is the cached
    :func:`_homography_model` of ``Q2``."""
    Tq, O = model if model is not None else _homography_model(Q2)
    Tm_inv, mn = _image_normalisation(m)
    h = smallest_eigvecs(kron_normal(O, mn, coord_outer=True), 1)[:, 0]
    H = Tm_inv @ (h.reshape(3, 3) @ Tq)
    # the plane-frame origin (the centroid) must lie in front: its depth is H[2, 2] / lambda
    if H[2, 2] < 0:
        H = -H
    R12, lam = _polar2(H[:, :2])
    R = np.empty((3, 3))
    R[:, :2] = R12
    R[:, 2] = np.cross(R12[:, 0], R12[:, 1])
    return R, H[:, 2] / lam


def _projection_model(P: np.ndarray):
    TX, Xn = _normalising_transform(P)
    return TX, _outer_rows(np.column_stack([Xn, np.ones(len(Xn))]))


def projection_dlt_pose(P: np.ndarray, m: np.ndarray, model=None) -> Candidate:
    """Pose from the normalised 12-unknown DLT of ``[R | t]`` (non-planar points); ``p`` from
    the normal matrix as in :func:`homography_pose`."""
    TX, O = model if model is not None else _projection_model(P)
    Tm_inv, mn = _image_normalisation(m)
    p = smallest_eigvecs(kron_normal(O, mn, coord_outer=True), 1)[:, 0]
    Pm = Tm_inv @ (p.reshape(3, 4) @ TX)
    if np.linalg.det(Pm[:, :3]) < 0:
        Pm = -Pm
    R, lam = _polar(Pm[:, :3])
    return R, Pm[:, 3] / lam


def candidates(P: np.ndarray, m: np.ndarray) -> list[Candidate]:
    """The DLT pose (one candidate); see the module docstring."""
    cache = model_cache(P)
    model = cache.get("dlt")
    if model is None:  # everything that depends on the model only, once per model
        if is_planar(P):
            W, c = plane_frame(P)
            Q = (P - c) @ W.T
            model = (True, W, W @ c, _homography_model(Q[:, :2]))
        elif len(P) < 6:
            raise DegenerateInputError(f"the DLT of non-planar points needs at least 6 points, "
                                       f"got {len(P)}")
        else:
            model = (False, None, None, _projection_model(P))
        cache["dlt"] = model
    planar, W, Wc, sub = model
    if planar:
        Rp, tp = homography_pose(None, m, sub)
        return [(Rp @ W, tp - Rp @ Wc)]
    return [projection_dlt_pose(P, m, sub)]


solve = make_solver("dlt", candidates, min_points=4)


class Dlt(CorrespondenceMethod):
    name = "dlt"
    description = "DLT (homography for planar points)"
    solve = staticmethod(solve)
