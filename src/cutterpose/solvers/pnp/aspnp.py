"""ASPnP: accurate and scalable PnP over a non-unit quaternion (Zheng, Sugimoto, Okutomi 2013).

Convention:
    Object points ``P`` (n, 3) in mm, image points ``m`` (n, 2) normalised (``K^-1`` ideal
    pixels); the pose maps ``X = R P + t`` (camera frame, mm). Internally ``P`` is centred and
    divided by its RMS radius ``s`` (notes 5.5): ``P' = (P - c)/s``; a pose ``(R, t')`` of
    ``P'`` is ``t = s t' - R c`` for ``P``. Quaternions are ``q = (a, b, c, d)``, ``a`` scalar.

Method (Zheng, Sugimoto, Okutomi, *ASPnP: an accurate and scalable solution to the
perspective-n-point problem*, IEICE Trans. Inf. & Syst. E96-D(7), 2013; the PnP notes section 4):

* ``R = Rbar(q)/|q|^2`` and ``t = tau/|q|^2`` with ``Rbar`` the rotation of a non-unit quaternion
  (quadratic in ``q``, linear in ``mu(q) = (a^2, ab, ac, ad, b^2, bc, bd, c^2, cd, d^2)``).
  Multiplying the projection equations by ``|q|^2`` makes them linear in ``(mu, tau)``::

      rho_x,i = (l_1(P_i) - u_i l_3(P_i)) . mu + tau_1 - u_i tau_3
      rho_y,i = (l_2(P_i) - v_i l_3(P_i)) . mu + tau_2 - v_i tau_3,     rho = A mu + B tau.

* ``tau = -(B^T B)^-1 B^T A mu`` by least squares, leaving the homogeneous quartic
  ``F(q) = mu^T M mu`` with ``M = A_perp^T A_perp``, ``A_perp = (I - B B^+) A``
  (``F = |q|^4 sum_i z_i^2 |e_i|^2``, a depth-weighted algebraic error).
* One component of ``q`` is fixed; the four cases partition all rotations: (1) ``a = 1``:
  ``grad F(1, b, c, d) = 0``, 3 cubics, 27 solutions; (2) ``a = 0, b = 1``: 2 cubics, 9;
  (3) ``a = b = 0, c = 1``: one cubic; (4) ``q = (0, 0, 0, 1)``.
* Every real stationary point of every case is a candidate (no Hessian test, as the authors);
  the common wrapper keeps those with all points in front (this removes the planar twin
  ``(R diag(-1, -1, 1), -t)``) and picks the least reprojection error.

The authors solve cases 1 and 2 with generated Groebner-basis solvers; here both go through the
Macaulay null-space solver of :mod:`cutterpose.solvers.pnp.polysolve` (degree 8, nullity 27; degree
7,
nullity 9), which returns all complex solutions; the real ones are polished by Newton's method.
"""

from __future__ import annotations

import numpy as np

from ..method import CorrespondenceMethod
from .base import Candidate, make_solver
from .polysolve import MacaulaySolver, PolySystem, monomials, quadratic_form_gradient_map

__all__ = ["ASPnP", "solve", "aspnp_candidates", "stationary_points", "MU_EXPS", "l_matrices",
           "rbar", "mu_of", "normalise_object"]

# ---- the quaternion monomials shared with OPnP ---------------------------------------------

#: exponents of mu(q) = (a^2, ab, ac, ad, b^2, bc, bd, c^2, cd, d^2) over (a, b, c, d)
MU_EXPS = np.array([[2, 0, 0, 0], [1, 1, 0, 0], [1, 0, 1, 0], [1, 0, 0, 1], [0, 2, 0, 0],
                    [0, 1, 1, 0], [0, 1, 0, 1], [0, 0, 2, 0], [0, 0, 1, 1], [0, 0, 0, 2]])

# row k of Rbar(q) p = l_k(p) . mu(q), l_k(p) = _L[k] @ p (notes section 0)
_L = np.zeros((3, 10, 3))
for _k, _rows in enumerate((
        ((1, 0, 0), (0, 0, 0), (0, 0, 2), (0, -2, 0), (1, 0, 0), (0, 2, 0), (0, 0, 2), (-1, 0, 0),
         (0, 0, 0), (-1, 0, 0)),
        ((0, 1, 0), (0, 0, -2), (0, 0, 0), (2, 0, 0), (0, -1, 0), (2, 0, 0), (0, 0, 0), (0, 1, 0),
         (0, 0, 2), (0, -1, 0)),
        ((0, 0, 1), (0, 2, 0), (-2, 0, 0), (0, 0, 0), (0, 0, -1), (0, 0, 0), (2, 0, 0),
         (0, 0, -1), (0, 2, 0), (0, 0, 1)))):
    _L[_k] = np.array(_rows, float)


