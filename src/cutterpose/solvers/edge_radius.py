"""``dm+r``: the pose of the *design* edge and the edge radius, jointly (issue 10, item 2).

A broken (rounded or chamfered) pocket edge images away from the design edge by an offset
``delta(r)`` that depends on the radius ``r`` and on the view and light at each edge
(:mod:`cutterpose.image.edge_model`). ``dm+`` fits the design corners to those image corners
and is biased (a uniform outward offset looks like a closer holder). ``dm+r`` starts from the
``dm+`` pose and its one-to-one corner assignment and minimises, over the six DOFs and one
radius per image,

    sum_i rho(|W_i (pi(R P_i(r) + t) - q_i)|^2) + s^2 ((r - r_0) / sigma_r)^2,

with ``P_i(r) = c_i + delta_(i,0)(r) o_(i-1) + delta_(i,1)(r) o_i`` the model corner of the
moved edge lines (``Z = 0``), ``q_i`` the detected corner (ideal px), ``W_i`` the whitening of
the corner's noise plus the edge model's uncertainty at that corner, ``rho`` Huber's loss (an
edge whose line locked onto a rival rise, a specular line on the fillet, is an outlier) and a
weak Gaussian prior on ``r`` (mean 2 mm, std 2 mm, clamped to [0, 6.5] mm), scaled by the
residual noise ``s``. Gauss-Newton / Levenberg-Marquardt in the DOFs themselves, so that the
normal matrix is the Fisher information in the pipeline's units.

Why one radius per image (the Fisher information, ``docs/notes/edge_model.md``): a free offset
per edge is confounded with the pose (moving the two edges of one direction by opposite amounts
is a translation, all edges outward a change of depth), so per-edge radii are unobservable
without a strong prior; per edge family (X-parallel and Y-parallel edges) they are observable
but cost a factor of 1.5-2 in the std of Z. One radius, with per-edge deviations in the error
budget, is what this contour supports.

Convention:
    Pose as in :mod:`cutterpose.geometry.pose` (``x_cam = R x_holder + t``, DOFs alpha, beta,
    gamma [deg], X, Y, Z [mm]); the estimate vector is ``(alpha, beta, gamma, X, Y, Z, r)``
    with ``r`` in mm; pixels are ideal (undistorted) pixels of the camera's ``K``.

References:
    Seed paper, sections 2.3 (distance matching) and 3.1 (the CRLB context); Kay,
    *Fundamentals of Statistical Signal Processing I* (1993), ch. 3 (Fisher information, the
    CRLB with nuisance parameters); Huber (1964) for the robust loss.
"""

from __future__ import annotations

import math
import time
from dataclasses import dataclass, field, replace

import numpy as np
from scipy.optimize import least_squares, linear_sum_assignment
from scipy.spatial.distance import cdist

from ..errors import InputError
from ..geometry.camera import Camera
from ..geometry.holder import Holder
from ..geometry.pose import Pose, rotation_from_euler_deg
from ..image.edge_model import (
    LOOK_VARIANTS,
    EdgeLook,
    OffsetTable,
    corner_offset_jacobian,
    edge_views,
    look_offsets_mm,
    model_corners_mm,
)
from .estimate import PoseEstimate

__all__ = ["RadiusPrior", "RadiusFit", "fit_pose_radius", "refine_radius", "refine_features",
           "solve",
           "fisher_pose_radius", "crlb_pose_radius", "model_offset_spread"]


#: another edge shape replaces the fillet only when its scan cost is below this fraction
SHAPE_MARGIN = 0.7
#: a shape screened on the offset grid is scanned again on exact offsets unless its scan cost
#: exceeds the first shape's by this many units of the budget's profile weight (twice the
#: e^-25 of the weight itself: the grid's cost is within a few percent, and such a shape
#: neither wins nor weighs in the budget)
SCREEN_EXPONENT = 50.0
#: fit on the shipped offset grid (``OffsetTable(tabulated=True)``) rather than on the exact
#: offsets: faster, but the grid blurs the jumps of delta(r) and the fit moves by up to a few
#: tenths of a millimetre on images where r and Z are confounded (edge_model.md, "Cost")
TABULATED_TABLES = False
#: the radii (mm) the fit starts from (the best one) and the budget's radius profile
SCAN_RADII_MM = (0.0, 0.5, 1.0, 1.5, 2.0, 3.0, 4.0, 5.0, 6.0)


