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
    * Gauss-Newton on the planar betas too (notes 2.3), 8 iterations, from every hypothesis;
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

from functools import cache

import numpy as np

from ..errors import DegenerateInputError
from .base import Candidate, align_rigid, is_planar, make_solver

__all__ = ["candidates", "solve"]

_GN_ITERATIONS = 8
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


def _kernel(alphas: np.ndarray, m: np.ndarray, n_vec: int) -> np.ndarray:
    """The ``n_vec`` eigenvectors of ``M^T M`` with the least eigenvalues, as (N, k+1, 3)."""
    n, kp = alphas.shape
    B = np.zeros((n, 2, 3))
    B[:, 0, 0] = 1.0
    B[:, 1, 1] = 1.0
    B[:, :, 2] = -m
    M = (alphas[:, None, :, None] * B[:, :, None, :]).reshape(2 * n, 3 * kp)
    _, V = np.linalg.eigh(M.T @ M)
    return V[:, :n_vec].T.reshape(n_vec, kp, 3)


def _beta_from_products(Bmat: np.ndarray) -> np.ndarray:
    """``beta`` with ``beta beta^T`` nearest the symmetric product matrix (sign arbitrary)."""
    w, V = np.linalg.eigh(Bmat)
    return V[:, -1] * np.sqrt(max(w[-1], 0.0))


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


def _minor_rows(Z: np.ndarray, N: int) -> np.ndarray:
    """Rows of the linearised rank-one conditions on ``B(lambda) = sym(Z lambda)``.

    Every 2x2 minor ``B_ik B_jl - B_il B_jk`` is a quadratic form ``lambda^T Q lambda``; the
    result holds its coefficients on the packed products ``lambda_a lambda_b`` (a <= b).
    """
    ik, jl, il, jk = _minor_index(N)
    Q = Z[ik][:, :, None] * Z[jl][:, None, :] - Z[il][:, :, None] * Z[jk][:, None, :]
    iu, _, w = _tri(Z.shape[1])
    # coefficient of lambda_a lambda_b: Q_ab + Q_ba (a < b), Q_aa (a = b)
    return 0.5 * w * (Q[:, iu[0], iu[1]] + Q[:, iu[1], iu[0]])


def _relinearise(L: np.ndarray, rho: np.ndarray, N: int) -> list[np.ndarray]:
    """Betas from more products than distance equations (paper section 3.3; notes 6.4)."""
    p = L.shape[1]
    A = np.column_stack([L, -rho])
    Vt = np.linalg.svd(A)[2]
    Z = Vt[L.shape[0]:].T  # (p + 1, r): the products and the homogenising 1
    r = Z.shape[1]
    C = _minor_rows(Z[:p], N)
    _, s, Wt = np.linalg.svd(C)
    n_null = C.shape[1] - np.count_nonzero(s > 1e-10 * s[0])
    lambdas = []
    if C.shape[0] >= C.shape[1] or n_null <= 1:
        # overdetermined: the least-squares rank-one product matrix
        lam = _beta_from_products(_sym_from_upper(Wt[-1], r))
        lambdas.append(lam)
    else:
        # exactly determined: r solutions; multiplication matrix on the null space
        Nl = Wt[C.shape[1] - r:].T  # (r(r+1)/2, r)
        pos = _tri(r)[1]
        Ng = np.einsum("j,jkc->kc", _G[:r], Nl[pos])
        Nh = np.einsum("j,jkc->kc", _H[:r], Nl[pos])
        w, E = np.linalg.eig(np.linalg.solve(Ng, Nh))
        real = np.abs(w.imag) <= 1e-6 * (1.0 + np.abs(w.real))
        lambdas.extend((Ng @ E[:, real].real).T)
    out = []
    for lam in lambdas:
        h = Z[p] @ lam
        if abs(h) < 1e-12 * np.linalg.norm(lam):
            continue
        out.append(_beta_from_products(_sym_from_upper(Z[:p] @ (lam / h), N)))
    return out


def _hypotheses(dots: np.ndarray, rho: np.ndarray, n_max: int) -> list[np.ndarray]:
    """Initial betas (padded to ``n_max``) for ``N = 1..n_max``; ``dots`` (pairs, n_max, n_max)
    holds ``Delta_k . Delta_l`` per control-point pair."""
    out = []
    for N in range(1, n_max + 1):
        iu, _, w = _tri(N)
        L = dots[:, iu[0], iu[1]] * w
        if L.shape[1] <= L.shape[0]:
            b = np.linalg.solve(L.T @ L, L.T @ rho)
            betas = [_beta_from_products(_sym_from_upper(b, N))]
        else:
            betas = _relinearise(L, rho, N)
        for beta in betas:
            full = np.zeros(n_max)
            full[:N] = beta
            out.append(full)
    return out


