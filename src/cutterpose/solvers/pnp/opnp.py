"""OPnP: the optimal PnP solver over a non-unit quaternion (Zheng, Kuang, Sugimoto, Astrom,
Okutomi, *Revisiting the PnP problem: a fast, general and optimal solution*, ICCV 2013).

Convention:
    Object points ``P`` (n, 3) in mm, image points ``m`` (n, 2) normalised (``K^-1`` ideal
    pixels); ``X = R P + t`` (camera frame, mm). ``P`` is centred and divided by its RMS radius
    ``s`` first (notes 5.5), ``P' = (P - c)/s``; a pose ``(R, t')`` of ``P'`` is
    ``t = s t' - R c``. Quaternions ``q = (a, b, c, d)``, ``a`` scalar.

Method (the PnP notes, section 5; equations of the ICCV paper, section 3):

* With centred points the mean depth is ``zbar = t'_3``; write ``q = s_unit / sqrt(zbar)``, so
  ``Rbar(q) = R / zbar`` and ``|q|^2 = 1/zbar`` (no scale freedom, only ``q ~ -q``).
* Dividing ``u_i z_i - x_i = 0`` by ``zbar`` gives residuals linear in ``w = (1, mu(q))``::

      rho_x,i = N_x,i . w - tau_1,   N_x,i = (u_i, u_i l_3(P'_i) - l_1(P'_i)),
      rho_y,i = N_y,i . w - tau_2,   N_y,i = (v_i, v_i l_3(P'_i) - l_2(P'_i)),

  with ``tau = (t'_1, t'_2)/zbar`` eliminated by its optimum ``tau = S w / n``,
  ``S = sum_i N_i``: the cost is ``f(q) = w^T G w``, ``G = sum_i N_i^T N_i - S^T S / n``
  (``f = sum_i (z_i/zbar)^2 |e_i|^2``), an unconstrained quartic with only even terms.
* ``grad f = 0`` is 4 odd cubics with 81 complex solutions: ``q = 0`` and 40 pairs ``+-q``.
  The authors use a symmetric Groebner-basis solver (Ask, Kuang, Astrom, ICPR 2012); here the
  Macaulay null-space solver of :mod:`cutterpose.solvers.pnp.polysolve` on the odd monomials
  (degree 9: 520 x 420 Macaulay matrix, nullity 40, notes 6.4.6) returns all 40 pairs, the
  real ones are polished by Newton's method on ``grad f``.
* Candidates are the real local minima (Hessian positive semidefinite up to a relative
  ``1e-6``, as the reference's Hessian test made relative, notes 5.5); pose
  ``R = R(q/|q|)``, ``zbar = 1/|q|^2``, ``t' = zbar (tau_1, tau_2, 1)``. The common wrapper
  then picks the least reprojection error (the paper picks the least ``f``; both agree except
  in near-ties, which the ambiguity ratio reports).
"""

from __future__ import annotations

import numpy as np

from ..method import CorrespondenceMethod
from .aspnp import MU_EXPS, l_matrices, mu_of, normalise_object, rbar
from .base import Candidate, make_solver
from .polysolve import MacaulaySolver, PolySystem, monomials, quadratic_form_gradient_map

__all__ = ["OPnP", "solve", "opnp_candidates", "stationary_points", "cost_matrix", "cost"]

_W_EXPS = np.vstack([np.zeros((1, 4), np.int64), MU_EXPS])  # w = (1, mu)
_SUPPORT = monomials(4, 3, "odd")  # the 4 linear and 20 cubic monomials
_GRAD_MAP = quadratic_form_gradient_map(_W_EXPS, np.full(4, np.nan), _SUPPORT)  # (4, 24, 121)
_SOLVER = MacaulaySolver(_SUPPORT, degree=9, n_solutions=40, odd=True)
SYSTEM = PolySystem(_SUPPORT)

#: reality test on a computed root, relative to its size
IMAG_TOL = 1e-6
#: a polished root is accepted when |grad f| <= this times the gradient's coefficient scale
GRAD_TOL = 1e-8
#: a stationary point is a minimum when lambda_min(Hessian) >= -this * |lambda|_max
HESS_TOL = 1e-6


