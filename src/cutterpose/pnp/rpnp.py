"""RPnP (Li, Xu & Xie, "A robust O(n) solution to the perspective-n-point problem", PAMI 2012).

1. **Rotation axis** (paper section 3.1): the pair ``(i1, i2)`` whose viewing rays make the
   largest angle (the longest projected edge), found exhaustively as the least ``b_i . b_j`` over
   all pairs of unit bearings ``b_i = (u_i, v_i, 1)/||.||``: deterministic.
2. **Local object frame**: origin ``p0 = (P_i1 + P_i2)/2``, x axis along ``P_i2 - p0``, completed
   by the rule of notes section 3 step 3; ``Pa_i = R_o^T (P_i - p0)``.
3. **Point-triplet constraints** (paper eqs. 3-6): with ``|X_i1| = 1`` and the unknown
   ``t = |X_i2| - c12``, the two laws of cosines of the triangle ``(i1, i2, i)`` eliminate
   ``|X_i|`` and give a quartic ``f_i(t) = g0 t^4 + g1 t^3 + g2 t^2 + g3 t + g4`` per point ``i``
   (coefficients in the notes, section 3 step 4).
4. **The 7th-degree polynomial** (paper eq. 8): ``F(t) = sum_i f_i(t)^2``, and
   ``G = F'/2 = sum_i f_i f_i'`` has degree 7; its real roots with ``G'(t) > 0`` are the local
   minima of ``F`` (at most 4).
5. **Linear recovery** per minimum (paper section 3.3): the axis in the camera frame
   ``x_c = normalise((c12 + t) b_i2 - b_i1)`` fixes ``R = R_x Rot_x(theta) R_o^T`` up to the
   angle ``theta`` about it; ``X_i = R_x Rot_x(theta) Pa_i + T`` and the collinearity equations
   ``u_i X_i3 - X_i1 = 0``, ``v_i X_i3 - X_i2 = 0`` are linear in ``(cos theta, sin theta, T)``
   (least squares, 2n x 5).
6. **Final alignment**: ``theta = atan2(s, c)`` (``c^2 + s^2 = 1`` imposed), ``T`` refitted
   for that rotation, the camera-frame points moved onto their rays ``X_i = b_i ||Xt_i||`` and
   ``(R, t)`` from the rigid alignment of ``P`` to them (AL-ok,
   :func:`~cutterpose.pnp.base.align_rigid`).

Every minimum gives a candidate; :func:`~cutterpose.pnp.base.make_solver` selects by
reprojection error, so the planar two-fold ambiguity shows up in the ambiguity ratio when ``F``
has both minima.

Points behind the camera: for a non-planar model the triangle constraints are met by the mirror
image of the true structure in front of the camera, which no rotation maps onto the model; RPnP
then returns a pose with a gross reprojection error (hundreds of pixels), as OpenCV's SQPnP does,
instead of a falsy estimate (DLT and EPnP return a falsy one). For a planar model the mirror image
*is* a rigid pose (the twin), and the image is explained exactly.

Convention:
    ``P`` (n, 3) object points in mm, ``m`` (n, 2) normalised image coordinates. ``t`` of the
    polynomial is unit-free (depth of ``X_i1`` set to 1); the linear step is in mm.

Deviations from the reference code (notes sections 3 and 8):
    * Exhaustive longest projection (the reference draws n random pairs: its result changes from
      run to run); ``i1`` is the pair's point with the smaller image ``u``, so the result does not
      depend on the order of the input points.
    * ``(c, s)`` normalised to a rotation and ``T`` refitted (the reference keeps the raw linear
      ``(c, s, T)``, a slightly scaled and sheared rotation).
    * AL-ok alignment instead of AL-S (``det Sigma`` test + column flip), which is wrong on
      planar sets in planes other than ``Z = 0``.
    * All minima are returned and selected by RMS reprojection error (the reference returns the
      one with the least ``||E||_F / n``, which ranks the same way).
    * The root filter is relative to the largest root modulus, as in the reference; the
      polynomial's coefficients are scaled to a unit maximum first.
"""

from __future__ import annotations

import numpy as np

from .base import Candidate, align_rigid, make_solver

__all__ = ["candidates", "solve"]


def _complete_frame(x: np.ndarray) -> np.ndarray:
    """Rotation ``[x y z]`` (columns) with first axis ``x`` (notes section 3 step 3)."""
    if abs(x[1]) < abs(x[2]):
        z = np.array([-x[2], 0.0, x[0]])  # x cross e_y
        z /= np.linalg.norm(z)
        y = np.array([z[1] * x[2] - z[2] * x[1], z[2] * x[0] - z[0] * x[2],
                      z[0] * x[1] - z[1] * x[0]])
    else:
        y = np.array([-x[1], x[0], 0.0])  # e_z cross x
        y /= np.linalg.norm(y)
        z = np.array([x[1] * y[2] - x[2] * y[1], x[2] * y[0] - x[0] * y[2],
                      x[0] * y[1] - x[1] * y[0]])
    return np.column_stack([x, y, z / np.linalg.norm(z)])