def l_matrices(P: np.ndarray) -> np.ndarray:
    """``(3, n, 10)``: ``[k, i] = l_k(P_i)``, so that ``(Rbar(q) P_i)_k = l_k(P_i) . mu(q)``."""
    return np.einsum("kmj,ij->kim", _L, P)


def mu_of(q: np.ndarray) -> np.ndarray:
    """``mu(q)`` for quaternions ``q`` ``(..., 4)`` -> ``(..., 10)``."""
    q = np.asarray(q, float)
    return np.prod(q[..., None, :] ** MU_EXPS, axis=-1)


def rbar(q: np.ndarray) -> np.ndarray:
    """``Rbar(q) = |q|^2 R(q/|q|)`` for ``q`` ``(..., 4)`` -> ``(..., 3, 3)``."""
    return np.einsum("kmj,...m->...kj", _L, mu_of(q))


def normalise_object(P: np.ndarray) -> tuple[np.ndarray, np.ndarray, float]:
    """``(P - c)/s`` with ``c`` the centroid and ``s`` the RMS radius (notes 5.5)."""
    c = P.mean(axis=0)
    s = float(np.sqrt(np.mean(np.sum((P - c) ** 2, axis=1))))
    return (P - c) / s, c, s


# ---- the four cases: fixed components, polynomial structure (built once) --------------------

_NAN = np.nan
CASE1_FIXED = np.array([1.0, _NAN, _NAN, _NAN])
CASE2_FIXED = np.array([0.0, 1.0, _NAN, _NAN])
_CASE3_FIXED = np.array([0.0, 0.0, 1.0, _NAN])
_SUP1, _SUP2, _SUP3 = monomials(3, 3), monomials(2, 3), monomials(1, 3)
MAP1 = quadratic_form_gradient_map(MU_EXPS, CASE1_FIXED, _SUP1)  # (3, 20, 100)
MAP2 = quadratic_form_gradient_map(MU_EXPS, CASE2_FIXED, _SUP2)  # (2, 10, 100)
_MAP3 = quadratic_form_gradient_map(MU_EXPS, _CASE3_FIXED, _SUP3)  # (1, 4, 100)
_SOLVER1 = MacaulaySolver(_SUP1, degree=8, n_solutions=27)
_SOLVER2 = MacaulaySolver(_SUP2, degree=7, n_solutions=9)
SYS1, SYS2, _SYS3 = PolySystem(_SUP1), PolySystem(_SUP2), PolySystem(_SUP3)

#: reality test on a computed root, relative to its size
IMAG_TOL = 1e-6
#: a polished root is accepted when |grad| <= this times the gradient's coefficient scale
GRAD_TOL = 1e-8


