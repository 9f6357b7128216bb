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
   (least squares, 2n x 5, solved through its normal equations: built from model-only moments
   and four image weights per point, ``T`` eliminated once for all minima).
6. **Final alignment**: ``theta = atan2(s, c)`` (``c^2 + s^2 = 1`` imposed), ``T`` refitted
   for that rotation, the camera-frame points moved onto their rays ``X_i = b_i ||Xt_i||`` and
   ``(R, t)`` from the rigid alignment of ``P`` to them (AL-ok,
   :func:`~cutterpose.solvers.pnp.base.align_rigid`).

Every minimum gives a candidate; :func:`~cutterpose.solvers.pnp.base.make_solver` selects by
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
from typing import NamedTuple

import numpy as np
from scipy.linalg.lapack import dgeev as _dgeev

from ..method import CorrespondenceMethod
from .base import (
    Candidate,
    align_rigid_many,
    image_weights,
    kron_normal,
    make_solver,
    model_cache,
)

__all__ = ["RPnP", "candidates", "solve"]

_COMPANION7 = np.zeros((7, 7))
_COMPANION7[np.arange(1, 7), np.arange(6)] = 1.0  # the sub-diagonal of a degree-7 companion
_EYE9 = np.eye(9)
_ONES3 = np.ones(3)


# The quartic of step 3 regrouped: f = p^2 - q r^2 with p = A6 t^2 + A3 t + A7, q = A1 t^2 + A2
# and r = c2i t + A4 (the A's of the notes, section 3 step 4). With the rows
# Z = (A1, A2, c2i, A4, A6, A3, A7, A1 c2i, A1 A4, A2 c2i, A2 A4) = (q, r, p, q r), the
# coefficients (t^4 .. t^0) of f are _QUARTIC @ vec(Z[4:] Z[2:7]^T), the products of
# (p, q r) with (r, p): p p - (q r) r. One broadcast product and one matrix product instead of
# the two dozen array operations of the coefficients written out.
_DEG_LEFT = (2, 1, 0, 3, 2, 1, 0)  # degrees in t of the coefficients in Z[4:]
_DEG_RIGHT = (1, 0, 2, 1, 0)  # and in Z[2:7]
_QUARTIC = np.zeros((5, 7, 5))
for _a, _b in np.ndindex(7, 5):
    if (_a < 3) == (_b >= 2):  # p times p, or q r times r
        _QUARTIC[4 - _DEG_LEFT[_a] - _DEG_RIGHT[_b], _a, _b] = 1.0 if _a < 3 else -1.0
_QUARTIC = _QUARTIC.reshape(5, 35)


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


def _fdf_map() -> np.ndarray:
    """(8, 25): ``G = _fdf_map() @ vec(g g^T)`` for ``G = f f'`` summed over the points, with
    ``f = sum_a g_a t^(4-a)``: the coefficient of ``t^(7-k)`` is ``sum_(a+b=k) (4-b) g_a g_b``."""
    M = np.zeros((8, 5, 5))
    for a in range(5):
        for b in range(4):  # g_4 is constant: no t^-1 term
            M[a + b, a, b] = 4 - b
    return M.reshape(8, 25)


_FDF = _fdf_map()


class _Pair(NamedTuple):
    """What depends on the model and the axis pair only (see :func:`_pair_model`)."""

    cos_idx: np.ndarray  # (2, n - 2) flat indices of b_i1 . b_i, b_i2 . b_i (i not i1, i2)
    basis: np.ndarray  # (7, n - 2) template of the rows 1, c1i, c2i, c1i^2, c1i c2i, A1, A6
    Pa1: np.ndarray | None  # (n, 4) rows a_i = (Pa_i, 1), Pa_i = R_o^T (P_i - p0); None when
    #                         i1, i2 coincide
    O: np.ndarray | None  # (n, 16) vec(a_i a_i^T): the linear step's moments


