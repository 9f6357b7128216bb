"""What every PnP solver shares: input checks, normalisation, candidate selection, timing.

A solver module implements one function::

    candidates(points_obj_mm: (n, 3), m: (n, 2)) -> list[(R, t_mm)]

on normalised image coordinates ``m = K^-1 ideal_px`` (undistorted), and wraps it with
:func:`make_solver`, which gives it the common signature::

    solve(points_px, camera, model) -> PoseEstimate

``model`` is a :class:`~cutterpose.geometry.holder.Holder` (its 20 corners, in model order) or any
``(n, 3)`` array of object points (non-planar sets included). The wrapper

* rejects bad input with typed errors (shape mismatch, NaN/inf, too few points, collinear points);
* drops candidates that are not finite or put a point behind the camera;
* picks the candidate with the least RMS reprojection error (ideal pixels) and reports the
  ratio best / second-best as ``ambiguity_ratio``;
* returns a falsy :class:`~cutterpose.solvers.estimate.PoseEstimate` with the reason when nothing
is left.
"""

from __future__ import annotations

import math
import time
from collections.abc import Callable

import numpy as np
from scipy.linalg.lapack import dgesdd as _dgesdd
from scipy.linalg.lapack import dsyevr as _dsyevr

from ...errors import DegenerateInputError, InputError
from ...geometry.camera import Camera
from ...geometry.holder import Holder
from ..estimate import PoseEstimate

__all__ = ["model_points", "model_cache", "check_correspondences", "reprojection_rms", "select",
           "make_solver", "is_planar", "plane_frame", "align_rigid", "align_rigid_many",
           "rotation_from_covariance", "det3", "image_weights", "kron_normal", "smallest_eigvecs",
           "svd_small"]

Candidate = tuple[np.ndarray, np.ndarray]


def _as_rows(a, cols: int, what: str) -> np.ndarray:
    """``a`` as an (n, cols) float array, else :class:`InputError` naming ``what``."""
    try:
        x = np.asarray(a, dtype=float)
    except (TypeError, ValueError):
        raise InputError(f"{what} must be an (n, {cols}) array of numbers") from None
    if x.ndim != 2 or x.shape[1] != cols:
        raise InputError(f"{what} must have shape (n, {cols}), got {x.shape}")
    return x


def model_points(model) -> np.ndarray:
    """(n, 3) object points of a holder or of a point array."""
    if isinstance(model, Holder):
        return model.points_holder_mm
    return _as_rows(model, 3, "object points (or a Holder)")


def model_cache(P: np.ndarray) -> dict:
    """Per-model scratch dict for quantities that depend only on the object points (checks,
    planarity, plane frame, control points...), keyed on the array's bytes so that an edited or
    different array never hits a stale entry. Solvers store read-only arrays under their own
    keys. Bounded: cleared when it grows past a few dozen models (random models per trial)."""
    key = (P.shape, P.dtype.str, P.tobytes())
    d = _MODEL_CACHE.get(key)
    if d is None:
        if len(_MODEL_CACHE) >= _MODEL_CACHE_SIZE:
            _MODEL_CACHE.clear()
        d = _MODEL_CACHE[key] = {}
    return d


_MODEL_CACHE: dict = {}
_MODEL_CACHE_SIZE = 64


def as_points_px(points_px) -> np.ndarray:
    """``points_px`` as an (n, 2) float array of finite numbers, else :class:`InputError`."""
    x = _as_rows(points_px, 2, "points_px")
    # a finite sum means finite entries (cheaper than the elementwise test, which runs otherwise)
    if not math.isfinite(x.sum()) and not np.isfinite(x).all():
        raise InputError(f"points_px holds NaN or inf (at point "
                         f"{np.argwhere(~np.isfinite(x))[0, 0]})")
    return x