def _gauss_newton(beta: np.ndarray, dots: np.ndarray, rho: np.ndarray):
    """Gauss-Newton on the distance residuals, all hypotheses at once: beta (H, N); returns the
    refined betas and which of them converged.

    With ``G_p = [Delta_k . Delta_l]`` of pair p, ``||c_a - c_b||^2 = beta^T G_p beta``, so the
    residual is ``rho_p - beta^T G_p beta`` and its gradient ``2 G_p beta``.
    """
    eye = 1e-12 * np.eye(beta.shape[1])
    for _ in range(_GN_ITERATIONS):
        Gb = np.einsum("pkl,hl->hpk", dots, beta)
        r = rho - np.einsum("hpk,hk->hp", Gb, beta)
        JtJ = np.einsum("hpk,hpl->hkl", Gb, Gb)
        scale = np.einsum("hkk->h", JtJ)[:, None, None]
        # J = 2 Gb: the step (J^T J)^-1 J^T r = (Gb^T Gb)^-1 Gb^T r / 2
        step = np.linalg.solve(JtJ + eye * scale, np.einsum("hpk,hp->hk", Gb, r)[..., None])
        beta = beta + 0.5 * step[..., 0]
    # converged: the last step is negligible (a hypothesis still on its way would be scored at an
    # arbitrary point of its path, and the choice between hypotheses would depend on that)
    converged = np.linalg.norm(step[..., 0], axis=1) < 1e-7 * np.linalg.norm(beta, axis=1)
    return beta, converged


def candidates(P: np.ndarray, m: np.ndarray) -> list[Candidate]:
    """EPnP poses, one per distinct refined hypothesis; see the module docstring."""
    planar = is_planar(P)
    if not planar and len(P) < 4:
        raise DegenerateInputError(f"EPnP needs at least 4 non-planar points, got {len(P)}")
    alphas, C, k, hand = _control_points(P, planar)
    n_max = k + 1
    W = _kernel(alphas, m, n_max)  # (n_max, k+1, 3)
    ia, ib = np.triu_indices(k + 1, 1)
    D = W[:, ia] - W[:, ib]  # (n_max, pairs, 3)
    rho = np.sum((C[ia] - C[ib]) ** 2, axis=1)

    dots = np.einsum("kpi,lpi->pkl", D, D)
    betas = np.array(_hypotheses(dots, rho, n_max))
    c = np.einsum("hk,kji->hji", betas, W)  # (H, k+1, 3) camera-frame control points
    X = np.einsum("nj,hji->hni", alphas, c)
    # scale to the object's distances from the centroid
    dw = np.linalg.norm(P - P.mean(axis=0), axis=1)
    dc = np.linalg.norm(X - X.mean(axis=1, keepdims=True), axis=2)
    den = np.einsum("hn,hn->h", dc, dc)
    ok = den > 0
    betas, dc, den = betas[ok], dc[ok], den[ok]
    betas = betas * (dc @ dw / den)[:, None]
    betas, converged = _gauss_newton(betas, dots, rho)
    if converged.any():
        betas = betas[converged]

    c = np.einsum("hk,kji->hji", betas, W)
    if planar:
        depth = np.einsum("nj,hj->h", alphas, c[:, :, 2])
        sign = np.where(depth < 0, -1.0, 1.0)
    else:
        # det [c_j - c_0] = det(R) det(diag(sigma) V^T): its sign must be the frame's
        sign = np.sign(np.linalg.det(c[:, 1:] - c[:, :1])) * hand
    c = c * sign[:, None, None]
    X = np.einsum("nj,hji->hni", alphas, c)

    # score on the camera-frame points themselves (no alignment needed), best first
    with np.errstate(divide="ignore", invalid="ignore"):
        e = np.sum((X[..., :2] / X[..., 2:] - m) ** 2, axis=(1, 2))
    e = np.where(np.isfinite(e), e, np.inf)
    order = np.argsort(e)
    # hypotheses that converged to the same betas are one candidate; select() needs only the
    # best and the runner-up (ambiguity ratio), so two distinct ones are aligned at most
    kept: list[int] = []
    for h in order:
        if not np.isfinite(e[h]):
            break
        if all(np.linalg.norm(betas[h] - betas[g]) > _SAME_BETA * np.linalg.norm(betas[g])
               for g in kept):
            kept.append(h)
            if len(kept) == 2:
                break
    return [align_rigid(P, X[h]) for h in kept]


solve = make_solver("epnp", candidates, min_points=4)
