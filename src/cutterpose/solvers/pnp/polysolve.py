"""All solutions of a square polynomial system: Macaulay matrix, null space, shift eigenproblem.

The Groebner-free solver of the PnP notes (``shared/notes/pnp-algorithms.md``, section 6.4),
shared by :mod:`cutterpose.solvers.pnp.aspnp` and :mod:`cutterpose.solvers.pnp.opnp`.

For a system ``g_1 = ... = g_k = 0`` in ``k`` variables with finitely many solutions and none at
infinity:

1. **Macaulay matrix** ``M``: one row per product ``x^alpha g_j`` (all multipliers with
   ``deg(x^alpha g_j) <= d``), one column per monomial of degree ``<= d``. Every solution ``x*``
   gives a null vector ``v(x*) = (x*^beta)_beta`` of ``M``. For ``d`` at or above the regularity
   of the system (``d >= sum_j (deg g_j - 1) + 1``, the Macaulay bound) the null space has
   dimension exactly the number ``N`` of solutions (counted with multiplicity) and is spanned by
   the ``v(x*)``: ``Z = V D`` with ``V = [v(x*_1) ... v(x*_N)]`` and ``D`` invertible.
2. **Basis monomials** ``B``: ``N`` low-degree monomials whose rows ``Z[B]`` are well conditioned,
   chosen by column-pivoted QR of ``Z[B_candidates]^T``.
3. **Shift**: for a random form ``h`` (linear, or quadratic for odd systems),
   ``Z[hB] = V[B] diag(h(x*)) D``, so ``T = Z[B]^-1 Z[hB] = D^-1 diag(h(x*)) D``: the
   eigenvalues of ``T`` are ``h(x*_j)`` and ``Z v_j`` is proportional to ``v(x*_j)``.
4. **Read-off**: the variables are ratios of entries of ``Z v_j``, taken at the basis monomial
   with the largest entry (best relative precision).

*Odd systems* (every ``g_j`` has only odd-degree terms, as the OPnP gradient): then ``x*`` and
``-x*`` are both solutions and ``0`` is one. Only even multipliers and odd columns are used; the
null space has one dimension per pair ``+-x*`` (``0`` gives the zero vector), the shift is a
quadratic form and the read-off goes through the products ``x_k x_l`` (notes 6.4.6).

Everything is exact algebra; the only tolerances are the rank decision (taken as the expected
solution count, with the singular-value gap reported) and the caller's reality test. Roots are
meant to be polished afterwards with :meth:`PolySystem.newton_polish`.

References
----------
Macaulay, *The algebraic theory of modular systems*, 1916. Dreesen, Batselier, De Moor,
*Back to the roots: polynomial system solving, linear algebra, systems theory*, IFAC 2012.
Stetter, *Numerical polynomial algebra*, SIAM 2004 (the eigenvalue/eigenvector theorem).
"""

from __future__ import annotations

import itertools
from dataclasses import dataclass

import numpy as np
import scipy.linalg as sla

__all__ = ["monomials", "PolySystem", "MacaulaySolver", "quadratic_form_gradient_map"]


def monomials(n_vars: int, max_degree: int, parity: str | None = None) -> np.ndarray:
    """Exponent vectors of all monomials of degree ``<= max_degree``, by degree then lexicographic.

    ``parity`` = ``"odd"`` or ``"even"`` keeps only those degrees.
    """
    out = []
    for deg in range(max_degree + 1):
        if parity == "odd" and deg % 2 == 0 or parity == "even" and deg % 2 == 1:
            continue
        for combo in itertools.combinations_with_replacement(range(n_vars), deg):
            e = np.zeros(n_vars, dtype=np.int64)
            for v in combo:
                e[v] += 1
            out.append(e)
    out.sort(key=lambda e: (e.sum(), tuple(-e)))
    return np.array(out, dtype=np.int64).reshape(-1, n_vars)


def _index(exps: np.ndarray) -> dict[tuple, int]:
    return {tuple(e): i for i, e in enumerate(exps)}


