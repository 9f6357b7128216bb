"""EPnP (Lepetit, Moreno-Noguer & Fua, IJCV 2009) with data-adapted control points and the
Gauss-Newton refinement of the betas, planar case included.

Every object point is a weighted sum of ``k + 1`` control points, ``P_i = sum_j alpha_ij C_j``
with ``sum_j alpha_ij = 1`` (paper eq. 1). The control points are the centroid and the centroid
plus each principal direction ``v_j`` scaled by the RMS spread ``sigma_j`` of the points along it
(paper section 3.1): ``k = 3`` for a general set, ``k = 2`` (three control points in the plane)
for a planar one (paper section 3.4), so ``alpha_ij = (P_i - Pbar) . v_j / sigma_j`` and
``alpha_i0 = 1 - sum_j alpha_ij``. Since the projection is linear in the camera-frame control
points ``c_j``, each point gives two rows of ``M x = 0`` (paper eq. 7)::

    sum_j alpha_ij (c_j1 - u_i c_j3) = 0,      sum_j alpha_ij (c_j2 - v_i c_j3) = 0

and ``x = sum_{k=1..N} beta_k w_k`` over the eigenvectors ``w_k`` of ``M^T M`` with the ``N``
least eigenvalues (eq. 8). The betas follow from the known squared distances between control
points, ``||c_a - c_b||^2 = ||C_a - C_b||^2`` (eq. 10), linear in the products
``beta_k beta_l`` (eq. 13):

* ``N = 1``: least squares for ``beta_1^2``;
* ``N = 2`` and (general) ``N = 3``: least squares for the products (3 <= 3 resp. 6 <= 6
  equations), ``beta`` is the leading eigenvector of the symmetric product matrix scaled by the
  square root of its eigenvalue;
* general ``N = 4`` (10 products, 6 equations): relinearisation (paper section 3.3): with the
  4-dimensional... null space ``Z`` of ``[L | -rho]`` the products are ``Z lambda`` (last entry 1);
  the 2x2 minors of the product matrix vanish (rank one), which is linear in the products
  ``lambda_a lambda_b``; their least-squares null vector gives ``lambda``;
* planar ``N = 3`` (6 products, 3 equations): the same construction is exactly determined (4
  solutions in ``lambda``: 6 minors, 10 products); the solutions are the eigenvectors of a 4x4
  multiplication matrix built from the null space of the linearised minors (notes 6.4).

``N = 1`` and ``N = 2`` are always built; the ``N >= 3`` hypotheses only when the better of
them has a mean reprojection error (``E_mean``) above 5 px, the reference's gate (below).
Each hypothesis is scaled to the object's distances (least squares on the distances from the
centroid, paper eq. 15 context). As in the paper (section 3.5) and the reference, only the
hypothesis of least reprojection error is refined, by Gauss-Newton on all ``k`` betas over the
distance residuals ``r_ab = ||C_a - C_b||^2 - ||c_a - c_b||^2`` (for the planar case notes 2.3:
3 residuals in 3 betas, a square Jacobian, so the step is Newton's ``J^-1 r``, on Python
floats). The sign of ``beta`` is fixed by the orientation of the control points for a general
set (``det [c_1 - c_0, c_2 - c_0, c_3 - c_0]`` has the sign of the world's, which keeps a
mirrored structure out) and by positive mean depth for a planar set.
The pose is the rigid alignment (:func:`~cutterpose.solvers.pnp.base.align_rigid`, AL-ok) of ``P``
to the
camera-frame points ``X_i = sum_j alpha_ij c_j``, whose centroid and cross-covariance with ``P``
are linear in the control points (model-only factors), so X itself is never formed.

Convention:
    ``P`` (n, 3) object points in mm, ``m`` (n, 2) normalised image coordinates; control points
    and betas are in mm (the alphas are unit-free, so the linear system is well conditioned
    whatever the units).

Deviations from the reference code (notes sections 2 and 8):
    * Data-adapted control points, as in the IJCV paper, instead of fixed unit points (those
      depend on the units and condition the system badly in mm).
    * Planarity detected, any plane; the planar case uses 3 control points in the plane.
    * The ``N >= 3`` gate in pixels: the reference builds ``N = 3`` (planar; ``3, 4`` general)
      only when ``min(eps_1, eps_2) > 5/800`` (planar; ``> 20`` general, i.e. never) with eps
      in normalised units, which is 5 px only for its f = 800 px camera (notes 2.1: ~15 px for
      ours). Here the gate is ``E_mean > 5 px`` for the camera's own focal length
      (:func:`solve` passes ``camera.focal_px`` to :func:`candidates`; called directly without
      ``f_px``, the nominal 2464 px of the project cameras), the same for planar and general sets.
      On the holder it runs at 5 px noise (81 % of trials), practically never at 1 to 3 px.
    * Hypotheses are scored by ``E_mean`` of the camera-frame points ``X_i = sum_j alpha_ij c_j``
      themselves (the reference scores the aligned pose): no alignment per hypothesis.
    * Gauss-Newton on the planar betas too (notes 2.3), up to 8 iterations (fewer once the step
      is at rounding level, or, for the planar Newton, once it converges quadratically with a
      step of 1e-8 relative, the next one being at rounding level). A best hypothesis whose GN
      has not converged (last step above 1e-7 relative) is returned unrefined (the reference
      keeps the refined result only when its ``E_mean`` is smaller). On the holder, refining
      only the best gives the same poses as the earlier refine-every-hypothesis code in all 4000
      trials of a 0.5 to 5 px sweep (to 1e-9 deg, the CSV's precision).
    * A second candidate, for the ambiguity ratio of :func:`~cutterpose.solvers.pnp.base.select`,
    only
      when it is a *different solution* of the distance equations: the next hypothesis by
      ``E_mean`` that does not start within 1 % of the refined best (``beta`` up to its sign),
      refined as well, and kept if it converged elsewhere. An unrefined neighbour of the best
      would differ from it by a few hundredths of a degree and report a false ambiguity (ratio
      near 1). At 1 to 3 px on the holder a second solution is found in about 1 % of trials, at
      5 px (where the ``N = 3`` roots are built) in about half, with ratios mostly below 0.3.
    * Alignment AL-ok, never ``R -> -R`` (AL-E is wrong on planar points).
    * Sign by orientation (general) / depth (planar), not "negate all if any depth < 0".
    * ``N = 2`` takes the nearest rank-one product matrix (leading eigenvector) rather than
      ``sqrt|b11|``, ``sqrt|b22| sign(b12)``.
"""