@dataclass(frozen=True)
class RadiusPrior:
    """The weak prior on the edge radius (mm): a new holder's break is 0.5-1.5 mm, a worn one
    1.5-5 mm; a Gaussian of ``mean_mm`` and ``std_mm`` clamped to ``[min_mm, max_mm]``."""

    mean_mm: float = 2.0
    std_mm: float = 2.0
    min_mm: float = 0.0
    max_mm: float = 6.5

    def __post_init__(self):
        if not (self.std_mm > 0 and self.min_mm >= 0 and self.max_mm > self.min_mm
                and math.isfinite(self.mean_mm)):
            raise InputError(f"bad radius prior {self}")


@dataclass
class RadiusFit:
    """What :func:`fit_pose_radius` found, with what the error budget needs.

    Attributes
    ----------
    dof : (6,) pose DOFs; radius_mm : the edge radius.
    residuals_px : (N, 2) detected minus model corners (ideal px), model order.
    jacobian : (2N, 7) d model pixels / d (DOFs, r) at the solution.
    weights : (N,) robust weights of the corners (1: inlier).
    whitening : (N, 2, 2) the corners' whitening ``W_i`` (1 / px).
    info : (7, 7) the normal matrix ``J^T W^T W J`` + the prior (1 / unit^2).
    sigma_px : the noise scale ``s`` (robust, from the start's residuals).
    table : the offsets' table at the solution's view.
    rms_px : RMS corner residual; iterations : function evaluations of the minimiser.
    profile : ``(r, cost, dof)`` of the radius scan (:func:`_scan_radius`).
    """

    dof: np.ndarray
    radius_mm: float
    residuals_px: np.ndarray
    jacobian: np.ndarray
    weights: np.ndarray
    whitening: np.ndarray
    info: np.ndarray
    sigma_px: float
    table: OffsetTable
    rms_px: float
    iterations: int
    profile: list = field(default_factory=list)


def _rotation_and_derivatives(dof):
    """R = Rz(gamma) Ry(beta) Rx(alpha) and its derivatives w.r.t. the angles in degrees."""
    a, b, g = np.radians(dof[:3])
    ca, sa, cb, sb, cg, sg = np.cos(a), np.sin(a), np.cos(b), np.sin(b), np.cos(g), np.sin(g)
    Rx = np.array([[1, 0, 0], [0, ca, -sa], [0, sa, ca]])
    Ry = np.array([[cb, 0, sb], [0, 1, 0], [-sb, 0, cb]])
    Rz = np.array([[cg, -sg, 0], [sg, cg, 0], [0, 0, 1]])
    dRx = np.array([[0, 0, 0], [0, -sa, -ca], [0, ca, -sa]])
    dRy = np.array([[-sb, 0, cb], [0, 0, 0], [-cb, 0, -sb]])
    dRz = np.array([[-sg, -cg, 0], [cg, -sg, 0], [0, 0, 0]])
    k = np.pi / 180.0
    return Rz @ Ry @ Rx, np.stack([Rz @ Ry @ dRx, Rz @ dRy @ Rx, dRz @ Ry @ Rx]) * k


def _project(R, dof, delta, table: OffsetTable, holder: Holder, K):
    """Model corners (N, 3), camera-frame points and ideal pixels (N, 2) for offsets ``delta``."""
    P = model_corners_mm(holder, delta, table.view.outward)
    X = P @ R.T + dof[3:]
    return P, X, (X @ K.T)[:, :2] / X[:, 2:3]