def quadratic_form_gradient_map(w_exps: np.ndarray, fixed: np.ndarray,
                                support: np.ndarray) -> np.ndarray:
    """Linear map from a symmetric matrix ``G`` to the gradient of ``f(x) = w(x)^T G w(x)``.

    ``w(x)`` is a vector of monomials (exponents ``w_exps``, shape ``(m, n)``); some variables
    may be fixed to constants (``fixed[v]`` finite) and the rest are free (``fixed[v]`` NaN).
    Returns ``C`` of shape ``(n_free, len(support), m*m)`` with
    ``d f / d x_free[k] = sum_s (C[k] @ G.ravel())[s] x_free^support[s]``.
    Built once at import time; the solvers only do the matrix product.
    """
    free = np.flatnonzero(np.isnan(fixed))
    fixed_vars = np.flatnonzero(~np.isnan(fixed))
    sidx = _index(support)
    m = len(w_exps)
    C = np.zeros((len(free), len(support), m * m))
    for i in range(m):
        for j in range(m):
            e = w_exps[i] + w_exps[j]
            factor = float(np.prod([fixed[v] ** e[v] for v in fixed_vars]))
            if factor == 0.0:
                continue
            ef = e[free]
            for k in range(len(free)):
                if ef[k] == 0:
                    continue
                g = ef.copy()
                g[k] -= 1
                C[k, sidx[tuple(g)], i * m + j] += factor * ef[k]
    return C


@dataclass
class PolySystem:
    """``k`` polynomials in ``k`` variables with a fixed support ``exps`` (``(s, k)``) each;
    coefficients ``(k, s)`` are given per call. Vectorised evaluation, Jacobian and Newton."""

    exps: np.ndarray

    def __post_init__(self):
        self.exps = np.asarray(self.exps, dtype=np.int64)
        k = self.exps.shape[1]
        # d x^e / d x_v = e_v x^(e - delta_v): exponents clipped at 0 where e_v = 0 (factor 0)
        self._dexps = np.maximum(self.exps[None, :, :] - np.eye(k, dtype=np.int64)[:, None, :], 0)
        self._dfac = self.exps.T.astype(float)  # (k, s)

    def _mono(self, x, exps):
        # x (p, k), exps (..., s, k) -> (p, ..., s)
        return np.prod(x[:, None, None, :] ** exps[None], axis=-1) if exps.ndim == 3 else \
            np.prod(x[:, None, :] ** exps[None], axis=-1)

    def evaluate(self, coef: np.ndarray, x: np.ndarray) -> np.ndarray:
        """Values ``(p, k)`` at points ``x`` ``(p, k)``."""
        return self._mono(x, self.exps) @ coef.T

    def jacobian(self, coef: np.ndarray, x: np.ndarray) -> np.ndarray:
        """Jacobians ``(p, k_eq, k_var)`` at points ``x``."""
        dm = self._mono(x, self._dexps) * self._dfac[None]  # (p, k_var, s)
        return np.einsum("es,pvs->pev", coef, dm)

    def newton_polish(self, coef: np.ndarray, x: np.ndarray, iterations: int = 4) -> np.ndarray:
        """A few Newton steps on ``g(x) = 0`` from each root; a step is kept only where it
        lowers ``|g|`` (so a polished root never moves away)."""
        x = np.array(x, dtype=float)
        r = np.linalg.norm(self.evaluate(coef, x), axis=1)
        for _ in range(iterations):
            J = self.jacobian(coef, x)
            g = self.evaluate(coef, x)
            ok = np.abs(np.linalg.det(J)) > 0
            step = np.zeros_like(x)
            if ok.any():
                step[ok] = np.linalg.solve(J[ok], g[ok][..., None])[..., 0]
            x_new = x - step
            r_new = np.linalg.norm(self.evaluate(coef, x_new), axis=1)
            better = r_new < r
            x[better] = x_new[better]
            r[better] = r_new[better]
        return x