from __future__ import annotations

import math
from functools import cache, lru_cache, partial
from typing import NamedTuple

import numpy as np
from scipy.linalg.lapack import dgeev as _dgeev
from scipy.linalg.lapack import dgesv as _dgesv

from ...errors import DegenerateInputError
from ..method import CorrespondenceMethod
from .base import (
    Candidate,
    det3,
    is_planar,
    kron_normal,
    make_solver,
    model_cache,
    rotation_from_covariance,
    smallest_eigvecs,
    svd_small,
)

__all__ = ["EPnP", "candidates", "solve"]

_GN_ITERATIONS = 8
_GN_AT_REST = 1e-14  # relative step below which Gauss-Newton has nothing left to do
_SAME_BETA = 1e-6  # relative: GN from two hypotheses reached the same solution
# a hypothesis within 1 % of the refined best converges onto it (measured on the holder, 1 to
# 10 px: 97 to 69 % of such starts lie within 1 %, fewer than 0.05 % of those reaching another
# solution do); it is not refined a second time
_SAME_START = 1e-2
# the N >= 3 gate of the reference, min(eps_1, eps_2) > 5/800 in normalised units, i.e. 5 px
# for its f = 800 px camera; here 5 px for the actual focal length (``candidates(f_px=...)``),
# else for the nominal one of the project cameras (synthetic 2464 px, table1 2475 px)
_GATE_PX = 5.0
_NOMINAL_F_PX = 2464.0
# fixed generic coefficients of the linear forms in the multiplication matrix (notes 6.4)
_G = np.array([1.0, 0.37, -0.61, 0.23])
_H = np.array([0.29, -0.83, 0.47, 1.0])


def _control_points(P: np.ndarray, planar: bool):
    """Alphas (n, k+1), world control points in the principal frame (k+1, k), ``k`` and the
    handedness (+-1) of the principal frame."""
    n = len(P)
    Pc = P - P.mean(axis=0)
    _, s, Vt = np.linalg.svd(Pc, full_matrices=False)
    # the sign of a principal direction is arbitrary but moves the control point to the other
    # side; fix it by the world frame (largest component positive) so that the result does not
    # depend on the order of the points
    Vt = Vt * np.sign(Vt[np.arange(3), np.argmax(np.abs(Vt), axis=1)])[:, None]
    k = 2 if planar else 3
    sig = s[:k] / np.sqrt(n)
    a = (Pc @ Vt[:k].T) / sig
    alphas = np.empty((n, k + 1))
    alphas[:, 0] = 1.0 - a.sum(axis=1)
    alphas[:, 1:] = a
    C = np.vstack([np.zeros(k), np.diag(sig)])
    return alphas, C, k, float(np.sign(np.linalg.det(Vt)))


@cache
def _normal_gather(kp: int) -> tuple[np.ndarray, np.ndarray]:
    """Flat index into ``F = E^T O`` (4, kp^2) and sign of every entry (3 kp, 3 kp) of
    ``kron_normal(O, m, coord_outer=False)``, whose entries are each one entry of F times the
    +-1 of one coefficient matrix of ``B_i^T B_i``, or zero (see :func:`_normal_matrix`)."""
    # the coefficient matrices: kron_normal of a 1x1 model with unit image weights
    B = np.array([kron_normal(np.ones((1, 1)), None, coord_outer=False, E=e[None])
                  for e in np.eye(4)])  # (4, 3, 3), at most one nonzero per (a, b)
    coef, sab = np.argmax(B != 0, axis=0), B.sum(axis=0)  # which one, and its +-1 (or 0)
    i, a, j, b = np.indices((kp, 3, kp, 3))
    # zero entries: index 0, F[0, 0] = sum_i alpha_i0^2 >= 0, so 0 * F[0, 0] is +0 as in
    # kron_normal
    idx = np.where(sab[a, b] != 0, coef[a, b] * kp * kp + i * kp + j, 0)
    return idx.reshape(3 * kp, 3 * kp), sab[a, b].reshape(3 * kp, 3 * kp)


