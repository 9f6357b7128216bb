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

import math
from functools import cache

import numpy as np
from scipy.linalg.lapack import dgeev as _dgeev

from .base import Candidate, align_rigid_many, make_solver, model_cache, svd_small

__all__ = ["candidates", "solve"]

_DER7 = np.arange(7.0, 0.0, -1.0)
_POW6 = np.arange(6.0, -1.0, -1.0)
_SUB7 = (np.arange(1, 7), np.arange(6))
_COMPANION7 = np.zeros((7, 7))
_COMPANION7[_SUB7] = 1.0  # the sub-diagonal of a degree-7 companion matrix


def _frame_rows(x) -> list[list[float]]:
    """:func:`_complete_frame` of a unit 3-vector as nested lists (rows), on Python floats:
    numpy's per-call overhead is most of the cost at this size."""
    x0, x1, x2 = x
    if abs(x1) < abs(x2):
        nz = math.sqrt(x2 * x2 + x0 * x0)
        z0, z1, z2 = -x2 / nz, 0.0, x0 / nz  # x cross e_y
        y0, y1, y2 = z1 * x2 - z2 * x1, z2 * x0 - z0 * x2, z0 * x1 - z1 * x0
    else:
        ny = math.sqrt(x1 * x1 + x0 * x0)
        y0, y1, y2 = -x1 / ny, x0 / ny, 0.0  # e_z cross x
        z0, z1, z2 = x1 * y2 - x2 * y1, x2 * y0 - x0 * y2, x0 * y1 - x1 * y0
    nz = math.sqrt(z0 * z0 + z1 * z1 + z2 * z2)
    return [[x0, y0, z0 / nz], [x1, y1, z1 / nz], [x2, y2, z2 / nz]]


def _complete_frame(x: np.ndarray) -> np.ndarray:
    """Rotation ``[x y z]`` (columns) with first axis ``x`` (notes section 3 step 3)."""
    return np.array(_frame_rows(x.tolist()))


@cache
def _fdf_map() -> np.ndarray:
    """(8, 25): ``G = _fdf_map() @ vec(g g^T)`` for ``G = f f'`` summed over the points, with
    ``f = sum_a g_a t^(4-a)``: the coefficient of ``t^(7-k)`` is ``sum_(a+b=k) (4-b) g_a g_b``."""
    M = np.zeros((8, 5, 5))
    for a in range(5):
        for b in range(4):  # g_4 is constant: no t^-1 term
            M[a + b, a, b] = 4 - b
    return M.reshape(8, 25)


def _pair_model(P: np.ndarray, i1: int, i2: int):
    """What depends on the model and the axis pair only (cached per model and pair: the
    holder's longest projection comes from a few pairs): the other points' mask, the squared
    distances ``D12^2``, ``D1i^2``, ``D2i^2``, and the local frame ``R_o`` with ``Pa``."""
    cache = model_cache(P).setdefault("rpnp", {})
    pm = cache.get((i1, i2))
    if pm is None:
        rest = np.ones(len(P), dtype=bool)
        rest[[i1, i2]] = False
        Pr = P[rest]
        D12_2 = float(np.sum((P[i1] - P[i2]) ** 2))
        D1i_2 = np.sum((Pr - P[i1]) ** 2, axis=1)
        D2i_2 = np.sum((Pr - P[i2]) ** 2, axis=1)
        edge = P[i2] - P[i1]
        if np.any(edge):
            p0 = 0.5 * (P[i1] + P[i2])
            R_o = _complete_frame(edge / np.linalg.norm(edge))
            Pa = (P - p0) @ R_o
        else:
            Pa = None
        # the distance terms of the quartics (A1, A6 of the notes) are model-only too
        A1 = D1i_2 / D12_2
        A6 = (D2i_2 - D12_2 - D1i_2) / (2.0 * D12_2)
        pm = cache[(i1, i2)] = (rest, D12_2, D1i_2, D2i_2, Pa, A1, A6, A6 * A6)
    return pm