def _pixels(dof, r, table: OffsetTable, holder: Holder, K):
    """The model pixels of :func:`_model` without the Jacobian (the minimiser's residual calls,
    most of them at trial points whose Jacobian is never asked for)."""
    a, b, g = np.radians(dof[:3])
    ca, sa, cb, sb, cg, sg = np.cos(a), np.sin(a), np.cos(b), np.sin(b), np.cos(g), np.sin(g)
    R = (np.array([[cg, -sg, 0], [sg, cg, 0], [0, 0, 1]])
         @ np.array([[cb, 0, sb], [0, 1, 0], [-sb, 0, cb]])
         @ np.array([[1, 0, 0], [0, ca, -sa], [0, sa, ca]]))
    return _project(R, dof, table(r)[0], table, holder, K)[2]


def _model(dof, r, table: OffsetTable, holder: Holder, K):
    """Model pixels (N, 2), their Jacobian (2N, 7) w.r.t. (DOFs, r) and the model corners
    (N, 3). (The pose part is :func:`cutterpose.geometry.pose.pixel_jacobian` for one pose,
    written out: this is the solver's inner loop.)"""
    R, dR = _rotation_and_derivatives(dof)
    delta, slope = table(r)
    P, X, uv = _project(R, dof, delta, table, holder, K)
    Z = X[:, 2]
    fx, sk, fy = K[0, 0], K[0, 1], K[1, 1]
    Jt = np.zeros((len(P), 2, 3))                                         # d px / d X_cam
    Jt[:, 0, 0], Jt[:, 0, 1] = fx / Z, sk / Z
    Jt[:, 0, 2] = -(fx * X[:, 0] + sk * X[:, 1]) / Z ** 2
    Jt[:, 1, 1], Jt[:, 1, 2] = fy / Z, -fy * X[:, 1] / Z ** 2
    dX_ang = np.einsum("kij,nj->nik", dR, P)                              # (N, 3, 3)
    dP_dr = np.einsum("nk,nkj->nj", slope, table.view.outward)            # (N, 2)
    dX_r = dP_dr @ R[:, :2].T                                             # (N, 3)
    J = np.concatenate([np.einsum("nij,njk->nik", Jt, dX_ang), Jt,
                        np.einsum("nij,nj->ni", Jt, dX_r)[..., None]], axis=2)
    return uv, J.reshape(-1, 7), P


def model_offset_spread(table: OffsetTable, radius_mm: float, camera: Camera, holder: Holder,
                        dof, looks=LOOK_VARIANTS) -> tuple[np.ndarray, np.ndarray]:
    """The edge model's remaining uncertainty at ``radius_mm``: per edge end the offsets under
    each plausible light and material (``looks``) and under the rival rise of the profile.

    Returns
    -------
    deltas : (L, N, 2) offsets (mm) under each look, minus the nominal one (the systematic
        errors the budget propagates).
    sigma_mm : (N, 2) per edge end, the RMS of those plus, where a rival rise is at least 0.6
        of the edge's, half the distance to it (the refinement may take either).
    """
    R = rotation_from_euler_deg(*dof[:3])
    d0 = table(radius_mm)[0]
    others = [look for look in looks if look != table.look]
    deltas = np.zeros((len(others),) + d0.shape)
    # the looks lit alike share one view and one batched profile computation
    by_light: dict = {}
    for i, look in enumerate(others):
        by_light.setdefault(look.ring_radius_mm, []).append(i)
    for idx in by_light.values():
        v = edge_views(R, dof[3:], camera.K, holder, others[idx[0]])
        d = look_offsets_mm(radius_mm, v, [others[i] for i in idx])[0]
        deltas[idx] = np.where(np.isfinite(d), d - d0, 0.0)
    d_nom, (rival_delta, ratio) = look_offsets_mm(radius_mm, table.view, (table.look,), 0)
    gap = np.abs(rival_delta - d_nom[0])
    rival = np.where((ratio >= 0.6) & np.isfinite(gap), 0.5 * gap, 0.0)
    sig = np.sqrt(np.mean(deltas ** 2, axis=0) + rival ** 2) if len(deltas) else rival
    return deltas, sig