class MacaulaySolver:
    """Precomputed Macaulay structure for one family of systems (one support, one degree).

    Parameters
    ----------
    support : (s, k) exponents shared by all ``k`` equations.
    degree : Macaulay degree ``d`` (columns: monomials of degree ``<= d``).
    n_solutions : expected null-space dimension (solution count, pairs for odd systems).
    odd : the system is odd (``g(-x) = -g(x)``): even multipliers, odd columns, quadratic shift.
    seed : seed of the random shift form (fixed, so results are reproducible).

    Convention:
        The row/column index maps are built once here; :meth:`solve` only scatters the
        coefficients into them, so a solve is a few dense LAPACK calls.
    """

    def __init__(self, support: np.ndarray, degree: int, n_solutions: int, odd: bool = False,
                 seed: int = 20130101):
        support = np.asarray(support, dtype=np.int64)
        k = support.shape[1]
        deg_eq = int(support.sum(axis=1).max())
        self.k, self.degree, self.n_solutions, self.odd = k, degree, n_solutions, odd
        self.support = support
        self.cols = monomials(k, degree, "odd" if odd else None)
        cidx = _index(self.cols)
        mult = monomials(k, degree - deg_eq, "even" if odd else None)
        n_mult, s = len(mult), len(support)
        self.shape = (k * n_mult, len(self.cols))
        # row j*n_mult + a holds x^mult[a] * g_j; term t of g_j lands in column mult[a]+support[t]
        prod_cols = np.array([[cidx[tuple(a + t)] for t in support] for a in mult])  # (n_mult, s)
        self._rows = np.repeat(np.arange(k * n_mult), s)
        self._cols = np.tile(prod_cols, (k, 1)).ravel()
        self._src = (np.arange(k)[:, None, None] * s + np.zeros((1, n_mult, 1), np.int64)
                     + np.arange(s)[None, None, :]).ravel()
        # basis candidates and their shifts
        shift_deg = 2 if odd else 1
        deg_cols = self.cols.sum(axis=1)
        cand = np.flatnonzero(deg_cols <= degree - shift_deg)
        if odd:
            pairs = [(a, b) for a in range(k) for b in range(a, k)]
        else:
            pairs = [(a,) for a in range(k)]
        self._pairs = pairs
        shifts = []
        for c in cand:
            row = []
            for p in pairs:
                e = self.cols[c].copy()
                for v in p:
                    e[v] += 1
                row.append(cidx[tuple(e)])
            shifts.append(row)
        self._cand = cand
        self._shift_cols = np.array(shifts)  # (n_cand, n_pairs)
        rng = np.random.default_rng(seed)
        self._h = rng.uniform(0.5, 1.5, len(pairs)) * rng.choice([-1.0, 1.0], len(pairs))
        # Degree split: only the rows with top-degree multipliers touch the top-degree columns.
        self._top_c = np.flatnonzero(deg_cols == degree)
        self._low_c = np.flatnonzero(deg_cols < degree)
        top_mult = mult.sum(axis=1) == degree - deg_eq
        self._top_r = np.flatnonzero(np.tile(top_mult, k))
        self._low_r = np.flatnonzero(~np.tile(top_mult, k))
        # A generically independent square subset of the top block (one random instance):
        # the top-degree values of a null vector then come from one LU solve.
        M = self.macaulay(rng.standard_normal((k, len(support))))
        _, _, piv = sla.qr(M[np.ix_(self._top_r, self._top_c)].T, pivoting=True,
                           check_finite=False)
        self._top_sel = np.sort(piv[: len(self._top_c)])
        # scatter maps straight into the three blocks (no full matrix on the hot path)
        r_top = np.isin(self._rows, self._top_r)
        c_top = np.isin(self._cols, self._top_c)
        r_loc = np.empty(self.shape[0], np.int64)
        r_loc[self._top_r] = np.arange(len(self._top_r))
        r_loc[self._low_r] = np.arange(len(self._low_r))
        c_loc = np.empty(self.shape[1], np.int64)
        c_loc[self._top_c] = np.arange(len(self._top_c))
        c_loc[self._low_c] = np.arange(len(self._low_c))
        self._blocks = {}
        for name, sel in (("low", ~r_top), ("top_top", r_top & c_top),
                          ("top_low", r_top & ~c_top)):
            self._blocks[name] = (r_loc[self._rows[sel]], c_loc[self._cols[sel]],
                                  self._src[sel])
        self._block_shapes = {"low": (len(self._low_r), len(self._low_c)),
                              "top_top": (len(self._top_r), len(self._top_c)),
                              "top_low": (len(self._top_r), len(self._low_c))}

    def _block(self, c_flat: np.ndarray, name: str) -> np.ndarray:
        B = np.zeros(self._block_shapes[name])
        r, col, src = self._blocks[name]
        B[r, col] = c_flat[src]
        return B

    def macaulay(self, coef: np.ndarray) -> np.ndarray:
        """The Macaulay matrix for coefficients ``(k, s)`` (each row scaled to unit norm)."""
        c = coef / np.linalg.norm(coef, axis=1, keepdims=True)
        M = np.zeros(self.shape)
        M[self._rows, self._cols] = c.ravel()[self._src]
        return M

    def solve(self, coef: np.ndarray) -> tuple[np.ndarray, dict]:
        """All solutions (complex, ``(N, k)``; one per pair for odd systems) and diagnostics.

        The null space is computed in two steps. The rows of degree ``< d`` form the Macaulay
        matrix of degree ``d - 1``; at or above the regularity its nullity is already ``N``
        (Hilbert function of a complete intersection without solutions at infinity), so its
        null space gives the lower-degree entries ``z_low``. The top-degree entries follow
        from the top rows, ``M_top,top z_top = -M_top,low z_low`` (full column rank when
        there are no solutions at infinity). This is the null space of the whole matrix, at a
        fraction of the cost of one decomposition of it.

        ``info['rank_gap']`` is ``|r_(rank+1)| / |r_rank|`` of the pivoted QR of ``M_low^T``
        (small means a clean null space of the expected dimension); ``info['top_residual']``
        the relative residual of the top rows.
        """
        c_flat = (coef / np.linalg.norm(coef, axis=1, keepdims=True)).ravel()
        N = self.n_solutions
        M_low = self._block(c_flat, "low")
        rank = len(self._low_c) - N
        Q, Rm, _ = sla.qr(M_low.T, pivoting=True, mode="full", check_finite=False)
        d = np.abs(np.diag(Rm))
        gap = d[rank] / d[rank - 1] if rank < len(d) else 0.0
        Z = np.zeros((self.shape[1], N))
        Z[self._low_c] = Q[:, rank:]
        if len(self._top_c):
            A = self._block(c_flat, "top_top")
            rhs = -self._block(c_flat, "top_low") @ Z[self._low_c]
            try:
                z_top = sla.lu_solve(sla.lu_factor(A[self._top_sel], check_finite=False),
                                     rhs[self._top_sel], check_finite=False)
                res = np.linalg.norm(A @ z_top - rhs) / max(np.linalg.norm(rhs), 1e-300)
            except (np.linalg.LinAlgError, ValueError):
                res = np.inf
            if not res <= 1e-6:  # the generic row subset is singular here: least squares
                z_top = np.linalg.lstsq(A, rhs, rcond=None)[0]
                res = np.linalg.norm(A @ z_top - rhs) / max(np.linalg.norm(rhs), 1e-300)
            Z[self._top_c] = z_top
        else:
            res = 0.0
        # basis monomials: the N best-conditioned candidate rows
        _, _, piv = sla.qr(Z[self._cand].T, pivoting=True, mode="economic", check_finite=False)
        b = piv[:N]
        ZB = Z[self._cand[b]]
        Zh = np.tensordot(self._h, Z[self._shift_cols[b]], axes=([0], [1]))
        T = np.linalg.solve(ZB, Zh)
        _, vecs = np.linalg.eig(T)
        W = Z @ vecs  # columns proportional to the monomial vectors of the solutions
        x = self._read_off(W, self._cand[b], self._shift_cols[b])
        info = {"rank_gap": float(gap), "top_residual": float(res)}
        return x, info

    def _read_off(self, W: np.ndarray, basis: np.ndarray, shifts: np.ndarray) -> np.ndarray:
        N = W.shape[1]
        j = np.arange(N)
        best = np.argmax(np.abs(W[basis]), axis=0)  # basis monomial with the largest entry
        denom = W[basis[best], j]
        ratios = W[shifts[best], j[:, None]] / denom[:, None]  # (N, n_pairs): h-monomials / beta
        if not self.odd:
            return ratios
        # ratios[:, p] = x_a x_b for pairs p = (a, b): rebuild x from the largest diagonal
        k = self.k
        Xq = np.zeros((N, k, k), dtype=complex)
        for p, (a, b) in enumerate(self._pairs):
            Xq[:, a, b] = Xq[:, b, a] = ratios[:, p]
        diag = np.einsum("nii->ni", Xq)
        piv = np.argmax(np.abs(diag), axis=1)
        xp = np.sqrt(diag[j, piv])
        with np.errstate(divide="ignore", invalid="ignore"):
            return Xq[j, piv, :] / xp[:, None]