def _cost_derivative(b: np.ndarray, P: np.ndarray, i1: int, i2: int) -> np.ndarray:
    """Coefficients (t^7 .. t^0) of ``G(t) = sum_i f_i(t) f_i'(t)`` (paper eq. 8)."""
    rest, _, _, _, _, A1, A6, A6_2 = _pair_model(P, i1, i2)
    c12 = float(b[i1] @ b[i2])
    c1i, c2i = (b[[i1, i2]] @ b[rest].T)  # one product for both cosines
    s12_2 = 1.0 - c12 * c12
    c1i_2 = c1i * c1i
    c2i_2 = c2i * c2i
    A2 = A1 * s12_2 - (1.0 - c1i_2)
    A3 = c1i * c2i - c12
    A4 = c12 * c2i - c1i
    A7 = s12_2 - c1i_2 + c12 * c1i * c2i + A6 * s12_2
    A1A4 = A1 * A4
    A2A4 = A2 * A4
    g = np.empty((5, len(c1i)))
    g[0] = A6_2 - A1 * c2i_2
    g[1] = 2.0 * (A3 * A6 - A1A4 * c2i)
    g[2] = A3 * A3 + 2.0 * A6 * A7 - A1A4 * A4 - A2 * c2i_2
    g[3] = 2.0 * (A3 * A7 - A2A4 * c2i)
    g[4] = A7 * A7 - A2A4 * A4
    # sum_i f_i f_i' from the 5x5 Gram matrix of the quartics' coefficients
    return _fdf_map() @ (g @ g.T).ravel()


def _roots(p: np.ndarray) -> np.ndarray:
    """``np.roots(p)``: the eigenvalues of the companion matrix, through LAPACK dgeev directly
    (the routine behind np.linalg.eigvals; np.roots' own overhead was most of its 40 us)."""
    n_trailing = 0
    if p[0] == 0 or p[-1] == 0:  # strip leading zeros, count trailing ones (zero roots)
        nz = np.flatnonzero(p)
        if nz.size == 0:
            return np.empty(0)
        n_trailing = len(p) - nz[-1] - 1
        p = p[nz[0]:nz[-1] + 1]
    N = len(p)
    roots = np.empty(0, dtype=complex)
    if N > 1:
        A = np.zeros((N - 1, N - 1))
        A[np.arange(1, N - 1), np.arange(N - 2)] = 1.0  # np.diag(np.ones(N - 2), -1)
        A[0, :] = -p[1:] / p[0]
        wr, wi, _, _, info = _dgeev(A, compute_vl=0, compute_vr=0)
        roots = np.linalg.eigvals(A) if info != 0 else wr + 1j * wi
    if n_trailing:
        roots = np.concatenate([roots, np.zeros(n_trailing, roots.dtype)])
    return roots


def _minima(G: np.ndarray) -> np.ndarray:
    """Real roots of G with G' > 0 (local minima of F)."""
    gmax = float(np.abs(G).max())
    if not 0.0 < gmax < math.inf:  # all zero, or not finite (NaN fails every comparison)
        return np.empty(0)
    G = G / gmax
    if G[0] != 0.0 and G[-1] != 0.0:
        # np.roots without its overhead: eigenvalues of the companion matrix by dgeev (the
        # routine behind np.linalg.eigvals), kept as real and imaginary parts
        A = _COMPANION7.copy()
        A[0] = -G[1:] / G[0]
        wr, wi, _, _, info = _dgeev(A, compute_vl=0, compute_vr=0)
        if info != 0:
            r = np.linalg.eigvals(A)
            wr, wi = r.real, r.imag
    else:
        roots = _roots(G)
        if roots.size == 0:
            return np.empty(0)
        wr, wi = roots.real, roots.imag
    tol = 1e-3 * np.abs(wr).max()
    t = wr[np.abs(wi) <= tol]
    dG = (t[:, None] ** _POW6) @ (G[:-1] * _DER7)  # np.polyval(np.polyder(G), t)
    return t[dG > 0]


def _inv_sym3(A: np.ndarray) -> np.ndarray:
    """Inverse of a symmetric positive definite 3x3 matrix by cofactors (np.linalg.inv's
    per-call overhead is most of its cost at this size)."""
    (a, b, c), (_, d, e), (_, _, f) = A.tolist()
    c00, c01, c02 = d * f - e * e, c * e - b * f, b * e - c * d
    c11, c12, c22 = a * f - c * c, b * c - a * e, a * d - b * b
    det = a * c00 + b * c01 + c * c02
    return np.array([[c00, c01, c02], [c01, c11, c12], [c02, c12, c22]]) / det