def _whitening(sigma_px: float, sig_end_mm: np.ndarray, table: OffsetTable, Jt6: np.ndarray,
               R: np.ndarray) -> np.ndarray:
    """(N, 2, 2) whitening of each corner: noise ``sigma_px^2 I`` plus the edge model's
    uncertainty of its two edges (``sig_end_mm``) seen in the image."""
    o = table.view.outward                                               # (N, 2, 2)
    o3 = np.concatenate([o, np.zeros(o.shape[:2] + (1,))], axis=-1) @ R.T  # camera frame
    Jt = Jt6.reshape(-1, 2, 3)
    img = np.einsum("nij,nkj->nki", Jt, o3)                              # (N, 2 ends, 2 px)
    C = sigma_px ** 2 * np.eye(2)[None] + np.einsum("nk,nki,nkj->nij", sig_end_mm ** 2, img,
                                                     img)
    L = np.linalg.cholesky(C)
    return np.linalg.inv(L)


def _rotations_many(D):
    """(M, 3, 3) rotations and (M, 3, 3, 3) derivatives of :func:`_rotation_and_derivatives`
    for M poses at once."""
    a, b, g = np.radians(D[:, 0]), np.radians(D[:, 1]), np.radians(D[:, 2])
    ca, sa, cb, sb, cg, sg = np.cos(a), np.sin(a), np.cos(b), np.sin(b), np.cos(g), np.sin(g)
    z, o = np.zeros_like(a), np.ones_like(a)

    def m(*rows):
        return np.stack([np.stack(r, -1) for r in rows], -2)

    Rx, dRx = m((o, z, z), (z, ca, -sa), (z, sa, ca)), m((z, z, z), (z, -sa, -ca), (z, ca, -sa))
    Ry, dRy = m((cb, z, sb), (z, o, z), (-sb, z, cb)), m((-sb, z, cb), (z, z, z), (-cb, z, -sb))
    Rz, dRz = m((cg, -sg, z), (sg, cg, z), (z, z, o)), m((-sg, -cg, z), (cg, -sg, z), (z, z, z))
    k = np.pi / 180.0
    return Rz @ Ry @ Rx, np.stack([Rz @ Ry @ dRx, Rz @ dRy @ Rx, dRz @ Ry @ Rx], 1) * k


def _model_many(D, radii, table: OffsetTable, holder: Holder, K):
    """:func:`_model` for M poses ``D`` (M, 6) and radii (M,) at once: model pixels (M, N, 2)
    and the pose part of the Jacobian (M, 2N, 6) (the radius scan's Gauss-Newton steps)."""
    R, dR = _rotations_many(D)
    delta = table.many(radii)[0]                                          # (M, N, 2)
    xy = holder.corners_mm + np.einsum("mnk,nkj->mnj", delta, table.view.outward)
    P = np.concatenate([xy, np.zeros(xy.shape[:2] + (1,))], axis=2)       # (M, N, 3)
    X = np.einsum("mij,mnj->mni", R, P) + D[:, None, 3:]
    Z = X[..., 2]
    fx, sk, fy = K[0, 0], K[0, 1], K[1, 1]
    uv = np.einsum("mnj,ij->mni", X, K)[..., :2] / Z[..., None]
    Jt = np.zeros(X.shape[:2] + (2, 3))
    Jt[..., 0, 0], Jt[..., 0, 1] = fx / Z, sk / Z
    Jt[..., 0, 2] = -(fx * X[..., 0] + sk * X[..., 1]) / Z ** 2
    Jt[..., 1, 1], Jt[..., 1, 2] = fy / Z, -fy * X[..., 1] / Z ** 2
    dX_ang = np.einsum("mkij,mnj->mnik", dR, P)                            # (M, N, 3, 3)
    J = np.concatenate([np.einsum("mnij,mnjk->mnik", Jt, dX_ang), Jt], axis=3)
    return uv, J.reshape(len(D), -1, 6)