_SUM2 = np.ones((2, 1))
_ONES3 = np.ones(3)


def _normal_matrix(O: np.ndarray, ones: np.ndarray, m: np.ndarray, kp: int) -> np.ndarray:
    """``M^T M`` of EPnP's system (paper eq. 7), bit for bit
    ``kron_normal(O, m, coord_outer=False)``, in fewer numpy calls.

    ``M^T M = sum_i kron(alpha_i alpha_i^T, B_i^T B_i)`` with ``B_i^T B_i`` linear in the image
    weights ``E_i = (1, u_i, v_i, u_i^2 + v_i^2)``; each entry is one entry of ``F = E^T O``
    (``O`` the cached ``alpha_i alpha_i^T``) times 1, -1 or 0, so it is gathered from F rather
    than mapped by a matrix product and two reshapes. ``ones`` is a cached (n, 1) column; the
    sum ``u^2 + v^2`` as a product with ``(1, 1)`` rounds as the plain sum (exact factors).
    ``kp = k + 1`` control points."""
    E = np.concatenate((ones, m, (m * m) @ _SUM2), axis=1)
    idx, sgn = _normal_gather(kp)
    return (E.T @ O).take(idx) * sgn


def _kernel(O: np.ndarray, ones: np.ndarray, m: np.ndarray, kp: int) -> np.ndarray:
    """The ``N = kp`` eigenvectors of ``M^T M`` (:func:`_normal_matrix`) with the least
    eigenvalues, as the columns of a (3 kp, N) array: column k holds the control points of
    ``w_k``, ``(kp, 3)`` flattened."""
    return smallest_eigvecs(_normal_matrix(O, ones, m, kp), kp)


def _beta_from_products(Bmat: np.ndarray) -> np.ndarray:
    """``beta`` with ``beta beta^T`` nearest the symmetric product matrix (sign arbitrary)."""
    w, V = np.linalg.eigh(Bmat)
    return V[:, -1] * np.sqrt(max(w[-1], 0.0))


def _betas_from_products(Bmats: np.ndarray) -> np.ndarray:
    """:func:`_beta_from_products` of a stack (h, N, N) in one call."""
    w, V = np.linalg.eigh(Bmats)
    return V[:, :, -1] * np.sqrt(np.maximum(w[:, -1], 0.0))[:, None]


@cache
def _tri(N: int):
    """Upper-triangle indices of an N x N symmetric matrix, the position of every (i, j) in the
    packed vector of products (i <= j), and the weights 1 (diagonal) / 2 (off-diagonal)."""
    iu = np.triu_indices(N)
    pos = np.zeros((N, N), dtype=int)
    pos[iu] = np.arange(len(iu[0]))
    pos = np.maximum(pos, pos.T)
    return iu, pos, np.where(iu[0] == iu[1], 1.0, 2.0)


def _sym_from_upper(b: np.ndarray, N: int) -> np.ndarray:
    return b[_tri(N)[1]]


@cache
def _minor_index(N: int):
    """Packed positions ``(ik, jl, il, jk)`` of the 2x2 minors ``B_ik B_jl - B_il B_jk`` of a
    symmetric N x N matrix, one per unordered pair of index pairs."""
    pos = _tri(N)[1]
    pairs = [(i, j) for i in range(N) for j in range(i + 1, N)]
    rows = [(pos[i, k], pos[j, l], pos[i, l], pos[j, k])
            for a, (i, j) in enumerate(pairs) for k, l in pairs[a:]]
    return tuple(np.array(c) for c in zip(*rows, strict=True))


@cache
def _minor_maps(N: int, p: int, r: int):
    """Constant matrices with ``_minor_rows(Z) = Sel @ kron-rows(Z, Z) @ Sym``: Sel picks
    ``+Z_ik Z_jl^T - Z_il Z_jk^T`` out of all row pairs, Sym sums ``Q_ab + Q_ba`` into the packed
    position of ``(a, b)`` (so each minor costs two matrix products, not a dozen gathers)."""
    ik, jl, il, jk = _minor_index(N)
    Sel = np.zeros((len(ik), p * p))
    rows = np.arange(len(ik))
    np.add.at(Sel, (rows, ik * p + jl), 1.0)
    np.add.at(Sel, (rows, il * p + jk), -1.0)
    pos = _tri(r)[1]
    Sym = np.zeros((r * r, len(_tri(r)[0][0])))
    Sym[np.arange(r * r), pos.ravel()] = 1.0
    return Sel, Sym


def _minor_rows(Z: np.ndarray, N: int) -> np.ndarray:
    """Rows of the linearised rank-one conditions on ``B(lambda) = sym(Z lambda)``.

    Every 2x2 minor ``B_ik B_jl - B_il B_jk`` is a quadratic form ``lambda^T Q lambda``; the
    result holds its coefficients on the packed products ``lambda_a lambda_b`` (a <= b):
    ``Q_ab + Q_ba`` (a < b), ``Q_aa`` (a = b).
    """
    p, r = Z.shape
    Sel, Sym = _minor_maps(N, p, r)
    ZZ = (Z[:, None, :, None] * Z[None, :, None, :]).reshape(p * p, r * r)
    return Sel @ ZZ @ Sym