def _recover_one(t: float, b: np.ndarray, m: np.ndarray, Pa: np.ndarray, i1: int,
                 i2: int) -> np.ndarray | None:
    """Camera-frame points for one root ``t`` (step 6 of the notes), as in :func:`candidates`'
    batched path: ``X_i = R_x Rot_x(theta) Pa_i + T`` with ``(cos, sin, T)`` from the linear
    least squares of ``u X3 - X1 = 0``, ``v X3 - X2 = 0``, ``theta`` from the direction of
    ``(cos, sin)``, ``T`` re-solved for that exact rotation, then each point moved onto its ray
    keeping its range. Returns (n, 3), or None for a degenerate axis."""
    c12 = float(b[i1] @ b[i2])
    ax = ((c12 + t) * b[i2] - b[i1]).tolist()
    nrm = math.sqrt(ax[0] * ax[0] + ax[1] * ax[1] + ax[2] * ax[2])
    if nrm == 0.0:
        return None
    (a1, a2, a3), (b1, b2, b3), (d1, d2, d3) = _frame_rows([ax[0] / nrm, ax[1] / nrm,
                                                             ax[2] / nrm])
    # columns r1 = (a1, b1, d1), r2 = (a2, b2, d2), r3 = (a3, b3, d3) of R_x
    u, v = m[:, 0], m[:, 1]
    px, py, pz = Pa[:, 0], Pa[:, 1], Pa[:, 2]
    # x rows: (u r_z - r_x) . term, y rows: (v r_z - r_y) . term, for the three terms
    e1x, e2x, e3x = u * d1 - a1, u * d2 - a2, u * d3 - a3
    e1y, e2y, e3y = v * d1 - b1, v * d2 - b2, v * d3 - b3
    n = len(m)
    M = np.empty((2 * n, 5))
    M[:n, 0] = e2x * py + e3x * pz
    M[n:, 0] = e2y * py + e3y * pz
    M[:n, 1] = e3x * py - e2x * pz
    M[n:, 1] = e3y * py - e2y * pz
    M[:n, 2:] = (-1.0, 0.0, 0.0)
    M[n:, 2:] = (0.0, -1.0, 0.0)
    M[:n, 4] = u
    M[n:, 4] = v
    r = np.concatenate([-e1x * px, -e1y * px])
    N = M.T @ M
    g = M.T @ r
    # (c, s) through the Schur complement of the T block (what the batched path's projection
    # computes); only its direction is used
    NT_inv = _inv_sym3(N[2:, 2:])
    S = N[:2, :2] - N[:2, 2:] @ NT_inv @ N[2:, :2]
    h = g[:2] - N[:2, 2:] @ (NT_inv @ g[2:])
    c_ = S[1, 1] * h[0] - S[0, 1] * h[1]
    s_ = S[0, 0] * h[1] - S[0, 1] * h[0]
    th = math.atan2(s_, c_)
    c, sn = math.cos(th), math.sin(th)
    T = NT_inv @ (g[2:] - N[2:, :2] @ (c, sn))
    R_t = np.array([[a1, c * a2 + sn * a3, c * a3 - sn * a2],
                    [b1, c * b2 + sn * b3, c * b3 - sn * b2],
                    [d1, c * d2 + sn * d3, c * d3 - sn * d2]])
    Xt = Pa @ R_t.T + T
    rng = np.sqrt(np.einsum("ij,ij->i", Xt, Xt)) * np.sign(Xt[:, 2])
    return b * rng[:, None]