def _scan_radius(dof, q, table, holder, K, prior: RadiusPrior, r_grid):
    """Profile of the fit over the radius: for each ``r`` of the grid, the pose after three
    Gauss-Newton steps from ``dof`` and its robust cost (plus the prior). Returns the best
    radius, its pose and the profile ``(r, cost, dof)`` rows (the offsets are not monotone in
    r, so a local fit from one start can stop in the wrong valley, and the budget needs to know
    whether another valley fits nearly as well). All radii are stepped together."""
    seen = np.isfinite(q).all(axis=1)
    rows2 = np.repeat(seen, 2)
    rs = np.array([r for r in r_grid if prior.min_mm <= r <= prior.max_mm], float)
    D = np.repeat(np.asarray(dof, float)[None], len(rs), axis=0)
    for _ in range(3):
        uv, J = _model_many(D, rs, table, holder, K)
        e = (uv - q)[:, seen].reshape(len(rs), -1)
        D = D - np.stack([np.linalg.lstsq(J[m][rows2], e[m], rcond=None)[0]
                          for m in range(len(rs))])
    uv = _model_many(D, rs, table, holder, K)[0]
    e = np.linalg.norm(uv[:, seen] - q[seen], axis=2)                      # (M, n_seen)
    s2 = max(0.05, float(np.median(e[0]))) ** 2
    cost = np.sum(np.minimum(e ** 2, 4 * s2), axis=1) + s2 * (
        (rs - prior.mean_mm) / prior.std_mm) ** 2
    rows = [(float(r), float(c), d) for r, c, d in zip(rs, cost, D)]
    best = min(rows, key=lambda row: row[1])
    return best[0], best[2], rows


def _huber(z: np.ndarray, k: float) -> np.ndarray:
    """Huber weights of whitened 2-D residuals (N, 2)."""
    e = np.linalg.norm(z, axis=1)
    return np.where(e <= k, 1.0, k / np.maximum(e, 1e-12))


def fit_pose_radius(dof0, ideal_px: np.ndarray, camera: Camera, holder: Holder,
                    look: EdgeLook = EdgeLook(), prior: RadiusPrior = RadiusPrior(),
                    max_iter: int = 30, huber_k: float = 2.5,
                    r_grid=None,
                    table: OffsetTable | None = None, scan=None) -> RadiusFit:
    """Levenberg-Marquardt on (DOFs, r) from ``dof0`` with the corners ``ideal_px`` given in
    model order (module doc).

    The offsets' table is made once at ``dof0`` (the offsets follow the viewing direction, not
    the millimetres the fit moves); a scan over ``r_grid`` picks the start; the first pass
    whitens the corners by the noise ``s`` alone (the robust scale of the start's residuals),
    the second by the noise plus the edge model's rival rises at the radius found (``table``:
    a table made before for a view close to ``dof0``, e.g. for repeated fits; ``scan``: the
    result of :func:`_scan_radius` with that table, when already made). The
    minimiser is SciPy's trust-region reflective ``least_squares`` with Huber's loss on each
    whitened coordinate and the bounds of the prior on ``r``.
    """
    K = camera.K
    q = np.asarray(ideal_px, float)
    n = len(q)
    seen = np.isfinite(q).all(axis=1)
    R0 = rotation_from_euler_deg(*np.asarray(dof0, float)[:3])
    if table is None:
        table = OffsetTable(R0, np.asarray(dof0, float)[3:], K, holder, look)
    if scan is None:
        scan = _scan_radius(np.asarray(dof0, float), q, table, holder, K, prior,
                            SCAN_RADII_MM if r_grid is None else r_grid)
    r, dof, profile = scan
    uv, J, _ = _model(dof, r, table, holder, K)
    # a corner not seen: a finite placeholder with zero whitening, so it adds nothing
    q = np.where(seen[:, None], q, uv)
    # noise scale: robust, from the start's residuals (|e| of a 2-D Gaussian: median 1.18 s)
    s = max(0.02, float(np.median(np.linalg.norm(uv - q, axis=1)[seen])) / 1.18)
    it = 0
    sig_end = np.zeros((n, 2))
    inv_sr = 1.0 / prior.std_mm
    x = np.r_[dof, r]
    lo = np.r_[np.full(6, -np.inf), prior.min_mm]
    hi = np.r_[np.full(6, np.inf), prior.max_mm]
    for pass_ in range(2):
        if pass_:
            sig_end = model_offset_spread(table, x[6], camera, holder, x[:6], ())[1]
        W = _whitening(s, sig_end, table, J[:, 3:6], R0) * seen[:, None, None]

        def fun(x_, W=W):
            uv_ = _pixels(x_[:6], x_[6], table, holder, K)
            z_ = np.einsum("nij,nj->ni", W, uv_ - q).ravel()
            return np.r_[z_, (x_[6] - prior.mean_mm) * inv_sr]

        def jac(x_, W=W):
            J_ = _model(x_[:6], x_[6], table, holder, K)[1]
            Jw_ = np.einsum("nij,njk->nik", W, J_.reshape(n, 2, 7)).reshape(-1, 7)
            return np.vstack([Jw_, np.r_[np.zeros(6), inv_sr]])

        # Huber's loss on each whitened coordinate (scipy's trust-region reflective, bounds on r)
        sol = least_squares(fun, np.clip(x, lo, hi), jac, bounds=(lo, hi), loss="huber",
                            f_scale=huber_k, x_scale="jac", max_nfev=max_iter)
        x = sol.x
        it += sol.nfev
    dof, r = x[:6], float(x[6])
    uv, J, _ = _model(dof, r, table, holder, K)
    res = np.where(seen[:, None], uv - q, 0.0)
    z = np.einsum("nij,nj->ni", W, res)
    wt = _huber(z, huber_k) * seen
    Jw = (np.einsum("nij,njk->nik", W, J.reshape(n, 2, 7)) * np.sqrt(wt)[:, None, None]
          ).reshape(-1, 7)
    H = Jw.T @ Jw
    H[6, 6] += inv_sr ** 2
    rms = float(np.sqrt(np.mean(np.sum(res[seen] ** 2, axis=1))))
    return RadiusFit(dof, r, res, J, wt, W, H, s, table, rms, it, profile)