@cache
def _forms(r: int) -> np.ndarray:
    """(2r, r(r+1)/2): ``[Ng; Nh] = _forms(r) @ Nl``, i.e. ``Ng_kc = sum_j G_j Nl[pos_jk, c]``
    (and H), as one matrix product."""
    pos = _tri(r)[1]
    F = np.zeros((2 * r, len(_tri(r)[0][0])))
    for j in range(r):
        for k in range(r):
            F[k, pos[j, k]] += _G[j]
            F[r + k, pos[j, k]] += _H[j]
    return F


def _eig_real(M: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Real and imaginary parts of the eigenvalues and the real parts of the right eigenvectors
    of a real square matrix, as ``w, E = np.linalg.eig(M)`` gives them, through LAPACK dgeev
    directly (numpy's routine without its overhead): a complex pair's vectors share the real
    part ``vr[:, j]``."""
    wr, wi, _, vr, info = _dgeev(M, compute_vl=0)
    if info != 0:
        w, E = np.linalg.eig(M)
        return w.real, w.imag, E.real
    second = np.flatnonzero(wi < 0)  # second of a conjugate pair: real part in column j - 1
    if second.size:
        vr = vr.copy()
        vr[:, second] = vr[:, second - 1]
    return wr, wi, vr


def _relinearise(L: np.ndarray, rho: np.ndarray, N: int) -> list[np.ndarray]:
    """Betas from more products than distance equations (paper section 3.3; notes 6.4)."""
    p = L.shape[1]
    A = np.column_stack([L, -rho])
    Vt = svd_small(A)[2]
    Z = Vt[L.shape[0]:].T  # (p + 1, r): the products and the homogenising 1
    r = Z.shape[1]
    C = _minor_rows(Z[:p], N)
    _, s, Wt = svd_small(C)
    n_null = C.shape[1] - np.count_nonzero(s > 1e-10 * s[0])
    if C.shape[0] >= C.shape[1] or n_null <= 1:
        # overdetermined: the least-squares rank-one product matrix
        lam = _beta_from_products(_sym_from_upper(Wt[-1], r))[None]
    else:
        # exactly determined: r solutions; multiplication matrix on the null space
        Nl = Wt[C.shape[1] - r:].T  # (r(r+1)/2, r)
        NgNh = _forms(r) @ Nl
        Ng, Nh = NgNh[:r], NgNh[r:]
        _, _, Mm, info = _dgesv(Ng, Nh)  # np.linalg.solve(Ng, Nh), without its overhead
        if info != 0:
            Mm = np.linalg.solve(Ng, Nh)
        wr, wi, E = _eig_real(Mm)
        real = np.abs(wi) <= 1e-6 * (1.0 + np.abs(wr))
        lam = (Ng @ E[:, real]).T  # (s, r)
        if not len(lam):
            return []
    h = lam @ Z[p]
    keep = np.abs(h) >= 1e-12 * np.sqrt(np.sum(lam * lam, axis=1))
    if not keep.all():
        if not keep.any():
            return []
        lam, h = lam[keep], h[keep]
    prods = (lam / h[:, None]) @ Z[:p].T  # (s, p)
    return list(_betas_from_products(prods[:, _tri(N)[1]]))


def _hypotheses(dots: np.ndarray, rho: np.ndarray, n_max: int, start: int = 1
                ) -> list[list[float]]:
    """Initial betas (padded to ``n_max``) for ``N = start..n_max``; ``dots`` (pairs, n_max,
    n_max) holds ``Delta_k . Delta_l`` per control-point pair."""
    out = []
    for N in range(start, n_max + 1):
        iu, _, w = _tri(N)
        L = dots[:, iu[0], iu[1]] * w
        if N == 1:
            # the 1x1 case of the branch below, on floats (eigh of [b] is 1 * b)
            ll, lr = (L[:, 0] @ L[:, 0]).item(), (L[:, 0] @ rho).item()
            if ll == 0.0:  # what np.linalg.solve raises on a singular system
                raise np.linalg.LinAlgError("Singular matrix")
            betas = [[math.sqrt(max(lr / ll, 0.0))]]
        elif L.shape[1] <= L.shape[0]:
            b = np.linalg.solve(L.T @ L, L.T @ rho)
            betas = [_beta_from_products(_sym_from_upper(b, N))]
        else:
            betas = _relinearise(L, rho, N)
        for beta in betas:
            full = [0.0] * n_max
            full[:N] = list(beta)
            out.append(full)
    return out


def _gauss_newton(beta: np.ndarray, dots: np.ndarray, rho: np.ndarray):
    """Gauss-Newton on the distance residuals, all hypotheses at once: beta (H, N); returns the
    refined betas and which of them converged.

    With ``G_p = [Delta_k . Delta_l]`` of pair p, ``||c_a - c_b||^2 = beta^T G_p beta``, so the
    residual is ``rho_p - beta^T G_p beta`` and its gradient ``2 G_p beta``.
    """
    H, N = beta.shape
    D2 = dots.reshape(-1, N).T  # (N, pairs * N): Gb = beta @ D2, as matrix products (cheaper
    eye = 1e-12 * np.eye(N)     # than einsum at these sizes)
    for it in range(_GN_ITERATIONS):
        Gb = (beta @ D2).reshape(H, -1, N)
        r = rho - np.einsum("hpk,hk->hp", Gb, beta)
        # [J^T J | J^T r] / 4 in one product
        Mg = Gb.transpose(0, 2, 1) @ np.concatenate([Gb, r[:, :, None]], axis=2)
        JtJ = Mg[..., :N]
        scale = np.einsum("hpk,hpk->h", Gb, Gb)[:, None, None]  # trace of JtJ
        # J = 2 Gb: the step (J^T J)^-1 J^T r = (Gb^T Gb)^-1 Gb^T r / 2
        step = np.linalg.solve(JtJ + eye * scale, Mg[..., N:])
        beta = beta + 0.5 * step[..., 0]
        # every hypothesis at its fixed point to rounding (the remaining iterations would move
        # beta by ~1e-16 relative): stop; usually after 4 or 5 of the 8 iterations
        if it >= 3:
            s2 = np.sum(step * step, axis=(1, 2))
            if (s2 <= _GN_AT_REST**2 * np.sum(beta * beta, axis=1)).all():
                break
    # converged: the last step is negligible (a hypothesis still on its way would be scored at an
    # arbitrary point of its path, and the choice between hypotheses would depend on that)
    converged = np.linalg.norm(step[..., 0], axis=1) < 1e-7 * np.linalg.norm(beta, axis=1)
    return beta, converged


def _two_by_two_beta(b11: float, b12: float, b22: float) -> list[float]:
    """:func:`_beta_from_products` of ``[[b11, b12], [b12, b22]]`` in closed form (floats): the
    leading eigenvector scaled by the square root of its eigenvalue (sign arbitrary)."""
    h = 0.5 * (b11 - b22)
    root = math.hypot(h, b12)
    lam = 0.5 * (b11 + b22) + root
    if lam <= 0.0:
        return [0.0, 0.0]
    # of the two eigenvector forms (b12, lam - b11) and (lam - b22, b12) take the longer one
    # (the other vanishes when b12 -> 0)
    x1, y1 = b12, lam - b11
    x2, y2 = lam - b22, b12
    if x1 * x1 + y1 * y1 < x2 * x2 + y2 * y2:
        x1, y1 = x2, y2
    nrm = math.hypot(x1, y1)
    if nrm == 0.0:  # b11 = b22, b12 = 0: a double eigenvalue, any unit vector
        x1, y1, nrm = 1.0, 0.0, 1.0
    s = math.sqrt(lam) / nrm
    return [x1 * s, y1 * s]


def _solve3(A: list, b: list) -> list[float]:
    """``A^-1 b`` for a 3x3 system on Python floats (adjugate); raises ``LinAlgError`` on an
    exactly singular matrix, as ``np.linalg.solve`` does."""
    (a00, a01, a02), (a10, a11, a12), (a20, a21, a22) = A
    c00, c10, c20 = a11 * a22 - a12 * a21, a12 * a20 - a10 * a22, a10 * a21 - a11 * a20
    det = a00 * c00 + a01 * c10 + a02 * c20
    if det == 0.0:
        raise np.linalg.LinAlgError("Singular matrix")
    b0, b1, b2 = b
    k = 1.0 / det
    return [(c00 * b0 + (a02 * a21 - a01 * a22) * b1 + (a01 * a12 - a02 * a11) * b2) * k,
            (c10 * b0 + (a00 * a22 - a02 * a20) * b1 + (a02 * a10 - a00 * a12) * b2) * k,
            (c20 * b0 + (a01 * a20 - a00 * a21) * b1 + (a00 * a11 - a01 * a10) * b2) * k]


def _hypotheses_low(dl: list, rho: list, n_max: int) -> list[list[float]]:
    """Betas (padded to ``n_max``) of ``N = 1`` and ``N = 2`` on Python floats; ``dl[p][k][l]``
    is ``Delta_k . Delta_l`` of control-point pair p."""
    # N = 2: least squares (normal equations) for (b11, b12, b22), then the nearest rank one
    s00 = s01 = s02 = s11 = s12 = s22 = y0 = y1 = y2 = 0.0
    for d, r in zip(dl, rho, strict=True):
        x0, x1, x2 = d[0][0], 2.0 * d[0][1], d[1][1]
        s00 += x0 * x0
        s01 += x0 * x1
        s02 += x0 * x2
        s11 += x1 * x1
        s12 += x1 * x2
        s22 += x2 * x2
        y0 += x0 * r
        y1 += x1 * r
        y2 += x2 * r
    if s00 == 0.0:  # what np.linalg.solve raises on a singular system
        raise np.linalg.LinAlgError("Singular matrix")
    # N = 1: least squares for beta_1^2, the first row and column of the same system
    h1 = [math.sqrt(max(y0 / s00, 0.0))]
    h2 = _two_by_two_beta(*_solve3([[s00, s01, s02], [s01, s11, s12], [s02, s12, s22]],
                                   [y0, y1, y2]))
    pad = [0.0] * n_max
    return [(h1 + pad)[:n_max], (h2 + pad)[:n_max]]


def _newton_planar(beta: list, G: list, rho: list):
    """Gauss-Newton on the 3 planar distance residuals in the 3 betas (notes 2.3) on Python
    floats. ``G[p]`` is ``(g00, g01, g02, g11, g12, g22)`` of the symmetric ``Delta_k . Delta_l``
    of pair p, so ``||c_a - c_b||^2 = beta^T G_p beta``, the residual ``rho_p - beta^T G_p beta``
    and its gradient ``2 G_p beta``. J is square, so the Gauss-Newton step ``(J^T J)^-1 J^T r``
    is the Newton step ``J^-1 r`` (adjugate form). Stops at rounding level, or one step earlier
    once the convergence is visibly quadratic (the step that is saved would move beta by ~1e-16
    relative). Returns the betas and whether they converged (last step below 1e-7 relative)."""
    b0, b1, b2 = beta
    nb2 = b0 * b0 + b1 * b1 + b2 * b2
    # the three pairs unrolled (rows of J: (a, b, c), (d, e, f), (g, h, i)), no lists per step
    (p00, p01, p02, p11, p12, p22), (q00, q01, q02, q11, q12, q22), \
        (s00, s01, s02, s11, s12, s22) = G
    rho0, rho1, rho2 = rho
    s2 = math.inf
    for it in range(_GN_ITERATIONS):
        a, b, c = p00 * b0 + p01 * b1 + p02 * b2, p01 * b0 + p11 * b1 + p12 * b2, \
            p02 * b0 + p12 * b1 + p22 * b2
        d, e, f = q00 * b0 + q01 * b1 + q02 * b2, q01 * b0 + q11 * b1 + q12 * b2, \
            q02 * b0 + q12 * b1 + q22 * b2
        g, h, i = s00 * b0 + s01 * b1 + s02 * b2, s01 * b0 + s11 * b1 + s12 * b2, \
            s02 * b0 + s12 * b1 + s22 * b2
        r0 = rho0 - (a * b0 + b * b1 + c * b2)
        r1 = rho1 - (d * b0 + e * b1 + f * b2)
        r2 = rho2 - (g * b0 + h * b1 + i * b2)
        A0, A1, A2 = e * i - f * h, c * h - b * i, b * f - c * e
        det = a * A0 + d * A1 + g * A2
        if not det or not math.isfinite(det):
            return [b0, b1, b2], False
        # J = 2 Gb: the step J^-1 r = (Gb)^-1 r / 2
        k = 0.5 / det
        x0 = (A0 * r0 + A1 * r1 + A2 * r2) * k
        x1 = ((f * g - d * i) * r0 + (a * i - c * g) * r1 + (c * d - a * f) * r2) * k
        x2 = ((d * h - e * g) * r0 + (b * g - a * h) * r1 + (a * e - b * d) * r2) * k
        b0, b1, b2 = b0 + x0, b1 + x1, b2 + x2
        s2_prev, nb2_prev = s2, nb2
        s2 = 4.0 * (x0 * x0 + x1 * x1 + x2 * x2)  # the unhalved step, as in _gauss_newton
        nb2 = b0 * b0 + b1 * b1 + b2 * b2
        # at its fixed point to rounding: the remaining iterations would move beta ~1e-16
        if it >= 3 and s2 <= _GN_AT_REST**2 * nb2:
            break
        # or converging quadratically, relative step d_t <= 10 d_{t-1}^2, with d_t <= 1e-8: the
        # next step (~d_t^2) would be at rounding level too (had the convergence been only
        # linear, at a rate r, this needs r^2 <= 10 d_t, and what is left is below 3e-12)
        if it and s2 <= 1e-16 * nb2 and s2 * nb2_prev**2 <= 100.0 * s2_prev**2 * nb2:
            break
    return [b0, b1, b2], s2 < 1e-14 * nb2


def _refine(beta: list, planar: bool, G, dots: np.ndarray, rho: np.ndarray, rhol: list):
    """Gauss-Newton from one hypothesis: (betas, converged)."""
    if planar:
        return _newton_planar(beta, G, rhol)
    b, conv = _gauss_newton(np.array([beta]), dots, rho)
    return b[0].tolist(), bool(conv[0])


class _Model(NamedTuple):
    """What depends on the object points only (see :func:`_model`)."""

    planar: bool
    k: int  # k + 1 control points
    hand: float  # handedness of the principal frame
    O: np.ndarray  # (n, (k+1)^2): alpha_i alpha_i^T
    ones: np.ndarray  # (n, 1)
    Dm3: np.ndarray  # (pairs, 3, (k+1) * 3): flattened control points -> c_a - c_b per pair
    rho: np.ndarray  # (pairs,): ||C_a - C_b||^2
    rhol: list  # the same as floats
    A3: np.ndarray  # (2n + 1, k+1): [alphas; alphas - mean alphas; mean alphas]
    W4: np.ndarray  # (3 (2n + 1), 4): the weighted sums of _score
    SaXt: np.ndarray  # (4, k+1): [Sa | mean alphas]^T, see _align_control
    Pbar: np.ndarray  # (3,): centroid


def _model(P: np.ndarray) -> _Model:
    """Everything that depends on the object points only, computed once per model (cached by
    :func:`~cutterpose.solvers.pnp.base.model_cache`)."""
    cache = model_cache(P)
    model = cache.get("epnp-v3")  # (a new key: the layout changed)
    if model is None:
        planar = is_planar(P)
        if not planar and len(P) < 4:
            raise DegenerateInputError(f"EPnP needs at least 4 non-planar points, got {len(P)}")
        n = len(P)
        alphas, C, k, hand = _control_points(P, planar)
        O = (alphas[:, :, None] * alphas[:, None, :]).reshape(n, -1)
        ia, ib = np.triu_indices(k + 1, 1)
        # Delta^(ab) = c_a - c_b of every pair as one product with a +-1 matrix, acting on the
        # flattened control points (index 3 j + coordinate)
        Dm = np.zeros((len(ia), k + 1))
        Dm[np.arange(len(ia)), ia] = 1.0
        Dm[np.arange(len(ia)), ib] = -1.0
        rho = np.sum((C[ia] - C[ib]) ** 2, axis=1)
        Pbar = P.mean(axis=0)
        # X - Xbar = (alphas - mean alphas) c: the centred alphas give the centred points, the
        # mean alphas the centroid
        abar = alphas.mean(axis=0)
        ac = alphas - abar
        # for the alignment: the cross-covariance sum_i (X_i - Xbar)(P_i - Pbar)^T is c^T Sa
        # with Sa = ac^T (P - Pbar), and the centroid Xbar is c^T abar: from the control points
        # c alone
        SaXt = np.vstack([(P - Pbar).T @ ac, abar])
        # rows: the norms, the squared norms and the depths of [X (errors); X - Xbar; Xbar]
        W4 = np.zeros((3, 2 * n + 1, 4))
        W4[0, :n, 0] = 1.0 / n  # E_mean
        W4[0, n:2 * n, 1] = np.linalg.norm(P - Pbar, axis=1)  # sum_i |X_i - Xbar| dw_i
        W4[1, n:2 * n, 2] = 1.0  # sum_i |X_i - Xbar|^2
        W4[2, 2 * n, 3] = 1.0  # mean depth
        W4 = W4.reshape(-1, 4)
        Dm3 = np.kron(Dm, np.eye(3)).reshape(len(ia), 3, 3 * (k + 1))
        model = _Model(planar, k, hand, O, np.ones((n, 1)), Dm3, rho, rho.tolist(),
                       np.vstack([alphas, ac, abar]), W4, SaXt, Pbar)
        for arr in model:
            if isinstance(arr, np.ndarray):
                arr.flags.writeable = False
        cache["epnp-v3"] = model
    return model


def _score(hyps: list, Wf: np.ndarray, md: _Model, m: np.ndarray):
    """Mean reprojection error (E_mean, normalised units) of every hypothesis, its scale to the
    object's distances from the centroid (least squares) and its mean depth, as lists.

    The camera-frame control points ``c = sum_k beta_k w_k`` give the points ``X = alphas c``,
    the centred points ``X - Xbar = (alphas - mean alphas) c`` and the centroid ``Xbar`` in one
    product with the model's stacked ``A3 = [alphas; alphas - mean alphas; mean alphas]``. With
    ``X_i`` replaced by its reprojection error ``X_i / z_i - (u_i, v_i, 1)`` (third entry 0),
    the row norms give ``E_mean`` and ``sum_i |X_i - Xbar| dw_i``, their squares
    ``sum_i |X_i - Xbar|^2``, the depths the mean depth: one weighted sum (``md.W4``)."""
    n = len(m)
    c = (np.array(hyps) @ Wf).reshape(len(hyps), -1, 3)
    T = md.A3 @ c  # (h, 2n + 1, 3)
    with np.errstate(divide="ignore", invalid="ignore", over="ignore"):
        X = T[:, :n]
        X /= X[:, :, 2:]
        X -= np.concatenate((m, md.ones), axis=1)
        sq = (T * T) @ _ONES3
        e, num, den, zbar = (np.concatenate((np.sqrt(sq), sq, T[:, :, 2]), axis=1)
                             @ md.W4).T.tolist()
    # E_mean is invariant to the scale and sign of beta; a zero spread has no scale
    return e, [a / b if b else math.nan for a, b in zip(num, den, strict=True)], zbar


def _align_control(SXt: np.ndarray, Pbar: np.ndarray):
    """:func:`~cutterpose.solvers.pnp.base.align_rigid` of ``P`` to ``X = alphas c`` from
    ``SXt = [Sa | abar]^T c`` (4, 3) of the camera-frame control points ``c``: the transposed
    cross-covariance ``(sum_i (X_i - Xbar)(P_i - Pbar)^T)^T = Sa^T c`` and the centroid
    ``Xbar = c^T abar`` of X (model-only ``Sa``, ``abar``, see :func:`_model`), without forming X.
    The same AL-ok rule: ``S = diag(1, 1, -1)`` when ``det(U V^T) < 0``."""
    R = rotation_from_covariance(SXt[:3].T)
    return R, SXt[3] - R @ Pbar


def candidates(P: np.ndarray, m: np.ndarray, f_px: float | None = None) -> list[Candidate]:
    """EPnP poses: the refined best hypothesis, and a second, different solution when there is
    one (see the module docstring). ``f_px`` (the focal length in pixels) only sets the N >= 3
    gate; without it the nominal focal length of the project cameras is assumed."""
    md = _model(P)
    planar, k, rho, rhol = md.planar, md.k, md.rho, md.rhol
    n_max = k + 1
    V = _kernel(md.O, md.ones, m, n_max)
    Wf = V.T  # row k: the control points of beta = e_k, flattened
    D = md.Dm3 @ V  # (pairs, 3, n_max): Delta of every w_k
    dots = D.transpose(0, 2, 1) @ D  # (pairs, n_max, n_max): Delta_k . Delta_l
    dl = dots.tolist()

    hyps = _hypotheses_low(dl, rhol, n_max)
    el, sc, zbar = _score(hyps, Wf, md, m)
    gate = _GATE_PX / (f_px if f_px else _NOMINAL_F_PX)
    if not min(el) <= gate:  # NaN runs them too
        more = _hypotheses(dots, rho, n_max, start=3)
        if more:
            hyps += more
            el, sc, zbar = _score(hyps, Wf, md, m)

    # scaled to the object's distances, positive mean depth
    bl = []
    for i, (beta, s) in enumerate(zip(hyps, sc, strict=True)):
        if not (math.isfinite(el[i]) and math.isfinite(s) and s > 0):
            el[i] = math.inf
        elif zbar[i] < 0:
            s = -s
        bl.append([b * s for b in beta])
    # hypotheses by E_mean, stably (two, the usual case, without sorted's overhead)
    order = (([1, 0] if el[1] < el[0] else [0, 1]) if len(el) == 2
             else sorted(range(len(el)), key=el.__getitem__))
    if not el[order[0]] < math.inf:
        return []

    G = [(d[0][0], d[0][1], d[0][2], d[1][1], d[1][2], d[2][2]) for d in dl] if planar else None
    best, conv = _refine(bl[order[0]], planar, G, dots, rho, rhol)
    if not conv:  # the best hypothesis as it is (a point on GN's path would be arbitrary)
        best = bl[order[0]]
    kept = [best]
    # a second solution, for the ambiguity ratio: the next hypothesis that does not start next
    # to the refined best (those converge onto it), refined, if it reaches a different solution
    nb = _dist(best, None)
    for h in order[1:]:
        if not el[h] < math.inf:
            break
        if _dist_pm(bl[h], best) <= _SAME_START * nb:
            continue
        second, conv = _refine(bl[h], planar, G, dots, rho, rhol)
        if conv and _dist_pm(second, best) > _SAME_BETA * nb:
            kept.append(second)
        break

    c = (np.array(kept) @ Wf).reshape(-1, k + 1, 3)
    SXt = md.SaXt @ c  # (h, 4, 3): [cross-covariance^T; centroid] (see _align_control)
    if planar:
        # positive mean depth (GN keeps the sign; checked again all the same)
        signs = [-1.0 if z < 0 else 1.0 for z in SXt[:, 3, 2].tolist()]
    else:
        # det [c_j - c_0] = det(R) det(diag(sigma) V^T): its sign must be the frame's
        # (as np.sign: a zero or NaN determinant zeroes or poisons the candidate)
        signs = [((d > 0) - (d < 0) if d == d else math.nan) * md.hand
                 for d in map(det3, (c[:, 1:] - c[:, :1]).tolist())]
    # -beta negates c, so the cross-covariance and the centroid
    return [_align_control(S if sg == 1.0 else S * sg, md.Pbar)
            for S, sg in zip(SXt, signs, strict=True)]


def _dist(a: list, b: list | None) -> float:
    """Euclidean norm of ``a - b`` (of ``a`` when b is None) on Python floats."""
    return math.hypot(*a) if b is None else math.dist(a, b)


def _dist_pm(a: list, b: list) -> float:
    """``min(||a - b||, ||a + b||)``: beta and -beta are the same solution up to the sign."""
    return min(math.dist(a, b), math.dist(a, [-y for y in b]))


def solve(points_px, camera, model):
    """epnp: ``solve(points_px, camera, model) -> PoseEstimate`` (the common wrapper of
    :func:`~cutterpose.solvers.pnp.base.make_solver`, with the camera's focal length passed on to
    :func:`candidates` for the gate in pixels)."""
    f = getattr(camera, "focal_px", None)
    return _solver_for(float(f) if f else None)(points_px, camera, model)


@lru_cache(maxsize=8)
def _solver_for(f_px: float | None):
    return make_solver("epnp", partial(candidates, f_px=f_px), min_points=4)


class EPnP(CorrespondenceMethod):
    name = "epnp"
    description = "EPnP (Lepetit et al. 2009)"
    solve = staticmethod(solve)