def _pair_model(P: np.ndarray, i1: int, i2: int) -> _Pair:
    """:class:`_Pair` of a model and an axis pair, cached per model and pair (the holder's
    longest projection comes from a few pairs)."""
    cache = model_cache(P).setdefault("rpnp", {})
    pm = cache.get((i1, i2))
    if pm is None:
        n = len(P)
        rest = np.flatnonzero((np.arange(n) != i1) & (np.arange(n) != i2))
        Pr = P[rest]
        D12_2 = float(np.sum((P[i1] - P[i2]) ** 2))
        D1i_2 = np.sum((Pr - P[i1]) ** 2, axis=1)
        D2i_2 = np.sum((Pr - P[i2]) ** 2, axis=1)
        edge = P[i2] - P[i1]
        Pa1 = O = None
        if np.any(edge):
            p0 = 0.5 * (P[i1] + P[i2])
            R_o = _complete_frame(edge / np.linalg.norm(edge))
            Pa1 = np.column_stack([(P - p0) @ R_o, np.ones(n)])
            O = (Pa1[:, :, None] * Pa1[:, None, :]).reshape(n, 16)
        # the distance terms of the quartics (A1, A6 of the notes) are model-only too
        A1 = D1i_2 / D12_2
        A6 = (D2i_2 - D12_2 - D1i_2) / (2.0 * D12_2)
        basis = np.zeros((7, n - 2))
        basis[0], basis[5], basis[6] = 1.0, A1, A6
        pm = cache[(i1, i2)] = _Pair(np.array([i1 * n + rest, i2 * n + rest]), basis, Pa1, O)
        for a in pm:  # shared by every solve with this model: read-only
            if a is not None:
                a.flags.writeable = False
    return pm


def _cost_derivative(cosines: np.ndarray, pair: _Pair, i1: int, i2: int) -> np.ndarray:
    """Coefficients (t^7 .. t^0) of ``G(t) = sum_i f_i(t) f_i'(t)`` (paper eq. 8), from the
    cosines ``b_i . b_j`` of the bearings."""
    c12 = float(cosines[i1, i2])
    s12_2 = 1.0 - c12 * c12
    B = pair.basis.copy()
    B[1:3] = cosines.take(pair.cos_idx)  # c1i, c2i
    np.multiply(B[1:3], B[1], out=B[3:5])  # c1i^2, c1i c2i
    # the rows q, r, p of Z (see _QUARTIC) are linear in the basis rows (the columns of C: 1,
    # c1i, c2i, c1i^2, c1i c2i, A1, A6), with coefficients from c12: A2 = A1 s12^2 - 1 + c1i^2,
    # A4 = c12 c2i - c1i, A3 = c1i c2i - c12, A7 = (1 + A6) s12^2 - c1i^2 + c12 c1i c2i
    C = np.array([0.0, 0.0, 0.0, 0.0, 0.0, 1.0, 0.0,  # A1
                  -1.0, 0.0, 0.0, 1.0, 0.0, s12_2, 0.0,  # A2
                  0.0, 0.0, 1.0, 0.0, 0.0, 0.0, 0.0,  # c2i
                  0.0, -1.0, c12, 0.0, 0.0, 0.0, 0.0,  # A4
                  0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 1.0,  # A6
                  -c12, 0.0, 0.0, 0.0, 1.0, 0.0, 0.0,  # A3
                  s12_2, 0.0, 0.0, -1.0, c12, 0.0, s12_2]).reshape(7, 7)  # A7
    k = B.shape[1]
    Z = np.empty((11, k))
    np.matmul(C, B, out=Z[:7])
    np.multiply(Z[:2, None], Z[2:4], out=Z[7:].reshape(2, 2, k))  # q r
    g = _QUARTIC @ (Z[4:, None] * Z[2:7]).reshape(35, k)
    # sum_i f_i f_i' from the 5x5 Gram matrix of the quartics' coefficients
    return _FDF @ (g @ g.T).ravel()


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