def _assigned(est: PoseEstimate, ideal_px: np.ndarray, camera: Camera, holder: Holder):
    """Detected corners in model order: the solver's assignment, else the nearest one-to-one
    assignment to the estimate's projection."""
    col = est.assignment
    if col is None or len(col) != holder.n_corners or len(ideal_px) != holder.n_corners:
        R, t = np.asarray(est.R_cam_holder, float), np.asarray(est.t_cam_holder_mm, float)
        X = holder.points_holder_mm @ R.T + t
        uv = (X @ camera.K.T)[:, :2] / X[:, 2:3]
        col = linear_sum_assignment(cdist(uv, ideal_px, "sqeuclidean"))[1]
    return np.asarray(ideal_px, float)[np.asarray(col)]


def refine_radius(est: PoseEstimate, ideal_px: np.ndarray, camera: Camera, holder: Holder,
                  look: EdgeLook = EdgeLook(), prior: RadiusPrior = RadiusPrior(),
                  name: str = "dm+r", shapes=("round", "chamfer"),
                  ordered: bool = False, tabulated: bool | None = None) -> PoseEstimate:
    """The refinement step after a solver: ``est`` -> the design-edge pose and the radius
    (``radius_fit``: the :class:`RadiusFit`; ``info["edge_radius_mm"]``), fitted for each
    edge ``shapes`` and the better kept (``info["edge_shape"]``).

    ``ordered``: ``ideal_px`` is already in model order (the field chain), NaN rows for the
    corners not seen, which the fit leaves out; else the solver's assignment orders them.
    ``info["shape_costs"]``: each shape's best scan cost (a shape screened on the offset grid
    and not rescanned: its grid cost).
    ``tabulated``: fit on the shipped offset grid instead of the exact offsets (default
    :data:`TABULATED_TABLES`; ~12 ms faster, but not the same fit: docs/notes/edge_model.md,
    "Cost")."""
    if not est:
        return PoseEstimate.failure(name, est.reason, info=est.info)
    t0 = time.perf_counter()
    if len(ideal_px) != holder.n_corners:
        return PoseEstimate.failure(name, f"{len(ideal_px)} corners: the radius fit needs all "
                                    f"{holder.n_corners}", info=est.info)
    q = (np.asarray(ideal_px, float) if ordered
         else _assigned(est, np.asarray(ideal_px, float), camera, holder))
    if np.isfinite(q).all(axis=1).sum() < 6:
        return PoseEstimate.failure(name, "fewer than 6 corners seen: no radius fit",
                                    info=est.info)
    dof0 = Pose(est.R_cam_holder, est.t_cam_holder_mm).dof
    # the edge's shape (a new holder's break is a fillet or a chamfer): the one whose radius
    # scan fits the corners better (the scan's trimmed cost, one noise scale for both); the
    # full fit only for that one
    R0 = rotation_from_euler_deg(*dof0[:3])

    def scanned(shape, tabulated):
        t = OffsetTable(R0, dof0[3:], camera.K, holder, replace(look, shape=shape),
                        tabulated=tabulated)
        sc = _scan_radius(dof0, q, t, holder, camera.K, prior, SCAN_RADII_MM)
        return t, sc, min(c for _, c, _ in sc[2])

    fast = TABULATED_TABLES if tabulated is None else tabulated
    t, sc, c = scanned(shapes[0], fast)
    tables, scans, cost = [t], [sc], [c]
    # a screened shape is kept from the grid only when its rows weigh nothing in the budget's
    # radius profile (radius_profile_cov: exp(-(cost - min) (2 n - 7) / (2 min)) < e^-25)
    n_seen = int(np.isfinite(q).all(axis=1).sum())
    screen_cost = cost[0] * (1.0 + SCREEN_EXPONENT / max(2 * n_seen - 7, 1))
    for sh in shapes[1:]:
        # the other shapes are screened on the shipped offset grid (~1 ms instead of ~10 ms;
        # its offsets are within ~0.01 mm, its scan cost within a few percent); one that could
        # win or weigh in the budget's radius profile is scanned again on exact offsets
        t, sc, c = scanned(sh, True)
        if t.tabulated and not fast and c <= screen_cost:
            t, sc, c = scanned(sh, False)
        tables.append(t)
        scans.append(sc)
        cost.append(c)
    # the first shape (the fillet, the common break) unless another fits clearly better: a
    # chamfer images at its foot, a depth offset the contour cannot tell from Z, so a chamfer
    # chosen on a tie would throw away the depth of a sharp or filleted edge
    k = int(np.argmin(cost))
    if cost[k] > SHAPE_MARGIN * cost[0]:
        k = 0
    fit = fit_pose_radius(dof0, q, camera, holder, tables[k].look, prior, table=tables[k],
                          scan=scans[k])
    if not np.all(np.isfinite(fit.dof)):
        return PoseEstimate.failure(name, "the radius fit diverged", info=est.info)
    # the other shapes' scans join the profile the budget weighs: a chamfer images at its foot,
    # a pure depth offset, so every chamfer size fits about equally well with another Z; when
    # the corners cannot tell the shapes apart, that depth range is part of the uncertainty
    fit.profile = list(fit.profile) + [row for i, sc in enumerate(scans) if i != k
                                       for row in sc[2]]
    info = dict(est.info, edge_radius_mm=fit.radius_mm, edge_shape=fit.table.look.shape,
                shape_costs=dict(zip(shapes, cost)), radius_iterations=fit.iterations,
                start_dof=dof0.tolist())
    pose = Pose.from_euler(*fit.dof)
    return PoseEstimate(method=name, R_cam_holder=pose.R, t_cam_holder_mm=pose.t_mm,
                        residual_px=fit.rms_px, candidates=est.candidates,
                        time_ms=(est.time_ms if math.isfinite(est.time_ms) else 0.0)
                        + (time.perf_counter() - t0) * 1e3, info=info,
                        assignment=est.assignment, radius_fit=fit)