def check_correspondences(points_px, points_obj, min_points: int) -> tuple[np.ndarray, np.ndarray]:
    """Validate image/object correspondences; return them as float arrays.

    Raises
    ------
    InputError
        Shapes do not match, or values are NaN/inf.
    DegenerateInputError
        Fewer than ``min_points`` points, or all points (image or object) collinear.
    """
    x = as_points_px(points_px)
    P = np.asarray(points_obj, dtype=float)
    if len(x) != len(P):
        raise InputError(f"points_px has {len(x)} points but the model has {len(P)}; they must "
                         "correspond one to one")
    # the object-point checks depend on the model only: a model that passed once passes again
    # (only a pass is remembered, so failures raise in the same order as before)
    cache = model_cache(P) if P.ndim == 2 else {}
    P_ok = cache.get("checked", False)
    if not P_ok and not np.isfinite(P).all():
        raise InputError("object points hold NaN or inf")
    if len(x) < min_points:
        raise DegenerateInputError(f"need at least {min_points} points, got {len(x)}")
    if _collinear(x):
        raise DegenerateInputError("all image points are collinear (or coincide): the pose is not "
                                   "determined")
    if not P_ok:
        if _collinear(P):
            raise DegenerateInputError("all object points are collinear (or coincide): the pose "
                                       "is not determined")
        cache["checked"] = True
    return x, P


def _collinear(a: np.ndarray, tol: float = 1e-9) -> bool:
    """True when the points span at most a line: the second singular value of the centred set is
    below ``tol`` times the first. Uses the covariance's invariants (sum of principal 2x2 minors
    = sum of products of eigenvalue pairs) instead of an SVD: this sits on every solve's path.
    The arithmetic on the 2x2 / 3x3 covariance is on Python floats (cheaper than numpy scalars)."""
    c = a - a.sum(axis=0) / len(a)  # = a.mean(axis=0), cheaper
    C = (c.T @ c).tolist()
    if len(C) == 2:
        tr = C[0][0] + C[1][1]
        pairs = C[0][0] * C[1][1] - C[0][1] ** 2
    else:
        tr = C[0][0] + C[1][1] + C[2][2]
        pairs = (C[0][0] * C[1][1] - C[0][1] ** 2 + C[0][0] * C[2][2] - C[0][2] ** 2
                 + C[1][1] * C[2][2] - C[1][2] ** 2)
    if tr <= 0:
        return True
    # pairs / tr^2 ~ (s2 / s1)^2 when s2 << s1
    return pairs <= (tol**2) * tr * tr


def is_planar(P: np.ndarray, tol: float = 1e-6) -> bool:
    """Singular-value test of the notes (section 6.3): ``s3 / s1 < tol``."""
    s = np.linalg.svd(P - P.mean(axis=0), compute_uv=False)
    return bool(s[2] <= tol * s[0])


