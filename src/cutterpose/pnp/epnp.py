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

Each hypothesis is scaled to the object's distances (least squares on the distances from the
centroid, paper eq. 15 context), then refined by Gauss-Newton on all ``k`` betas over the
distance residuals ``r_ab = ||C_a - C_b||^2 - ||c_a - c_b||^2`` (paper section 3.5; for the
planar case notes 2.3: 3 residuals in 3 betas). The sign of ``beta`` is fixed by the orientation of
the control points for a general set (``det [c_1 - c_0, c_2 - c_0, c_3 - c_0]`` has the sign of
the world's, which keeps a mirrored structure out) and by positive mean depth for a planar set.
The pose is the rigid alignment (:func:`~cutterpose.pnp.base.align_rigid`, AL-ok) of ``P`` to the
camera-frame points ``X_i = sum_j alpha_ij c_j``.

Convention:
    ``P`` (n, 3) object points in mm, ``m`` (n, 2) normalised image coordinates; control points
    and betas are in mm (the alphas are unit-free, so the linear system is well conditioned
    whatever the units).

Deviations from the reference code (notes sections 2 and 8):
    * Data-adapted control points, as in the IJCV paper, instead of fixed unit points (those
      depend on the units and condition the system badly in mm).
    * Planarity detected, any plane; the planar case uses 3 control points in the plane.
    * Hypotheses ``N = 1..3`` (planar) / ``1..4`` (general) are all built and all refined,
      without the reference's error gates (5/800 or 20 in normalised units).
    * Gauss-Newton on the planar betas too (notes 2.3), 8 iterations (fewer once every step is at
      rounding level), from every hypothesis;
      hypotheses whose GN has not converged are dropped (unless none converged).
    * Alignment AL-ok, never ``R -> -R`` (AL-E is wrong on planar points).
    * Sign by orientation (general) / depth (planar), not "negate all if any depth < 0".
    * Candidates are returned for selection by RMS reprojection error (not ``E_mean``); after
      refinement the hypotheses usually converge to the same betas; duplicates are merged and
      only the best two distinct hypotheses (by reprojection error of the camera-frame points
      ``X_i``) are returned: the selection and the ambiguity ratio need no more, and every
      alignment costs time.
"""

from __future__ import annotations

import math
from functools import cache

import numpy as np
from scipy.linalg.lapack import dgeev as _dgeev
from scipy.linalg.lapack import dgesv as _dgesv

from ..errors import DegenerateInputError
from .base import (
    Candidate,
    align_rigid_many,
    is_planar,
    kron_normal,
    make_solver,
    model_cache,
    smallest_eigvecs,
    svd_small,
)

__all__ = ["candidates", "solve"]

_GN_ITERATIONS = 8
_GN_AT_REST = 1e-14  # relative step below which Gauss-Newton has nothing left to do
_SAME_BETA = 1e-6  # relative: GN from two hypotheses reached the same solution
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


def _kernel(alphas: np.ndarray, m: np.ndarray, n_vec: int, O: np.ndarray | None = None
            ) -> np.ndarray:
    """The ``n_vec`` eigenvectors of ``M^T M`` with the least eigenvalues, as (N, k+1, 3).

    ``M^T M = sum_i kron(alpha_i alpha_i^T, B_i^T B_i)`` is built from its structure
    (:func:`~cutterpose.pnp.base.kron_normal`; ``O`` the cached ``alpha_i alpha_i^T``) rather than
    from the 2n rows of ``M``: the same matrix, fewer operations."""
    kp = alphas.shape[1]
    if O is None:
        O = (alphas[:, :, None] * alphas[:, None, :]).reshape(len(alphas), -1)
    V = smallest_eigvecs(kron_normal(O, m, coord_outer=False), n_vec)
    return V.T.reshape(n_vec, kp, 3)


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


def _hypotheses(dots: np.ndarray, rho: np.ndarray, n_max: int) -> list[np.ndarray]:
    """Initial betas (padded to ``n_max``) for ``N = 1..n_max``; ``dots`` (pairs, n_max, n_max)
    holds ``Delta_k . Delta_l`` per control-point pair."""
    out = []
    for N in range(1, n_max + 1):
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


def _model(P: np.ndarray):
    """Everything that depends on the object points only, computed once per model (cached by
    :func:`~cutterpose.pnp.base.model_cache`)."""
    cache = model_cache(P)
    model = cache.get("epnp")
    if model is None:
        planar = is_planar(P)
        if not planar and len(P) < 4:
            raise DegenerateInputError(f"EPnP needs at least 4 non-planar points, got {len(P)}")
        alphas, C, k, hand = _control_points(P, planar)
        O = (alphas[:, :, None] * alphas[:, None, :]).reshape(len(P), -1)
        ia, ib = np.triu_indices(k + 1, 1)
        rho = np.sum((C[ia] - C[ib]) ** 2, axis=1)
        dw = np.linalg.norm(P - P.mean(axis=0), axis=1)
        asum = alphas.sum(axis=0)
        for arr in (alphas, O, rho, dw, asum):
            arr.flags.writeable = False
        model = cache["epnp"] = (planar, alphas, O, k, hand, ia, ib, rho, dw, asum)
    return model


def candidates(P: np.ndarray, m: np.ndarray) -> list[Candidate]:
    """EPnP poses, one per distinct refined hypothesis; see the module docstring."""
    planar, alphas, O, k, hand, ia, ib, rho, dw, asum = _model(P)
    n_max = k + 1
    W = _kernel(alphas, m, n_max, O)  # (n_max, k+1, 3)
    D = W[:, ia] - W[:, ib]  # (n_max, pairs, 3)
    Df = D.transpose(1, 0, 2)
    dots = Df @ Df.transpose(0, 2, 1)  # (pairs, n_max, n_max): Delta_k . Delta_l
    betas = np.array(_hypotheses(dots, rho, n_max))
    Wf = W.reshape(n_max, -1)
    # camera-frame points X = alphas c, c = sum_k beta_k W_k (H, k+1, 3)
    X = alphas @ (betas @ Wf).reshape(-1, k + 1, 3)
    # scale to the object's distances from the centroid
    Xc = X - X.sum(axis=1, keepdims=True) / X.shape[1]
    dc = np.sqrt(np.sum(Xc * Xc, axis=2))
    den = np.sum(dc * dc, axis=1)
    ok = den > 0
    if not ok.all():
        betas, dc, den = betas[ok], dc[ok], den[ok]
    betas = betas * (dc @ dw / den)[:, None]
    betas, converged = _gauss_newton(betas, dots, rho)
    if converged.any() and not converged.all():
        betas = betas[converged]

    c = (betas @ Wf).reshape(-1, k + 1, 3)
    if planar:
        depth = c[:, :, 2] @ asum
        sign = np.where(depth < 0, -1.0, 1.0)
    else:
        # det [c_j - c_0] = det(R) det(diag(sigma) V^T): its sign must be the frame's
        sign = np.sign(np.linalg.det(c[:, 1:] - c[:, :1])) * hand
    c = c * sign[:, None, None]
    X = alphas @ c

    # score on the camera-frame points themselves (no alignment needed), best first
    with np.errstate(divide="ignore", invalid="ignore"):
        d = X[..., :2] / X[..., 2:] - m
        e = np.sum(d * d, axis=(1, 2))
    order = np.argsort(e)  # NaN sorts last, as inf; the loop stops at the first of either
    # hypotheses that converged to the same betas are one candidate; select() needs only the
    # best and the runner-up (ambiguity ratio), so two distinct ones are aligned at most
    kept: list[int] = []
    bl = betas.tolist()
    el = e.tolist()
    for h in order.tolist():
        if not el[h] < math.inf:
            break
        bh = bl[h]
        if all(_dist(bh, bl[g]) > _SAME_BETA * _dist(bl[g], None) for g in kept):
            kept.append(h)
            if len(kept) == 2:
                break
    if not kept:
        return []
    return align_rigid_many(P, X[kept])


def _dist(a: list, b: list | None) -> float:
    """Euclidean norm of ``a - b`` (of ``a`` when b is None) on Python floats."""
    if b is None:
        return sum(x * x for x in a) ** 0.5
    return sum((x - y) ** 2 for x, y in zip(a, b, strict=True)) ** 0.5


solve = make_solver("epnp", candidates, min_points=4)