def _minima(G: np.ndarray) -> list[float]:
    """Real roots of G with G' > 0 (local minima of F), in the order LAPACK returns them.

    The seven roots and their filter are few enough for Python floats (cheaper than numpy calls
    at this size). The tests are those of the array formulation, ``t = wr[|wi| <= 1e-3
    max|wr|]`` and ``polyval(polyder(G), t) > 0`` (here by Horner), which still handles
    non-finite roots, where numpy's NaN/inf rules decide."""
    g = G.tolist()
    if not all(map(math.isfinite, g)):
        return []
    gmax = max(map(abs, g))
    if gmax == 0.0:
        return []
    g = [v / gmax for v in g]
    if g[0] != 0.0 and g[-1] != 0.0:
        # np.roots without its overhead: eigenvalues of the companion matrix by dgeev (the
        # routine behind np.linalg.eigvals), kept as real and imaginary parts
        A = _COMPANION7.copy()
        A[0] = [-v / g[0] for v in g[1:]]
        wr, wi, _, _, info = _dgeev(A, compute_vl=0, compute_vr=0)
        if info != 0:
            r = np.linalg.eigvals(A)
            wr, wi = r.real, r.imag
    else:
        roots = _roots(np.array(g))
        if roots.size == 0:
            return []
        wr, wi = roots.real, roots.imag
    wr_l = wr.tolist()
    if not all(map(math.isfinite, wr_l)):  # only from an overflowing companion row
        t = wr[np.abs(wi) <= 1e-3 * np.abs(wr).max()]
        dG = (t[:, None] ** np.arange(6.0, -1.0, -1.0)) @ (np.array(g[:-1]) * np.arange(7, 0, -1))
        return t[dG > 0].tolist()
    tol = 1e-3 * max(map(abs, wr_l))
    dg = [(7 - k) * gk for k, gk in enumerate(g[:-1])]  # G' (t^6 .. t^0)
    out = []
    for t, ti in zip(wr_l, wi.tolist()):
        if abs(ti) <= tol:
            d = 0.0
            for c in dg:  # Horner
                d = d * t + c
            if d > 0:
                out.append(t)
    return out


