"""What every PnP solver shares: input checks, normalisation, candidate selection, timing.

A solver module implements one function::

    candidates(points_obj_mm: (n, 3), m: (n, 2)) -> list[(R, t_mm)]

on normalised image coordinates ``m = K^-1 ideal_px`` (undistorted), and wraps it with
:func:`make_solver`, which gives it the common signature::

    solve(points_px, camera, model) -> PoseEstimate

``model`` is a :class:`~cutterpose.holder.Holder` (its 20 corners, in model order) or any
``(n, 3)`` array of object points (non-planar sets included). The wrapper

* rejects bad input with typed errors (shape mismatch, NaN/inf, too few points, collinear points);
* drops candidates that are not finite or put a point behind the camera;
* picks the candidate with the least RMS reprojection error (ideal pixels) and reports the
  ratio best / second-best as ``ambiguity_ratio``;
* returns a falsy :class:`~cutterpose.estimate.PoseEstimate` with the reason when nothing is left.
"""

from __future__ import annotations

import time
from collections.abc import Callable

import numpy as np

from ..camera import Camera
from ..errors import DegenerateInputError, InputError
from ..estimate import PoseEstimate
from ..holder import Holder

__all__ = ["model_points", "check_correspondences", "reprojection_rms", "select", "make_solver",
           "is_planar", "plane_frame", "align_rigid"]

Candidate = tuple[np.ndarray, np.ndarray]


def model_points(model) -> np.ndarray:
    """(n, 3) object points of a holder or of a point array."""
    if isinstance(model, Holder):
        return model.points_holder_mm
    try:
        P = np.asarray(model, dtype=float)
    except (TypeError, ValueError):
        raise InputError("model must be a Holder or an (n, 3) array of object points") from None
    if P.ndim != 2 or P.shape[1] != 3:
        raise InputError(f"object points must have shape (n, 3), got {P.shape}")
    return P


def check_correspondences(points_px, points_obj, min_points: int) -> tuple[np.ndarray, np.ndarray]:
    """Validate image/object correspondences; return them as float arrays.

    Raises
    ------
    InputError
        Shapes do not match, or values are NaN/inf.
    DegenerateInputError
        Fewer than ``min_points`` points, or all points (image or object) collinear.
    """
    try:
        x = np.asarray(points_px, dtype=float)
    except (TypeError, ValueError):
        raise InputError("points_px must be an (n, 2) array of numbers") from None
    P = np.asarray(points_obj, dtype=float)
    if x.ndim != 2 or x.shape[1] != 2:
        raise InputError(f"points_px must have shape (n, 2), got {x.shape}")
    if len(x) != len(P):
        raise InputError(f"points_px has {len(x)} points but the model has {len(P)}; they must "
                         "correspond one to one")
    if not np.all(np.isfinite(x)):
        raise InputError(f"points_px holds NaN or inf (at {np.argwhere(~np.isfinite(x))[0, 0]})")
    if not np.all(np.isfinite(P)):
        raise InputError("object points hold NaN or inf")
    if len(x) < min_points:
        raise DegenerateInputError(f"need at least {min_points} points, got {len(x)}")
    for arr, what in ((x, "image points"), (P, "object points")):
        if _collinear(arr):
            raise DegenerateInputError(f"all {what} are collinear (or coincide): the pose is not "
                                       "determined")
    return x, P


def _collinear(a: np.ndarray, tol: float = 1e-9) -> bool:
    """True when the points span at most a line: the second singular value of the centred set is
    below ``tol`` times the first. Uses the covariance's invariants (sum of principal 2x2 minors
    = sum of products of eigenvalue pairs) instead of an SVD: this sits on every solve's path."""
    c = a - a.mean(axis=0)
    C = c.T @ c
    tr = np.trace(C)
    if tr <= 0:
        return True
    if C.shape == (2, 2):
        pairs = C[0, 0] * C[1, 1] - C[0, 1] ** 2
    else:
        pairs = (C[0, 0] * C[1, 1] - C[0, 1] ** 2 + C[0, 0] * C[2, 2] - C[0, 2] ** 2
                 + C[1, 1] * C[2, 2] - C[1, 2] ** 2)
    # pairs / tr^2 ~ (s2 / s1)^2 when s2 << s1
    return bool(pairs <= (tol**2) * tr * tr)


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
    Pc, Xc = P.mean(axis=0), X.mean(axis=0)
    S = (X - Xc).T @ (P - Pc)
    U, _, Vt = np.linalg.svd(S)
    D = np.diag([1.0, 1.0, np.sign(np.linalg.det(U) * np.linalg.det(Vt)) or 1.0])
    R = U @ D @ Vt
    return R, Xc - R @ Pc


def reprojection_rms(R, t, P, m) -> float:
    """RMS reprojection error in normalised units (multiply by f for pixels)."""
    X = P @ np.asarray(R).T + np.asarray(t)
    with np.errstate(divide="ignore", invalid="ignore"):
        proj = X[:, :2] / X[:, 2:3]
    return float(np.sqrt(np.mean(np.sum((proj - m) ** 2, axis=1))))


def _det3(M: np.ndarray) -> np.ndarray:
    """Determinants of (k, 3, 3) matrices (explicit: np.linalg.det costs more on tiny batches)."""
    return (M[:, 0, 0] * (M[:, 1, 1] * M[:, 2, 2] - M[:, 1, 2] * M[:, 2, 1])
            - M[:, 0, 1] * (M[:, 1, 0] * M[:, 2, 2] - M[:, 1, 2] * M[:, 2, 0])
            + M[:, 0, 2] * (M[:, 1, 0] * M[:, 2, 1] - M[:, 1, 1] * M[:, 2, 0]))


def select(method: str, cands: list[Candidate], P, m, f_px: float) -> PoseEstimate:
    """Pick the candidate with the least reprojection error; see the module docstring."""
    n_raw = len(cands)
    if cands:
        Rs = np.array([np.asarray(R, float).reshape(3, 3) for R, _ in cands])
        ts = np.array([np.asarray(t, float).reshape(3) for _, t in cands])
        finite = np.isfinite(Rs).all(axis=(1, 2)) & np.isfinite(ts).all(axis=1)
        Rs, ts = Rs[finite], ts[finite]
        X = P @ Rs.transpose(0, 2, 1) + ts[:, None, :]
        ok = (np.abs(_det3(Rs) - 1.0) <= 1e-6) & np.all(X[..., 2] > 0, axis=1)
        Rs, ts, X = Rs[ok], ts[ok], X[ok]
    if not cands or len(Rs) == 0:
        reason = ("no candidate pose" if not cands
                  else f"none of {n_raw} candidates is finite with all points in front")
        return PoseEstimate.failure(method, reason, info={"n_candidates": n_raw})
    err = np.sqrt(np.mean(np.sum((X[..., :2] / X[..., 2:3] - m) ** 2, axis=2), axis=1))
    order = np.argsort(err, kind="stable")
    Rs, ts, err = Rs[order], ts[order], err[order]
    ratio = np.nan
    # a second candidate counts only when it is a different pose, not the same minimum reached
    # twice (iterative refiners stop ~1e-6 apart): 1e-4 rad / 1e-4 relative in t
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
        if not np.all(np.isfinite(m)):
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