def cost_matrix(Pn: np.ndarray, m: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """``G`` (11, 11) of ``f(q) = w^T G w`` and ``S/n`` (2, 11) with ``tau = (S/n) w``, for
    centred, scaled object points ``Pn``."""
    Lk = l_matrices(Pn)
    u, v = m[:, :1], m[:, 1:]
    Nx = np.hstack([u, u * Lk[2] - Lk[0]])
    Ny = np.hstack([v, v * Lk[2] - Lk[1]])
    S = np.vstack([Nx.mean(axis=0), Ny.mean(axis=0)])
    n = len(Pn)
    G = Nx.T @ Nx + Ny.T @ Ny - n * (S.T @ S)
    return 0.5 * (G + G.T), S


def cost(G: np.ndarray, q: np.ndarray) -> np.ndarray:
    """``f(q) = w(q)^T G w(q)`` for quaternions ``q`` ``(..., 4)``."""
    q = np.asarray(q, float)
    w = np.concatenate([np.ones(q.shape[:-1] + (1,)), mu_of(q)], axis=-1)
    return np.einsum("...i,ij,...j->...", w, G, w)


def gradient_coefficients(G: np.ndarray) -> np.ndarray:
    """Coefficients ``(4, 24)`` of ``grad f`` over the odd monomials of degree <= 3."""
    return _GRAD_MAP @ G.ravel()


def stationary_points(Pn: np.ndarray, m: np.ndarray) -> dict:
    """All real non-zero stationary points of ``f`` (one per pair ``+-q``).

    Returns a dict with ``q`` (p, 4), ``cost`` (p,), ``minimum`` (p,) (Hessian test), ``G``,
    ``S`` and diagnostics ``info``.
    """
    G, S = cost_matrix(Pn, m)
    coef = gradient_coefficients(G)
    roots, sinfo = _SOLVER.solve(coef)
    ok = np.all(np.isfinite(roots), axis=1)
    size = np.linalg.norm(roots, axis=1)
    ok &= size > 0
    ok[ok] &= np.abs(roots[ok].imag).max(axis=1) <= IMAG_TOL * size[ok]
    q = SYSTEM.newton_polish(coef, roots[ok].real)
    nq = np.linalg.norm(q, axis=1)
    scale = np.abs(coef).sum(axis=1).max() * (nq + nq ** 3)
    q = q[(nq > 0) & (np.linalg.norm(SYSTEM.evaluate(coef, q), axis=1) <= GRAD_TOL * scale)]
    # one representative per pair +-q, duplicates (a root read twice) removed
    q = q * np.where(q[np.arange(len(q)), np.argmax(np.abs(q), axis=1)] < 0, -1.0, 1.0)[:, None]
    keep = []
    for i, qi in enumerate(q):
        if all(np.linalg.norm(qi - q[j]) > 1e-9 * np.linalg.norm(qi) for j in keep):
            keep.append(i)
    q = q[keep]
    if len(q):
        H = SYSTEM.jacobian(coef, q)
        ev = np.linalg.eigvalsh(0.5 * (H + np.swapaxes(H, 1, 2)))
        minimum = ev[:, 0] >= -HESS_TOL * np.abs(ev).max(axis=1)
    else:
        minimum = np.zeros(0, bool)
    info = {"rank_gap": sinfo["rank_gap"], "n_stationary": len(q),
            "n_minima": int(minimum.sum())}
    return {"q": q, "cost": cost(G, q), "minimum": minimum, "G": G, "S": S, "info": info}


def opnp_candidates(P: np.ndarray, m: np.ndarray):
    """The real local minima of ``f`` as poses ``(R, t)`` (mm), plus info."""
    Pn, c, s = normalise_object(np.asarray(P, float))
    sp = stationary_points(Pn, m)
    q = sp["q"][sp["minimum"]]
    n2 = np.sum(q ** 2, axis=1)
    R = rbar(q) / n2[:, None, None]
    w = np.concatenate([np.ones((len(q), 1)), mu_of(q)], axis=1)
    tau = w @ sp["S"].T  # (p, 2) = (t'_1, t'_2) / zbar
    t_n = np.column_stack([tau, np.ones(len(q))]) / n2[:, None]
    t = s * t_n - R @ c
    return [(R[i], t[i]) for i in range(len(q))], dict(sp["info"])


def _candidates(P: np.ndarray, m: np.ndarray) -> list[Candidate]:
    return opnp_candidates(P, m)


solve = make_solver("opnp", _candidates, min_points=4)


class OPnP(CorrespondenceMethod):
    name = "opnp"
    description = "OPnP (Zheng et al. 2013)"
    solve = staticmethod(solve)