def _eliminate_translation(O: np.ndarray, E: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The collinearity equations of step 5 with ``T`` eliminated, the same for every root.

    Written for any 3x3 ``M`` in place of ``R_x Rot_x(theta)``, the camera-frame points are
    ``X_i = M Pa_i + T`` and the rows ``u X3 - X1``, ``v X3 - X2`` of point i are
    ``kron(a_i, B_i) (vec M, T)`` with ``a_i = (Pa_i, 1)`` and ``B_i = [[-1, 0, u], [0, -1,
    v]]``: their 12x12 normal matrix comes from the model's moments ``O`` with the image weights
    ``E`` (:func:`~cutterpose.solvers.pnp.base.kron_normal`) instead of from the 2n rows.

    Returns
    -------
    Nm : (9, 9) normal matrix in ``vec M`` (columns stacked) once ``T`` is eliminated (the Schur
        complement of the ``T`` block).
    L : (12, 9) ``(vec M, T) = L vec M``, with ``T`` the least-squares translation for ``M``.
    """
    N = kron_normal(O, None, coord_outer=False, E=E)  # B_i^T B_i is the same for -B_i
    # minus the inverse of the T block (symmetric positive definite, 3x3) by cofactors:
    # np.linalg.inv's per-call overhead is most of its cost at this size
    (a, b, c), (_, d, e), (_, _, f) = N[9:, 9:].tolist()
    c00, c01, c02 = d * f - e * e, c * e - b * f, b * e - c * d
    c11, c12, c22 = a * f - c * c, b * c - a * e, a * d - b * b
    det = -(a * c00 + b * c01 + c * c02)
    L = np.empty((12, 9))
    L[:9] = _EYE9
    np.matmul(np.array([[c00 / det, c01 / det, c02 / det], [c01 / det, c11 / det, c12 / det],
                        [c02 / det, c12 / det, c22 / det]]), N[9:, :9], out=L[9:])
    return N[:9] @ L, L  # N_mm + N_mt K, N being symmetric


def _recover_one(t: float, c12: float, bi1: list[float], bi2: list[float], b: np.ndarray,
                 Pa1: np.ndarray, Nm: np.ndarray, L: np.ndarray) -> np.ndarray | None:
    """Camera-frame points for one root ``t`` (steps 5 and 6): ``X_i = R_x Rot_x(theta) Pa_i +
    T`` with ``(cos, sin, T)`` from the linear least squares of ``u X3 - X1 = 0``, ``v X3 - X2 =
    0``, ``theta`` from the direction of ``(cos, sin)``, ``T`` re-solved for that exact
    rotation, then each point moved onto its ray keeping its range. ``bi1``, ``bi2`` are the
    bearings of ``i1``, ``i2``, ``Pa1`` the rows ``(Pa_i, 1)``; ``Nm``, ``L`` from
    :func:`_eliminate_translation`. Returns (n, 3), or None for a degenerate axis."""
    ax = [(c12 + t) * y - x for x, y in zip(bi1, bi2)]
    nrm = math.sqrt(ax[0] * ax[0] + ax[1] * ax[1] + ax[2] * ax[2])
    if nrm == 0.0:
        return None
    (a1, a2, a3), (b1, b2, b3), (d1, d2, d3) = _frame_rows([ax[0] / nrm, ax[1] / nrm,
                                                             ax[2] / nrm])
    # columns r1 = (a1, b1, d1), r2 = (a2, b2, d2), r3 = (a3, b3, d3) of R_x: M = R_x Rot_x
    # has columns (r1, c r2 + s r3, c r3 - s r2), so vec M = W (1, c, s)
    W = np.array([a1, 0.0, 0.0, b1, 0.0, 0.0, d1, 0.0, 0.0,
                  0.0, a2, a3, 0.0, b2, b3, 0.0, d2, d3,
                  0.0, a3, -a2, 0.0, b3, -b2, 0.0, d3, -d2]).reshape(9, 3)
    # the cost in (1, c, s) with T eliminated; (c, s) = S^-1 h with S = N[1:, 1:], h = -N[1:, 0],
    # up to the positive factor det S: only its direction is used
    (_, n01, n02), (_, n11, n12), (_, _, n22) = (W.T @ Nm @ W).tolist()
    c_ = n12 * n02 - n22 * n01
    s_ = n12 * n01 - n11 * n02
    th = math.atan2(s_, c_)
    c, sn = math.cos(th), math.sin(th)
    # T for that exact rotation: (R_t^T; T^T) = L vec R_t, and vec R_t lists the columns of R_t
    RT = L @ np.array([a1, b1, d1, c * a2 + sn * a3, c * b2 + sn * b3, c * d2 + sn * d3,
                       c * a3 - sn * a2, c * b3 - sn * b2, c * d3 - sn * d2])
    Xt = Pa1 @ RT.reshape(4, 3)
    rng = np.sqrt((Xt * Xt) @ _ONES3) * np.sign(Xt[:, 2])
    return b * rng[:, None]


def candidates(P: np.ndarray, m: np.ndarray) -> list[Candidate]:
    """RPnP poses, one per local minimum of the triplet cost; see the module docstring."""
    n = len(P)
    E = image_weights(m)  # (1, u, v, u^2 + v^2): for the linear step, and the bearings' norms
    b = np.empty((n, 3))
    b[:, :2] = m
    b[:, 2] = 1.0
    b /= np.sqrt(E[:, 3] + 1.0)[:, None]
    # longest projection: least cosine between two rays, exhaustively
    cosines = b @ b.T
    i1, i2 = divmod(int(cosines.argmin()), n)
    # order the pair by the image, not by the input order, so that permuting the points does not
    # change the result (the cost is not symmetric in i1, i2 under noise)
    if (m[i1, 0], m[i1, 1]) > (m[i2, 0], m[i2, 1]):
        i1, i2 = i2, i1
    pair = _pair_model(P, i1, i2)
    if pair.Pa1 is None:  # the two points coincide
        return []

    ts = _minima(_cost_derivative(cosines, pair, i1, i2))
    if not ts:
        return []
    Nm, L = _eliminate_translation(pair.O, E)
    c12 = float(cosines[i1, i2])
    bi1, bi2 = b[i1].tolist(), b[i2].tolist()
    Xs = [X for X in (_recover_one(t, c12, bi1, bi2, b, pair.Pa1, Nm, L) for t in ts)
          if X is not None]
    if not Xs:
        return []
    return align_rigid_many(P, Xs[0][None] if len(Xs) == 1 else np.array(Xs))


solve = make_solver("rpnp", candidates, min_points=4)


class RPnP(CorrespondenceMethod):
    name = "rpnp"
    description = "RPnP (Li et al. 2012)"
    solve = staticmethod(solve)