def _cost_derivative(b: np.ndarray, P: np.ndarray, i1: int, i2: int) -> np.ndarray:
    """Coefficients (t^7 .. t^0) of ``G(t) = sum_i f_i(t) f_i'(t)`` (paper eq. 8)."""
    rest = np.ones(len(P), dtype=bool)
    rest[[i1, i2]] = False
    bi = b[rest]
    c12 = b[i1] @ b[i2]
    c1i = bi @ b[i1]
    c2i = bi @ b[i2]
    s12_2 = 1.0 - c12 * c12
    s1i_2 = 1.0 - c1i * c1i
    D12_2 = np.sum((P[i1] - P[i2]) ** 2)
    D1i_2 = np.sum((P[rest] - P[i1]) ** 2, axis=1)
    D2i_2 = np.sum((P[rest] - P[i2]) ** 2, axis=1)
    A1 = D1i_2 / D12_2
    A2 = A1 * s12_2 - s1i_2
    A3 = c1i * c2i - c12
    A4 = c12 * c2i - c1i
    A6 = (D2i_2 - D12_2 - D1i_2) / (2.0 * D12_2)
    A7 = 1.0 - c12 * c12 - c1i * c1i + c12 * c1i * c2i + A6 * s12_2
    g0 = A6 * A6 - A1 * c2i * c2i
    g1 = 2.0 * (A3 * A6 - A1 * A4 * c2i)
    g2 = A3 * A3 + 2.0 * A6 * A7 - A1 * A4 * A4 - A2 * c2i * c2i
    g3 = 2.0 * (A3 * A7 - A2 * A4 * c2i)
    g4 = A7 * A7 - A2 * A4 * A4
    G = np.array([4 * g0 * g0, 7 * g0 * g1, 6 * g0 * g2 + 3 * g1 * g1,
                  5 * g0 * g3 + 5 * g1 * g2, 4 * g0 * g4 + 4 * g1 * g3 + 2 * g2 * g2,
                  3 * g1 * g4 + 3 * g2 * g3, 2 * g2 * g4 + g3 * g3, g3 * g4])
    return G.sum(axis=1)


def _minima(G: np.ndarray) -> np.ndarray:
    """Real roots of G with G' > 0 (local minima of F)."""
    if not np.all(np.isfinite(G)) or not np.any(G):
        return np.empty(0)
    G = G / np.abs(G).max()
    roots = np.roots(G)
    if roots.size == 0:
        return np.empty(0)
    tol = 1e-3 * np.abs(roots.real).max()
    t = roots.real[np.abs(roots.imag) <= tol]
    dG = np.polyval(np.polyder(G), t)
    return t[dG > 0]


def candidates(P: np.ndarray, m: np.ndarray) -> list[Candidate]:
    """RPnP poses, one per local minimum of the triplet cost; see the module docstring."""
    n = len(P)
    bh = np.column_stack([m, np.ones(n)])
    b = bh / np.linalg.norm(bh, axis=1, keepdims=True)
    # longest projection: least cosine between two rays, exhaustively
    cosines = b @ b.T
    i1, i2 = np.unravel_index(np.argmin(cosines), cosines.shape)
    # order the pair by the image, not by the input order, so that permuting the points does not
    # change the result (the cost is not symmetric in i1, i2 under noise)
    if (m[i1, 0], m[i1, 1]) > (m[i2, 0], m[i2, 1]):
        i1, i2 = i2, i1
    edge = P[i2] - P[i1]
    if not np.any(edge):
        return []
    p0 = 0.5 * (P[i1] + P[i2])
    R_o = _complete_frame(edge / np.linalg.norm(edge))
    Pa = (P - p0) @ R_o

    ts = _minima(_cost_derivative(b, P, i1, i2))
    c12 = b[i1] @ b[i2]
    u, v = m[:, 0], m[:, 1]
    out = []
    for t in ts:
        axis = (c12 + t) * b[i2] - b[i1]
        norm = np.linalg.norm(axis)
        if norm == 0:
            continue
        R_x = _complete_frame(axis / norm)
        r1, r2, r3 = R_x.T
        # X_i = r1 Pa_x + c (r2 Pa_y + r3 Pa_z) + s (r3 Pa_y - r2 Pa_z) + T
        Fc = np.outer(Pa[:, 1], r2) + np.outer(Pa[:, 2], r3)
        Fs = np.outer(Pa[:, 1], r3) - np.outer(Pa[:, 2], r2)
        F0 = np.outer(Pa[:, 0], r1)
        A = np.zeros((2 * n, 5))
        rhs = np.empty(2 * n)
        for row, w in ((0, u), (1, v)):
            A[row::2, 0] = Fc[:, row] - w * Fc[:, 2]
            A[row::2, 1] = Fs[:, row] - w * Fs[:, 2]
            A[row::2, 2 + row] = 1.0
            A[row::2, 4] = -w
            rhs[row::2] = -(F0[:, row] - w * F0[:, 2])
        cs = np.linalg.lstsq(A, rhs, rcond=None)[0]
        theta = np.arctan2(cs[1], cs[0])
        c, s = np.cos(theta), np.sin(theta)
        R_t = R_x @ np.array([[1.0, 0.0, 0.0], [0.0, c, -s], [0.0, s, c]])
        # T for the exact rotation: the same equations with (c, s) fixed
        Y = Pa @ R_t.T
        T = np.linalg.lstsq(A[:, 2:], -(np.concatenate([Y[:, :2] - Y[:, 2:] * m], axis=1)
                                        .ravel()), rcond=None)[0]
        Xt = Y + T
        X = b * np.linalg.norm(Xt, axis=1, keepdims=True) * np.sign(Xt[:, 2:3])
        out.append(align_rigid(P, X))
    return out


solve = make_solver("rpnp", candidates, min_points=4)