def refine_features(start: PoseEstimate, features, camera: Camera, model: Holder,
                    shapes=("round",)) -> PoseEstimate:
    """``dm+r`` in the pipeline (:class:`~cutterpose.methods.Method` ``refine``): the radius
    fit from ``start`` (the ``dm+`` pose) on the detected corners. The edge model predicts the
    rise the line refinement takes: the field chain's innermost rise (``order == "holder"``),
    the paper chain's strongest."""
    corners = np.asarray(features.corners_px, float)
    seen = np.isfinite(corners).all(axis=1)
    ideal = np.full_like(corners, np.nan)
    ideal[seen] = camera.undistort_px(corners[seen])
    field = features.order == "holder"
    look = EdgeLook() if field else EdgeLook(innermost=0.0)
    return refine_radius(start, ideal, camera, model, look=look, shapes=shapes, ordered=field)


def solve(points_px, camera: Camera, model: Holder) -> PoseEstimate:
    """Registered method ``dm+r``: ``dm+`` (synthetic motion range) + :func:`refine_radius`."""
    from .dm import solve_dm_plus

    est = solve_dm_plus(points_px, camera, model)
    ideal = camera.undistort_px(np.asarray(points_px, float))
    return refine_radius(est, ideal, camera, model)


# ---- Fisher information ---------------------------------------------------------------------
def fisher_pose_radius(pose: Pose, camera: Camera, holder: Holder, radius_mm: float,
                       sigma_px: float, look: EdgeLook = EdgeLook()) -> np.ndarray:
    """(7, 7) Fisher information of (DOFs, r) from the 20 corners with independent Gaussian
    noise of ``sigma_px`` per coordinate (PROTOCOL.md's noise model), without prior."""
    table = OffsetTable(pose.R, pose.t_mm, camera.K, holder, look)
    _, J, _ = _model(pose.dof, radius_mm, table, holder, camera.K)
    return J.T @ J / sigma_px ** 2


