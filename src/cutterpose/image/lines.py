"""Lines in ideal pixels and their robust fits (the field chain's line step, issue 10): a
total-least-squares line, least median of squares (LMedS) from seeded point pairs, and Tukey
biweight IRLS with a MAD scale, one line at a time or many batched (issue 13).

Convention:
    Lines are homogeneous ``(a, b, c)`` with ``a u + b v + c = 0`` and ``(a, b)`` a unit normal,
    in ideal (undistorted) pixels; see :mod:`cutterpose.image.features`.

References:
    P. J. Rousseeuw, "Least median of squares regression", JASA 79, 1984; J. W. Tukey's
    biweight (Beaton & Tukey, Technometrics 16, 1974).
"""

from __future__ import annotations

import threading

import numpy as np

__all__ = ["fit_line", "line_from", "intersect_consecutive", "TUKEY_C", "MAD_TO_SIGMA",
           "tukey_weights", "mad_scale", "lmeds_line", "lmeds_lines", "tukey_line",
           "tukey_lines", "median_rows"]


def fit_line(p: np.ndarray, w: np.ndarray | None = None):
    """Total least squares line: centroid, unit direction, unit normal."""
    if w is None:
        c = p.mean(axis=0)
        q = p - c
        C = q.T @ q
    else:
        c = (w[:, None] * p).sum(axis=0) / w.sum()
        q = p - c
        C = (w[:, None] * q).T @ q
    evals, evecs = np.linalg.eigh(C)
    d = evecs[:, 1]
    n = evecs[:, 0]
    return c, d, n


# ------------------------------------------------------------------------------------------
# lines and corners
def line_from(c, n) -> np.ndarray:
    return np.array([n[0], n[1], -(n @ c)])


def intersect_consecutive(lines: np.ndarray) -> np.ndarray:
    """Corner k = intersection of lines k and k + 1 (cyclic), as (N, 2) points."""
    L = np.asarray(lines, float)
    X = np.cross(L, np.roll(L, -1, axis=0))
    with np.errstate(divide="ignore", invalid="ignore"):
        return X[:, :2] / X[:, 2:3]


# ------------------------------------------------------------------------------------------
# robust line estimation for the field chain (issue 10)
TUKEY_C = 4.685   #: Tukey's biweight constant: 95 % efficiency under Gaussian residuals
MAD_TO_SIGMA = 1.4826


def tukey_weights(r: np.ndarray, scale: float) -> np.ndarray:
    """Tukey biweight ``(1 - (r / c)^2)^2`` for ``|r| < c = 4.685 scale``, else 0 (a
    redescending M-estimator: points far off the line get no weight at all)."""
    u = np.asarray(r, float) / (TUKEY_C * max(scale, 1e-12))
    return np.where(np.abs(u) < 1.0, (1.0 - u * u) ** 2, 0.0)


def mad_scale(r: np.ndarray, floor: float = 0.0) -> float:
    """Robust standard deviation of residuals about a fitted line: ``1.4826 median |r|``."""
    return max(MAD_TO_SIGMA * float(np.median(np.abs(r))), floor)


def median_rows(a: np.ndarray) -> np.ndarray:
    """Median of each row of ``a`` (2-D), as ``np.median(a, axis=1)`` (the mean of the two
    middle values for an even count) with one partition and no checks."""
    m = a.shape[1]
    lo, hi = (m - 1) // 2, m // 2
    part = np.partition(a, [lo] if lo == hi else [lo, hi], axis=1)
    return 0.5 * (part[:, lo] + part[:, hi])


_GENERATORS = threading.local()


def _seeded_pairs(seed: int, n: int, hypotheses: int) -> np.ndarray:
    """(2, hypotheses) point indices below ``n``: what ``np.random.default_rng(seed)`` draws
    first, as two ``integers(0, n, hypotheses)`` calls. The seeded generator's state is kept
    per seed (per thread) and restored: seeding costs twice the draws (issue 13)."""
    cache = getattr(_GENERATORS, "by_seed", None)
    if cache is None:
        cache = _GENERATORS.by_seed = {}
    hit = cache.get(seed)
    if hit is None:
        if len(cache) >= 256:   # callers use a few seeds (the edges' indices); stay small
            cache.clear()
        rng = np.random.default_rng(seed)
        hit = cache[seed] = (rng, rng.bit_generator.state)
    rng, state = hit
    rng.bit_generator.state = state
    return rng.integers(0, n, (2, hypotheses))