def plane_frame(P: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Rotation W and centroid c such that ``W (P - c)`` has zero third coordinate.

    A pose ``(R', t')`` found in the plane frame maps back as ``R = R' W``,
    ``t = t' - R' W c``.
    """
    c = P.mean(axis=0)
    U, _, _ = np.linalg.svd((P - c).T)
    v1, v2 = U[:, 0], U[:, 1]
    W = np.vstack([v1, v2, np.cross(v1, v2)])
    return W, c


def align_rigid(P: np.ndarray, X: np.ndarray) -> Candidate:
    """Least-squares rigid motion ``X ~ R P + t`` (Umeyama/Kabsch with the correct reflection
    rule ``S = diag(1, 1, det U det V)``, the notes' AL-ok; valid for planar sets)."""
    return align_rigid_many(P, np.asarray(X)[None])[0]


def align_rigid_many(P: np.ndarray, Xs: np.ndarray) -> list[Candidate]:
    """:func:`align_rigid` of ``P`` to each of ``Xs`` (k, n, 3) in one batched pass (the
    per-call numpy overhead dominates at these sizes)."""
    if len(Xs) == 1:  # the common case: a dozen fewer numpy calls than the batched path
        return [_align_one(P, Xs[0])]
    # sum / n is what mean computes, without its Python-level overhead
    Pc = P.sum(axis=0) / len(P)
    Xc = Xs.sum(axis=1) / Xs.shape[1]
    S = np.matmul((Xs - Xc[:, None, :]).transpose(0, 2, 1), P - Pc)
    if len(S) <= 3:  # one LAPACK call each beats numpy's batched wrapper at these counts
        USV = [svd_small(Si) for Si in S]
        U, Vt = np.array([u for u, _, _ in USV]), np.array([vt for _, _, vt in USV])
    else:
        U, _, Vt = np.linalg.svd(S)
    R = np.matmul(U, Vt)
    # det U det Vt = det(U Vt): S = diag(1, 1, -1) where it is negative
    flip = np.linalg.det(R) < 0
    if flip.any():
        R[flip] -= 2.0 * U[flip, :, 2:] * Vt[flip, 2:, :]
    t = Xc - R @ Pc
    return list(zip(R, t))


def _align_one(P: np.ndarray, X: np.ndarray) -> Candidate:
    """:func:`align_rigid` of one set, with the model's centred points cached."""
    mc = model_cache(P)
    cent = mc.get("centred")
    if cent is None:
        Pc = P.sum(axis=0) / len(P)
        cent = mc["centred"] = (Pc, P - Pc)
    Pc, Pcent = cent
    Xc = X.sum(axis=0) / len(X)
    R = rotation_from_covariance((X - Xc).T @ Pcent)
    return R, Xc - R @ Pc


def rotation_from_covariance(S: np.ndarray) -> np.ndarray:
    """The rotation of the rigid alignment whose cross-covariance ``sum_i (X_i - Xbar)(P_i -
    Pbar)^T`` is ``S`` (3, 3): ``U diag(1, 1, det(U V^T)) V^T`` from ``S = U D V^T`` (the notes'
    AL-ok rule, valid for planar sets)."""
    U, _, Vt = svd_small(S)
    R = U @ Vt
    if det3(R.tolist()) < 0:  # S = diag(1, 1, -1)
        R -= 2.0 * np.outer(U[:, 2], Vt[2])
    return R


def det3(rows) -> float:
    """Determinant of a 3x3 matrix given as nested lists, on Python floats (np.linalg.det's
    per-call overhead dominates at this size, on every solve's path)."""
    (a, b, c), (d, e, f), (g, h, i) = rows
    return a * (e * i - f * h) - b * (d * i - f * g) + c * (d * h - e * g)


# B_i^T B_i = [[1, 0, -u], [0, 1, -v], [-u, -v, u^2 + v^2]] of a point's two projection rows
# B_i = [[1, 0, -u], [0, 1, -v]], as coefficients of (1, u, v, u^2 + v^2)
_BTB = np.zeros((4, 3, 3))
_BTB[0, 0, 0] = _BTB[0, 1, 1] = 1.0
_BTB[1, 0, 2] = _BTB[1, 2, 0] = -1.0
_BTB[2, 1, 2] = _BTB[2, 2, 1] = -1.0
_BTB[3, 2, 2] = 1.0
_BTB9 = _BTB.reshape(4, 9).T.copy()


def image_weights(m: np.ndarray) -> np.ndarray:
    """(n, 4) weights ``(1, u, v, u^2 + v^2)`` of the points' ``B_i^T B_i`` (see ``_BTB``)."""
    E = np.empty((len(m), 4))
    E[:, 0] = 1.0
    E[:, 1:3] = m
    E[:, 3] = m[:, 0] * m[:, 0] + m[:, 1] * m[:, 1]
    return E


def kron_normal(O: np.ndarray, m: np.ndarray | None, coord_outer: bool,
                E: np.ndarray | None = None) -> np.ndarray:
    """Normal matrix ``A^T A`` of the linear systems whose rows for point i are
    ``kron(B_i, a_i)`` (``coord_outer``, the DLT's layout) or ``kron(a_i, B_i)`` (EPnP's), with
    ``B_i`` as in ``_BTB`` and ``a_i`` a model vector of length d: ``A^T A = sum_i
    kron(B_i^T B_i, a_i a_i^T)``. ``O`` (n, d*d) holds the model's ``a_i a_i^T`` (cache it);
    the image enters through 4 weights per point (``E``, :func:`image_weights` of ``m`` unless
    given), so this is two small matrix products instead of building the 2n-row system."""
    n, dd = O.shape
    d = int(round(dd**0.5))
    if E is None:
        E = image_weights(m)
    T = (_BTB9 @ (E.T @ O)).reshape(3, 3, d, d)  # [a, b, i, j]
    if coord_outer:
        return T.transpose(0, 2, 1, 3).reshape(3 * d, 3 * d)
    return T.transpose(2, 0, 3, 1).reshape(3 * d, 3 * d)


def svd_small(A: np.ndarray, full_matrices: bool = True):
    """``np.linalg.svd(A)`` of one small matrix through LAPACK's dgesdd directly (the routine
    numpy calls), without numpy's per-call overhead (a quarter of its time at 3x3)."""
    u, s, vt, info = _dgesdd(A, compute_uv=1, full_matrices=int(full_matrices))
    if info != 0:
        return np.linalg.svd(A, full_matrices=full_matrices)
    return u, s, vt


def smallest_eigvecs(N: np.ndarray, k: int) -> np.ndarray:
    """Eigenvectors (columns, ascending eigenvalue) of the k least eigenvalues of a symmetric
    matrix: LAPACK dsyevr for just those (a third of np.linalg.eigh's time at 9x9)."""
    w, z, _, _, info = _dsyevr(N, range="I", il=1, iu=k)
    if info != 0:
        return np.linalg.eigh(N)[1][:, :k]
    return z


def reprojection_rms(R, t, P, m) -> float:
    """RMS reprojection error in normalised units (multiply by f for pixels)."""
    X = P @ np.asarray(R).T + np.asarray(t)
    with np.errstate(divide="ignore", invalid="ignore"):
        proj = X[:, :2] / X[:, 2:3]
    return float(np.sqrt(np.mean(np.sum((proj - m) ** 2, axis=1))))


def _dets(Rs: np.ndarray) -> np.ndarray:
    """Determinants of (k, 3, 3) matrices; one candidate (the usual case) on Python floats,
    where np.linalg.det's per-call overhead would dominate."""
    if len(Rs) != 1:
        return np.linalg.det(Rs)
    return np.array([det3(Rs[0].tolist())])


def _select_one(method: str, cand: Candidate, P: np.ndarray, m: np.ndarray,
                f_px: float) -> PoseEstimate | None:
    """:func:`select` of a single admissible candidate (the usual case) with a third of its
    numpy calls; None when ``cand`` is not a finite (3, 3), (3,) float pair with all points in
    front and a proper rotation, which the general path then handles (and reports)."""
    R, t = cand
    if not (type(R) is np.ndarray and type(t) is np.ndarray and R.shape == (3, 3)
            and t.shape == (3,) and R.dtype == np.float64 and t.dtype == np.float64):
        return None
    det = det3(R.tolist())
    # a finite determinant means a finite R (an inf or NaN entry makes it inf or NaN)
    if not (abs(det - 1.0) <= 1e-6 and all(map(math.isfinite, t.tolist()))):
        return None
    X = P @ R.T + t
    z = X[:, 2:]
    if not z.min() > 0:
        return None
    r = X[:, :2] / z - m
    err = math.sqrt(float((r * r).sum()) / len(r))  # RMS over the points
    R, t = R.copy(), t.copy()  # as the general path: the estimate owns its arrays
    return PoseEstimate(method=method, R_cam_holder=R, t_cam_holder_mm=t,
                        residual_px=float(err * f_px), ambiguity_ratio=math.nan,
                        candidates=[(R, t)], info={"n_candidates": 1})


def select(method: str, cands: list[Candidate], P, m, f_px: float) -> PoseEstimate:
    """Pick the candidate with the least reprojection error; see the module docstring."""
    n_raw = len(cands)
    if n_raw == 1:
        est = _select_one(method, cands[0], P, m, f_px)
        if est is not None:
            return est
    if cands:
        try:  # one conversion for the stack (the usual case: all (3, 3) and (3,))
            Rs = np.array([R for R, _ in cands], dtype=float).reshape(n_raw, 3, 3)
            ts = np.array([t for _, t in cands], dtype=float).reshape(n_raw, 3)
        except ValueError:
            Rs = np.array([np.asarray(R, float).reshape(3, 3) for R, _ in cands])
            ts = np.array([np.asarray(t, float).reshape(3) for _, t in cands])
        X = P @ Rs.transpose(0, 2, 1) + ts[:, None, :]
        # a NaN/inf in R or t makes X non-finite, so a finite sum means all are finite (the
        # exact per-candidate test runs only otherwise)
        if not math.isfinite(X.sum()):
            finite = np.isfinite(Rs).all(axis=(1, 2)) & np.isfinite(ts).all(axis=1)
            Rs, ts = Rs[finite], ts[finite]
            X = P @ Rs.transpose(0, 2, 1) + ts[:, None, :]
        ok = (np.abs(_dets(Rs) - 1.0) <= 1e-6) & (X[..., 2].min(axis=1) > 0)
        if not ok.all():
            Rs, ts, X = Rs[ok], ts[ok], X[ok]
    if not cands or len(Rs) == 0:
        reason = ("no candidate pose" if not cands
                  else f"none of {n_raw} candidates is finite with all points in front")
        return PoseEstimate.failure(method, reason, info={"n_candidates": n_raw})
    d = X[..., :2] / X[..., 2:3] - m
    err = np.sqrt(np.sum(d * d, axis=(1, 2)) / d.shape[1])  # RMS over the points
    ratio = np.nan
    if len(err) > 1:
        order = np.argsort(err, kind="stable")
        Rs, ts, err = Rs[order], ts[order], err[order]
        # a second candidate counts only when it is a different pose, not the same minimum
        # reached twice (iterative refiners stop ~1e-6 apart): 1e-4 rad / 1e-4 relative in t
        dR = np.abs(Rs - Rs[0]).max(axis=(1, 2))
        dt = np.linalg.norm(ts - ts[0], axis=1) / max(np.linalg.norm(ts[0]), 1e-12)
        other = np.flatnonzero((dR > 1e-4) | (dt > 1e-4))
        if other.size:
            e2 = err[other[0]]
            ratio = err[0] / e2 if e2 > 0 else 1.0
    return PoseEstimate(method=method, R_cam_holder=Rs[0], t_cam_holder_mm=ts[0],
                        residual_px=float(err[0] * f_px), ambiguity_ratio=float(ratio),
                        candidates=list(zip(Rs, ts)), info={"n_candidates": n_raw})


def make_solver(method: str, candidates: Callable[[np.ndarray, np.ndarray], list[Candidate]],
                min_points: int) -> Callable[..., PoseEstimate]:
    """Give a ``candidates(P, m)`` function the common solver signature."""

    def solve(points_px, camera: Camera, model) -> PoseEstimate:
        t0 = time.perf_counter()
        P = model_points(model)
        x, P = check_correspondences(points_px, P, min_points)
        m = camera.normalize_px(x)
        if not math.isfinite(m.sum()) and not np.isfinite(m).all():  # as in as_points_px
            raise InputError("points_px lie outside the camera's valid distortion domain")
        extra = {}
        try:
            cands = candidates(P, m)
        except np.linalg.LinAlgError as e:
            cands = []
            reason = f"linear algebra failed: {e}"
        else:
            reason = ""
        if isinstance(cands, tuple):  # optional form: (candidates, info dict for est.info)
            cands, extra = cands
        est = select(method, cands, P, m, camera.focal_px)
        est.info.update(extra)
        if reason and not est:
            est.reason = reason
        est.time_ms = (time.perf_counter() - t0) * 1e3
        return est

    solve.__name__ = f"solve_{method.replace('-', '_')}"
    solve.__doc__ = f"{method}: ``solve(points_px, camera, model) -> PoseEstimate``."
    return solve