def crlb_pose_radius(pose: Pose, camera: Camera, holder: Holder, radius_mm: float,
                     sigma_px: float, look: EdgeLook = EdgeLook(),
                     prior: RadiusPrior | None = None) -> dict:
    """The bound on the std of the DOFs with the radius free and known, and the radius's
    bound and correlation with each DOF.

    Returns
    -------
    dict: ``std_free`` (7,) (DOFs then r), ``std_known`` (6,), ``corr_r`` (6,) correlation of
    r with each DOF, ``std_per_family`` (8,) with one radius per edge direction (without
    prior), ``fisher`` (7, 7).
    """
    F = fisher_pose_radius(pose, camera, holder, radius_mm, sigma_px, look)
    if prior is not None:  # the prior's information on r (a Bayesian bound)
        F[6, 6] += 1.0 / prior.std_mm ** 2
    C = np.linalg.inv(F)
    std_free = np.sqrt(np.diag(C))
    std_known = np.sqrt(np.diag(np.linalg.inv(F[:6, :6])))
    corr = C[6, :6] / (std_free[6] * std_free[:6])
    # one radius per edge direction: split the r column by the family of each edge end
    table = OffsetTable(pose.R, pose.t_mm, camera.K, holder, look)
    _, J, P = _model(pose.dof, radius_mm, table, holder, camera.K)
    R = pose.R
    slope = table(radius_mm)[1]
    fam = holder.edge_direction_index                                    # per edge
    fam_end = np.stack([np.roll(fam, 1), fam], axis=1)                   # (N, 2)
    Jt = J[:, 3:6].reshape(-1, 2, 3)
    cols = []
    for f in (0, 1):
        sl = np.where(fam_end == f, slope, 0.0)
        dP = np.einsum("nk,nkj->nj", sl, table.view.outward)
        dX = np.column_stack([dP, np.zeros(len(dP))]) @ R.T
        cols.append(np.einsum("nij,nj->ni", Jt, dX).reshape(-1))
    J8 = np.column_stack([J[:, :6]] + cols)
    C8 = np.linalg.inv(J8.T @ J8 / sigma_px ** 2)
    return {"std_free": std_free, "std_known": std_known, "corr_r": corr,
            "std_per_family": np.sqrt(np.diag(C8)), "fisher": F}


def per_edge_jacobian(fit: RadiusFit, camera: Camera, holder: Holder) -> np.ndarray:
    """(2N, N) d model pixels / d (offset of each edge, mm) at the fit (both of its ends)."""
    R = rotation_from_euler_deg(*fit.dof[:3])
    D = corner_offset_jacobian(fit.table.view.outward)                   # (N, 3, N)
    Jt = fit.jacobian[:, 3:6].reshape(-1, 2, 3)
    return np.einsum("nij,jk,nkm->nim", Jt, R, D).reshape(-1, D.shape[2])