def lmeds_line(p: np.ndarray, hypotheses: int = 64, prior: np.ndarray | None = None,
               seed: int = 0, gate_points: np.ndarray | None = None, gate_px: float = np.inf,
               subsample: int = 256, top: int = 4):
    """Least-median-of-squares line through points ``p`` (n, 2): among lines through random
    pairs of points (and ``prior``, a homogeneous line, if given) the one whose median squared
    residual is smallest. Robust to just under 50 % outliers with no threshold (Rousseeuw
    1984). With ``gate_points`` only hypotheses passing within ``gate_px`` of all of them are
    admitted (the ends of the predicted edge: a line must stay near the outline fit). Returns
    the line and its LMedS scale ``1.4826 (1 + 5 / (n - 2)) sqrt(med r^2)``.

    More than ``2 subsample`` points: the hypotheses are ranked on about ``subsample``
    evenly spread points and the ``top`` best scored on all (speed, issue 13)."""
    L, s = lmeds_lines([p], hypotheses, None if prior is None else [prior], [seed],
                       None if gate_points is None else [gate_points], gate_px, subsample, top)
    return L[0], float(s[0])


def lmeds_lines(points: list, hypotheses: int = 64, priors=None, seeds=None,
                gate_points=None, gate_px: float = np.inf, subsample: int = 256,
                top: int = 4):
    """:func:`lmeds_line` for several point sets (issue 13): the same random pairs (one
    generator per set, seeded by ``seeds[e]``), the hypotheses of all sets built and gated in
    one go, then scored per set; each set gets what :func:`lmeds_line` gives it. ``priors``
    (E, 3) and ``gate_points`` (E, m, 2): per set, or None. Returns lines (E, 3), scales."""
    E = len(points)
    counts = np.array([len(p) for p in points], int)
    first = np.cumsum(counts) - counts
    P = np.concatenate([np.asarray(p, float).reshape(-1, 2) for p in points])
    seeds = range(E) if seeds is None else seeds
    draws = [_seeded_pairs(seed, counts[e], hypotheses) + first[e]
             for e, seed in enumerate(seeds)]
    i = np.concatenate([d[0] for d in draws])
    j = np.concatenate([d[1] for d in draws])
    lab = np.repeat(np.arange(E), hypotheses)
    keep = i != j
    a, b, lab = P[i[keep]], P[j[keep]], lab[keep]
    d = b - a
    nrm = np.column_stack([-d[:, 1], d[:, 0]])
    ln = np.linalg.norm(nrm, axis=1)
    ok = ln > 1e-9
    nrm = nrm[ok] / ln[ok, None]
    L = np.column_stack([nrm, -(nrm * a[ok]).sum(axis=1)])
    lab = lab[ok]
    if priors is not None:  # each set's prior first among its hypotheses (ties keep it)
        L = np.vstack([np.asarray(priors, float).reshape(E, 3), L])
        lab = np.concatenate([np.arange(E), lab])
        order = np.argsort(lab, kind="stable")
        L, lab = L[order], lab[order]
    if gate_points is not None:
        G = np.asarray(gate_points, float)[lab]                     # (H, m, 2)
        dist = np.abs(G[:, :, 0] * L[:, None, 0] + G[:, :, 1] * L[:, None, 1] + L[:, None, 2])
        passed = dist.max(axis=1) <= gate_px
        L, lab = L[passed], lab[passed]
    bounds = np.searchsorted(lab, np.arange(E + 1))

    def med_r2(L, q):  # squared residuals, one row per hypothesis (a fast partition)
        return median_rows((L[:, 0:1] * q[:, 0] + L[:, 1:2] * q[:, 1] + L[:, 2:3]) ** 2)

    out_L, out_s = np.zeros((E, 3)), np.zeros(E)
    for e in range(E):
        p, n = P[first[e]: first[e] + counts[e]], counts[e]
        Le = L[bounds[e]: bounds[e + 1]]
        if len(Le) == 0:
            c, _, nn = fit_line(p)
            out_L[e], out_s[e] = line_from(c, nn), np.inf
            continue
        if n > 2 * subsample and len(Le) > top:
            # speed (issue 13): rank the hypotheses on every m-th point, then the best few
            # on all points (a long edge has ~1000: the ranking costs a quarter, the result
            # the same but where near-equal hypotheses swap places)
            best = np.argsort(med_r2(Le, p[:: -(-n // subsample)]), kind="stable")[:top]
            Le = Le[np.sort(best)]
        med = med_r2(Le, p)
        k = int(np.argmin(med))
        out_L[e] = Le[k]
        out_s[e] = MAD_TO_SIGMA * (1 + 5 / max(n - 2, 1)) * float(np.sqrt(med[k]))
    return out_L, out_s


def tukey_line(p: np.ndarray, line0: np.ndarray, scale0: float, floor_px: float = 0.02,
               iterations: int = 20):
    """IRLS total least squares line with Tukey weights from ``line0`` (a robust start); the
    scale is re-estimated from the weighted points' residuals each step (MAD of the current
    inliers, never above the previous scale). Returns line, scale and the final weights."""
    L = np.asarray(line0, float)
    s = max(float(scale0), floor_px)
    w = tukey_weights(p @ L[:2] + L[2], s)
    for _ in range(iterations):
        if np.count_nonzero(w) < 3:
            break
        c, _, nn = fit_line(p, w)
        if nn @ L[:2] < 0:
            nn = -nn
        L1 = line_from(c, nn)
        r = p @ L1[:2] + L1[2]
        s = min(s, mad_scale(r[w > 0], floor_px))
        w = tukey_weights(r, s)
        moved = abs(L1[2] - L[2]) + float(np.linalg.norm(L1[:2] - L[:2])) * 1e3
        L = L1
        if moved < 1e-4:
            break
    return L, s, w


def tukey_lines(points: list, lines0: np.ndarray, scales0: np.ndarray, floor_px: float = 0.02,
                iterations: int = 20):
    """:func:`tukey_line` for several lines at once (issue 13): all points in one flat array
    with a line label, every IRLS step of all lines in a few array operations (per-line sums
    by ``np.bincount``, the weighted TLS normal in closed form, the per-line MAD from one
    sort); each line stops on its own convergence test, so each gets what
    :func:`tukey_line` gives it (to rounding).

    Returns
    -------
    lines : (E, 3); scales : (E,); weights : per line, the final weights of its points.
    """
    E = len(points)
    counts = np.array([len(p) for p in points], int)
    L = np.array(lines0, float).reshape(E, 3)
    s = np.maximum(np.asarray(scales0, float), floor_px)
    if E == 0 or counts.sum() == 0:
        return L, s, [np.zeros(0) for _ in range(E)]
    P = np.concatenate([np.asarray(p, float).reshape(-1, 2) for p in points])
    lab_all = np.repeat(np.arange(E), counts)
    stop = np.cumsum(counts)
    start = stop - counts
    lines_e = np.arange(E)

    def weights(r, sa):
        u = r / (TUKEY_C * np.maximum(sa, 1e-12))
        return np.where(np.abs(u) < 1.0, (1.0 - u * u) ** 2, 0.0)

    w_all = weights(P[:, 0] * L[lab_all, 0] + P[:, 1] * L[lab_all, 1] + L[lab_all, 2],
                    s[lab_all])
    active = np.bincount(lab_all, w_all > 0, E) >= 3
    # the points of the lines still iterating (compacted as lines converge)
    sel = np.nonzero(active[lab_all])[0]
    changed = True
    for _ in range(iterations):
        if not active.any():
            break
        if changed:
            x, y, lab = P[sel, 0], P[sel, 1], lab_all[sel]
            n_e = np.bincount(lab, minlength=E)
            first = np.cumsum(n_e) - n_e
            block = 1e4 * lab
        w = w_all[sel]
        sw = np.where(active, np.bincount(lab, w, E), 1.0)
        cx, cy = np.bincount(lab, w * x, E) / sw, np.bincount(lab, w * y, E) / sw
        qx, qy = x - cx[lab], y - cy[lab]
        sxx = np.bincount(lab, w * qx * qx, E)
        sxy = np.bincount(lab, w * qx * qy, E)
        syy = np.bincount(lab, w * qy * qy, E)
        # the weighted scatter's major axis is the line direction; its normal (-sin, cos)
        th = 0.5 * np.arctan2(2.0 * sxy, sxx - syy)
        nx, ny = -np.sin(th), np.cos(th)
        flip = nx * L[:, 0] + ny * L[:, 1] < 0
        nx, ny = np.where(flip, -nx, nx), np.where(flip, -ny, ny)
        c = -(nx * cx + ny * cy)
        r = x * nx[lab] + y * ny[lab] + c[lab]
        # MAD of the previous step's inliers, per line: one sort of keys offset per line
        # (the residuals of edge points are a few px, << 5e3: each line's values stay in
        # their own block, and the offset costs < 1e-10 px of precision)
        inl = w > 0
        k = np.bincount(lab, inl, E).astype(int)
        srt = np.sort(block + np.where(inl, np.minimum(np.abs(r), 5e3), 5e3))
        last = max(len(srt) - 1, 0)
        lo = np.minimum(first + np.maximum(k - 1, 0) // 2, last)
        hi = np.minimum(first + k // 2, last)
        med = 0.5 * ((srt[lo] - 1e4 * lines_e) + (srt[hi] - 1e4 * lines_e))
        s_new = np.where(active, np.minimum(s, np.maximum(MAD_TO_SIGMA * med, floor_px)), s)
        w = weights(r, s_new[lab])
        w_all[sel] = w
        moved = (np.abs(c - L[:, 2]) + np.hypot(nx - L[:, 0], ny - L[:, 1]) * 1e3)
        L = np.where(active[:, None], np.column_stack([nx, ny, c]), L)
        s = s_new
        was = active
        active = active & ~(moved < 1e-4) & (np.bincount(lab, w > 0, E) >= 3)
        changed = not np.array_equal(active, was)
        if changed:
            sel = sel[active[lab]]
    return L, s, [w_all[a:b] for a, b in zip(start, stop)]