def candidates(P: np.ndarray, m: np.ndarray) -> list[Candidate]:
    """RPnP poses, one per local minimum of the triplet cost; see the module docstring."""
    n = len(P)
    b = np.empty((n, 3))
    b[:, :2] = m
    b[:, 2] = 1.0
    b /= np.sqrt(np.einsum("ij,ij->i", b, b))[:, None]
    # longest projection: least cosine between two rays, exhaustively
    cosines = b @ b.T
    i1, i2 = divmod(int(np.argmin(cosines)), n)
    # order the pair by the image, not by the input order, so that permuting the points does not
    # change the result (the cost is not symmetric in i1, i2 under noise)
    if (m[i1, 0], m[i1, 1]) > (m[i2, 0], m[i2, 1]):
        i1, i2 = i2, i1
    Pa = _pair_model(P, i1, i2)[4]
    if Pa is None:  # the two points coincide
        return []

    ts = _minima(_cost_derivative(b, P, i1, i2))
    if ts.size == 0:
        return []
    if ts.size == 1:  # the usual case: the same least squares with a third of the numpy calls
        X = _recover_one(float(ts[0]), b, m, Pa, i1, i2)
        return [] if X is None else align_rigid_many(P, X[None])
    # the rotation axis in the camera frame, one per minimum
    c12 = b[i1] @ b[i2]
    axes = (c12 + ts)[:, None] * b[i2] - b[i1]
    norms = np.linalg.norm(axes, axis=1)
    if not norms.all():
        axes, norms = axes[norms != 0], norms[norms != 0]
        if not len(axes):
            return []
    R_x = np.array([_frame_rows(a) for a in (axes / norms[:, None]).tolist()])  # (k, 3, 3)
    k = len(R_x)
    r1, r2, r3 = R_x[:, :, 0], R_x[:, :, 1], R_x[:, :, 2]
    # X_i = r1 Pa_x + c (r2 Pa_y + r3 Pa_z) + s (r3 Pa_y - r2 Pa_z) + T: the three terms
    # (F0, Fc, Fs) for every root at once, F = Pa @ Mk (k, n, 3 terms x 3 coordinates)
    Mk = np.zeros((k, 3, 3, 3))
    Mk[:, 0, 0] = r1
    Mk[:, 1, 1] = r2
    Mk[:, 2, 1] = r3
    Mk[:, 1, 2] = r3
    Mk[:, 2, 2] = -r2
    F = (Pa @ Mk.reshape(k, 3, 9)).reshape(k, n, 3, 3)
    # the collinearity rows (u X3 - X1, v X3 - X2, interleaved per point as before) of each term
    Aterm = (F[..., :2] - F[..., 2:] * m[:, None, :]).transpose(0, 1, 3, 2).reshape(k, 2 * n, 3)
    # the T columns B = [[1, 0, -u], [0, 1, -v]] per point are the same for every root: the
    # least squares in (c, s, T) is the one in (c, s) with range(B) projected out (exactly what
    # lstsq of the 2n x 5 system solves), then T from B's pseudo-inverse
    B = np.zeros((n, 2, 3))
    B[:, 0, 0] = B[:, 1, 1] = 1.0
    B[:, :, 2] = -m
    Ub, sb, Vbt = svd_small(B.reshape(2 * n, 3), full_matrices=False)
    At = Aterm - Ub @ (Ub.T @ Aterm)
    Acs, rhs = At[:, :, 1:], -At[:, :, 0]
    N = Acs.transpose(0, 2, 1) @ Acs  # (k, 2, 2)
    g = (Acs.transpose(0, 2, 1) @ rhs[:, :, None])[..., 0]
    # (c, s) = N^-1 g up to the positive factor det N: only its direction is used
    c_ = N[:, 1, 1] * g[:, 0] - N[:, 0, 1] * g[:, 1]
    s_ = N[:, 0, 0] * g[:, 1] - N[:, 0, 1] * g[:, 0]
    theta = np.arctan2(s_, c_)
    c, s = np.cos(theta)[:, None], np.sin(theta)[:, None]
    R_t = np.empty((k, 3, 3))
    R_t[:, :, 0] = r1
    R_t[:, :, 1] = c * r2 + s * r3
    R_t[:, :, 2] = c * r3 - s * r2
    # T for the exact rotation: the same equations with (c, s) fixed
    Y = Pa @ R_t.transpose(0, 2, 1)  # (k, n, 3)
    rhs2 = -(Y[..., :2] - Y[..., 2:] * m).reshape(k, 2 * n)
    T = ((rhs2 @ Ub) / sb) @ Vbt
    Xt = Y + T[:, None, :]
    X = b * (np.sqrt(np.sum(Xt * Xt, axis=2, keepdims=True)) * np.sign(Xt[..., 2:3]))
    return align_rigid_many(P, X)


solve = make_solver("rpnp", candidates, min_points=4)