def cost_matrices(P: np.ndarray, m: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """``M`` (10, 10) of ``F(q) = mu^T M mu`` and ``K`` (3, 10) with ``tau = -K mu``."""
    Lk = l_matrices(P)
    u, v = m[:, 0], m[:, 1]
    A = np.concatenate([Lk[0] - u[:, None] * Lk[2], Lk[1] - v[:, None] * Lk[2]])
    n = len(P)
    B = np.zeros((2 * n, 3))
    B[:n, 0] = 1.0
    B[n:, 1] = 1.0
    B[:n, 2] = -u
    B[n:, 2] = -v
    K = np.linalg.solve(B.T @ B, B.T @ A)
    Ap = A - B @ K
    return Ap.T @ Ap, K


def _real_stationary(system: PolySystem, coef: np.ndarray, roots: np.ndarray) -> np.ndarray:
    """Near-real roots, polished by Newton and kept if they really are stationary points."""
    if len(roots) == 0:
        return roots.real
    size = 1.0 + np.linalg.norm(roots, axis=1)
    keep = np.all(np.isfinite(roots), axis=1) & \
        (np.abs(roots.imag).max(axis=1) <= IMAG_TOL * size)
    x = system.newton_polish(coef, roots[keep].real)
    scale = np.abs(coef).sum(axis=1).max() * (1.0 + np.linalg.norm(x, axis=1)) ** 3
    ok = np.linalg.norm(system.evaluate(coef, x), axis=1) <= GRAD_TOL * scale
    x = x[ok]
    # drop duplicates (a double root found twice)
    out = []
    for xi in x:
        if all(np.linalg.norm(xi - y) > 1e-9 * (1 + np.linalg.norm(xi)) for y in out):
            out.append(xi)
    return np.array(out).reshape(-1, system.exps.shape[1])


def stationary_points(Pn: np.ndarray, m: np.ndarray) -> dict:
    """All real stationary points of the four cases for normalised object points ``Pn``.

    Returns a dict with ``q`` (p, 4) the quaternions (fixed components included), ``case`` (p,),
    ``cost`` (p,) the case's cost ``F`` at the point, ``minimum`` (p,) whether the Hessian in the
    case's free variables is positive semidefinite (relative tolerance), ``M``, ``K`` and
    diagnostics.
    """
    M, K = cost_matrices(Pn, m)
    M = M / np.trace(M)  # scale-free coefficients; does not move the stationary points
    g = M.ravel()
    qs, cases, minima, info = [], [], [], {}
    for case, (mp, solver, system, fixed) in enumerate(
            ((MAP1, _SOLVER1, SYS1, CASE1_FIXED), (MAP2, _SOLVER2, SYS2, CASE2_FIXED),
             (_MAP3, None, _SYS3, _CASE3_FIXED)), start=1):
        coef = mp @ g
        if solver is not None:
            roots, sinfo = solver.solve(coef)
            info[f"case{case}_rank_gap"] = sinfo["rank_gap"]
        else:
            c3 = coef[0]  # coefficients of (1, d, d^2, d^3)
            if abs(c3[3]) <= 1e-12 * np.abs(c3).max():
                roots = np.roots(c3[::-1][np.argmax(np.abs(c3[::-1]) > 0):]).reshape(-1, 1)
            else:
                roots = np.roots(c3[::-1]).reshape(-1, 1)
        x = _real_stationary(system, coef, roots.astype(complex))
        free = np.isnan(fixed)
        q = np.tile(fixed, (len(x), 1))
        q[:, free] = x
        if len(x):
            H = system.jacobian(coef, x)
            ev = np.linalg.eigvalsh(0.5 * (H + np.swapaxes(H, 1, 2)))
            minima.append(ev[:, 0] >= -1e-9 * np.abs(ev).max(axis=1))
        qs.append(q)
        cases += [case] * len(x)
        info[f"case{case}_n_stationary"] = len(x)
    qs.append(np.array([[0.0, 0.0, 0.0, 1.0]]))
    cases.append(4)
    minima.append(np.array([True]))
    q = np.concatenate(qs)
    mu = mu_of(q)
    cost = np.einsum("pi,ij,pj->p", mu, M, mu)
    return {"q": q, "case": np.array(cases), "cost": cost, "minimum": np.concatenate(minima),
            "M": M, "K": K, "info": info}


def aspnp_candidates(P: np.ndarray, m: np.ndarray):
    """Every real stationary point of the four cases as a pose ``(R, t)`` (mm), plus info."""
    Pn, c, s = normalise_object(np.asarray(P, float))
    sp = stationary_points(Pn, m)
    q = sp["q"]
    n2 = np.sum(q ** 2, axis=1)
    R = rbar(q) / n2[:, None, None]
    tau = -(mu_of(q) @ sp["K"].T)
    t = s * tau / n2[:, None] - R @ c
    info = dict(sp["info"])
    info["n_stationary"] = len(q)
    info["n_minima_case1"] = int(np.sum(sp["minimum"] & (sp["case"] == 1)))
    return [(R[i], t[i]) for i in range(len(q))], info


def _candidates(P: np.ndarray, m: np.ndarray) -> list[Candidate]:
    return aspnp_candidates(P, m)


solve = make_solver("aspnp", _candidates, min_points=4)


class ASPnP(CorrespondenceMethod):
    name = "aspnp"
    description = "ASPnP (Zheng et al. 2013)"
    solve = staticmethod(solve)
