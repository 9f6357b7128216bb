"""Initial pose from the holder's own geometry: vanishing directions and contour area.

The seed paper's section 2.2, without 2D-3D correspondences. The detected contour gives the 20
corners in order up to an unknown start and direction, so its edges split into two groups by
parity (edges alternate between the holder's X and Y directions), but which group is X, and which
corner is which, is unknown.

1. **Directions.** The image of the model edges parallel to a direction ``d`` (unit, camera
   frame) meet in the vanishing point ``v ~ K d``.

   * ``paper`` (faithful): every pair of image lines of a group is intersected in homogeneous
     coordinates, ``v_ij = l_i x l_j`` (points at infinity included); pairs of (nearly) collinear
     lines, which the holder has (e.g. the two edges on ``x = +-120``), give no vanishing point
     and are left out. The final vanishing point is the geometric median (Weiszfeld) of the
     pairwise ones in the image plane, and ``d = K^-1 v / |K^-1 v|``.
   * ``sphere`` (ours): each edge ``(m_a, m_b)`` (normalised homogeneous corners) spans the
     interpretation plane with normal ``l = m_a x m_b``; every direction of its group satisfies
     ``l . d = 0``. The un-normalised ``l`` makes the residual ``l . d`` roughly homoscedastic
     (its size grows with the edge length), so the two directions are the joint least-squares
     solution ``min sum_X (l_i . r1)^2 + sum_Y (l_j . r2)^2`` over a rotation ``[r1 r2 r3]``,
     i.e. with ``r1 _|_ r2`` enforced (start: the least eigenvectors of ``sum l l^T`` per group).
     This stays well conditioned when the view is fronto-parallel (vanishing points at
     infinity), where the image-plane median of the paper breaks down.

2. **Rotation.** ``R = nearest_rotation([r1, r2, r1 x r2])`` (paper: normalised ``K^-1 v``,
   cross product).

3. **Translation.** The plane with normal ``n = r3`` through the ray of one corner (at depth 1)
   cuts the corner rays in a polygon similar to the holder's contour; with ``A_bp`` its area and
   ``A`` the model's, the scale is ``s = sqrt(A / A_bp)`` (paper: ``(d1/d2)^2`` equals the area
   ratio), the contour in the camera frame is ``s X_k`` and, the vertex centroid being
   order-free, ``t = s mean(X_k) - R mean(P_k)`` (paper: "X and Y by similarity").

4. **Ambiguities.** The signs of ``r1, r2`` and the X/Y labelling of the two edge groups give 8
   rotations. The holder is symmetric under 180 deg about Z (and, as a planar set, about X and
   Y), so 4 of them explain the image equally well: we keep the candidates whose visible side
   faces the camera (``r3 . t > 0``) and whose DOFs lie in the known :class:`MotionRange`
   (the 180 deg about Z twin is then outside any range narrower than +-90 deg in gamma); the
   X/Y labelling is decided by the correspondence-free chamfer score (RMS distance of each
   projected model corner to the nearest detected corner).

Convention:
    Pose as in :mod:`cutterpose.geometry.pose`: ``x_cam = R @ x_holder + t`` (mm), ``R = Rz Ry Rx``.
    Inputs are observed (distorted) pixels; everything here works on ideal pixels
    (``camera.undistort_px``) or normalised coordinates ``K^-1 ideal``.

References:
    Seed paper, section 2.2 and Fig. 2. R. Hartley and A. Zisserman, *Multiple View Geometry*,
    2nd ed., section 8.6 (vanishing points and lines). Weiszfeld's algorithm for the geometric
    median.
"""

from __future__ import annotations

import time

import numpy as np
from scipy.spatial import cKDTree
from scipy.spatial.transform import Rotation

from ..errors import DegenerateInputError, InputError
from ..geometry.camera import Camera
from ..geometry.holder import Holder
from ..geometry.pose import nearest_rotation
from ..geometry.working_range import MotionRange, pose_dof
from .estimate import PoseEstimate
from .method import ContourMethod
from .pnp.base import as_points_px

__all__ = ["Initial", "InitialPaper", "check_contour", "initial_pose",
           "initial_pose_paper", "solve", "solve_paper", "chamfer_rms_px",
           "direction_candidates", "sphere_directions", "paper_directions", "depth_from_area"]


# ------------------------------------------------------------------------------------------
def check_contour(points_px, holder: Holder) -> np.ndarray:
    """Validate the detected contour corners; return them as an ``(n, 2)`` float array.

    Raises
    ------
    InputError
        Not an ``(n, 2)`` array of finite numbers, or ``holder`` not a :class:`Holder`.
    DegenerateInputError
        Not exactly the holder's number of corners, or all corners (nearly) collinear.
    """
    if not isinstance(holder, Holder):
        raise InputError("the correspondence-free methods need a Holder (its contour), got "
                         f"{type(holder).__name__}")
    x = as_points_px(points_px)
    if len(x) != holder.n_corners:
        raise DegenerateInputError(
            f"need the {holder.n_corners} corners of the holder's inner contour (in contour "
            f"order), got {len(x)}")
    s = np.linalg.svd(x - x.mean(axis=0), compute_uv=False)
    if s[0] <= 0 or s[1] / s[0] < 1e-6:
        raise DegenerateInputError("all contour corners are collinear (or coincide): the "
                                   "holder's pose is not determined")
    return x


def _normalised(points_px, camera: Camera) -> np.ndarray:
    """Observed pixels -> homogeneous normalised coordinates ``(x, y, 1)``."""
    m = camera.normalize_px(points_px)
    if not np.all(np.isfinite(m)):
        raise InputError("points_px lie outside the camera's valid distortion domain")
    return np.column_stack([m, np.ones(len(m))])


# ---- directions -----------------------------------------------------------------------------
def _edge_lines(m: np.ndarray) -> np.ndarray:
    """(n, 3) un-normalised interpretation-plane normals ``m_k x m_{k+1}`` of the contour
    edges (edge k joins corner k and k+1)."""
    return np.cross(m, np.roll(m, -1, axis=0))


def _rot_from_columns(r1, r2) -> np.ndarray:
    return nearest_rotation(np.column_stack([r1, r2, np.cross(r1, r2)]))


def sphere_directions(m: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Directions of the even and odd edge groups, jointly on the unit sphere (module doc 1).

    Parameters
    ----------
    m : (n, 3) homogeneous normalised corners in contour order.

    Returns
    -------
    d_even, d_odd : unit directions (signs arbitrary), exactly orthogonal.
    """
    lines = _edge_lines(m)
    scale = np.sqrt(np.mean(np.sum(lines ** 2, axis=1)))
    lines = lines / scale
    L0, L1 = lines[0::2], lines[1::2]
    d = []
    for L in (L0, L1):
        _, V = np.linalg.eigh(L.T @ L)
        d.append(V[:, 0])
    R = _rot_from_columns(d[0], d[1])
    # Gauss-Newton on R <- exp([w]x) R: d(l . R e_i) / dw = (R e_i) x l
    for _ in range(20):
        r1, r2 = R[:, 0], R[:, 1]
        res = np.concatenate([L0 @ r1, L1 @ r2])
        J = np.vstack([np.cross(r1, L0), np.cross(r2, L1)])
        w = -np.linalg.lstsq(J, res, rcond=None)[0]
        R = Rotation.from_rotvec(w).as_matrix() @ R
        if np.linalg.norm(w) < 1e-13:
            break
    return R[:, 0], R[:, 1]


def _weiszfeld(points: np.ndarray, iters: int = 100, tol: float = 1e-9) -> np.ndarray:
    """Geometric median of ``(k, 2)`` points: the point with the least summed distance."""
    y = np.median(points, axis=0)
    for _ in range(iters):
        dist = np.linalg.norm(points - y, axis=1)
        if np.any(dist < 1e-12):
            return points[np.argmin(dist)].copy()
        w = 1.0 / dist
        y_new = (w[:, None] * points).sum(axis=0) / w.sum()
        if np.linalg.norm(y_new - y) <= tol * (1.0 + np.linalg.norm(y)):
            return y_new
        y = y_new
    return y


def paper_directions(ideal_px: np.ndarray, K: np.ndarray,
                     collinear_tol_px: float = 25.0) -> tuple[np.ndarray, np.ndarray]:
    """Directions of the even and odd edge groups by the paper's construction (module doc 1).

    Parameters
    ----------
    ideal_px : (n, 2) ideal (undistorted) pixels in contour order.
    K : (3, 3) intrinsics.
    collinear_tol_px : two lines whose segments' end points all lie within this distance of
        the other line are collinear and give no vanishing point.

    Returns
    -------
    d_even, d_odd : unit directions ``K^-1 v / |K^-1 v|`` (signs arbitrary, not orthogonalised).
    """
    p = np.column_stack([ideal_px, np.ones(len(ideal_px))])
    a, b = p, np.roll(p, -1, axis=0)
    lines = np.cross(a, b)
    lines = lines / np.linalg.norm(lines[:, :2], axis=1, keepdims=True)   # unit normal: px dist
    K_inv = np.linalg.inv(K)
    out = []
    for g in (0, 1):
        idx = np.arange(g, len(p), 2)
        i, j = np.triu_indices(len(idx), 1)
        li, lj = lines[idx[i]], lines[idx[j]]
        # end-point distances of each segment to the other line
        dij = np.abs(np.stack([np.sum(li * a[idx[j]], 1), np.sum(li * b[idx[j]], 1),
                               np.sum(lj * a[idx[i]], 1), np.sum(lj * b[idx[i]], 1)], 1))
        keep = dij.max(axis=1) > collinear_tol_px
        if not np.any(keep):
            raise DegenerateInputError("every pair of lines of an edge group is collinear: no "
                                       "vanishing point")
        v = np.cross(li[keep], lj[keep])
        # points at infinity (w = 0) are taken as very far points in their direction, so the
        # median still "sees" them; 1e12 px is far beyond any finite vanishing point
        w = v[:, 2]
        far = 1e12
        vn = v[:, :2] / np.linalg.norm(v[:, :2], axis=1, keepdims=True)
        with np.errstate(divide="ignore", invalid="ignore"):
            fin = v[:, :2] / w[:, None]
        big = ~np.isfinite(fin).all(axis=1) | (np.linalg.norm(fin, axis=1) > far)
        pts = np.where(big[:, None], vn * far, fin)
        vp = _weiszfeld(pts)
        d = K_inv @ np.array([vp[0], vp[1], 1.0])
        out.append(d / np.linalg.norm(d))
    return out[0], out[1]


# ---- translation and candidates ----------------------------------------------------------
def depth_from_area(R: np.ndarray, m: np.ndarray, holder: Holder) -> np.ndarray | None:
    """Translation from the contour area and similarity (module doc 3); None when a corner
    ray does not meet the plane in front of the camera."""
    n = R[:, 2]
    den = m @ n
    num = n @ m[0]
    if not np.all(den * num > 0):
        return None
    X = (num / den)[:, None] * m                      # corners on the plane through m[0]
    area_vec = 0.5 * np.sum(np.cross(X, np.roll(X, -1, axis=0)), axis=0)
    area_bp = abs(area_vec @ n)
    if not area_bp > 0:
        return None
    s = np.sqrt(holder.area_mm2 / area_bp)
    return s * X.mean(axis=0) - R @ holder.points_holder_mm.mean(axis=0)


def chamfer_rms_px(R, t, holder: Holder, ideal_px: np.ndarray, K: np.ndarray,
                   tree: cKDTree | None = None) -> np.ndarray:
    """RMS distance (ideal px) of each projected model corner to the nearest detected corner;
    vectorised over poses ``R (..., 3, 3)``, ``t (..., 3)``. Correspondence-free."""
    tree = tree or cKDTree(ideal_px)
    Xc = np.einsum("...ij,nj->...ni", R, holder.points_holder_mm) + np.asarray(t)[..., None, :]
    with np.errstate(divide="ignore", invalid="ignore"):
        uv = (Xc @ K.T)[..., :2] / Xc[..., 2:3]
    bad = ~np.all(np.isfinite(uv), axis=-1) | (Xc[..., 2] <= 0)
    uv = np.where(bad[..., None], 1e9, uv)
    d, _ = tree.query(uv)
    d = np.where(bad, 1e9, d)
    return np.sqrt(np.mean(d ** 2, axis=-1))


def direction_candidates(d_even, d_odd) -> list[np.ndarray]:
    """The 8 rotations from two directions: X/Y labelling x signs of r1 and r2."""
    out = []
    for dx, dy in ((d_even, d_odd), (d_odd, d_even)):
        for s1 in (1.0, -1.0):
            for s2 in (1.0, -1.0):
                out.append(_rot_from_columns(s1 * dx, s2 * dy))
    return out


def _initial(method: str, points_px, camera: Camera, holder: Holder, motion_range: MotionRange,
             directions: str, slack: float) -> PoseEstimate:
    t0 = time.perf_counter()
    x = check_contour(points_px, holder)
    m = _normalised(x, camera)
    ideal = camera.undistort_px(x)
    K = camera.K
    if directions == "sphere":
        d0, d1 = sphere_directions(m)
    elif directions == "paper":
        d0, d1 = paper_directions(ideal, K)
    else:
        raise InputError(f"unknown direction method {directions!r}")
    cands = []
    for R in direction_candidates(d0, d1):
        t = depth_from_area(R, m, holder)
        if t is None or not np.all(np.isfinite(t)) or R[:, 2] @ t <= 0:
            continue                                   # the visible side must face the camera
        cands.append((R, t))
    if not cands:
        return PoseEstimate.failure(method, "no initial pose with the holder in front of the "
                                    "camera", time_ms=(time.perf_counter() - t0) * 1e3)
    Rs = np.array([c[0] for c in cands])
    ts = np.array([c[1] for c in cands])
    excess = motion_range.excess(pose_dof(Rs, ts))
    score = chamfer_rms_px(Rs, ts, holder, ideal, K)
    inside = excess <= slack
    order = np.lexsort((score, ~inside))              # in range first, then by score
    kept = [i for i in order if inside[i]]
    info = {"n_candidates": len(cands), "scores_px": score[order].tolist(),
            "range_excess": excess[order].tolist(), "directions": directions}
    if not kept:
        return PoseEstimate.failure(
            method, f"no initial pose within the motion range (least excess "
            f"{excess.min():.2f} half widths)", info=info,
            time_ms=(time.perf_counter() - t0) * 1e3)
    best = kept[0]
    ratio = score[best] / score[kept[1]] if len(kept) > 1 and score[kept[1]] > 0 else np.nan
    return PoseEstimate(method=method, R_cam_holder=Rs[best], t_cam_holder_mm=ts[best],
                        residual_px=float(score[best]), ambiguity_ratio=float(ratio),
                        candidates=[(Rs[i], ts[i]) for i in kept], info=info,
                        time_ms=(time.perf_counter() - t0) * 1e3)


def initial_pose(points_px, camera: Camera, holder: Holder,
                 motion_range: MotionRange | None = None, slack: float = 0.5) -> PoseEstimate:
    """Initial pose with the sphere direction estimate (module doc), correspondence-free.

    Parameters
    ----------
    points_px : (20, 2) observed corners in contour order (unknown start and direction).
    camera, holder : the camera model and the holder geometry.
    motion_range : the known pose range (default: the synthetic protocol's wide range).
    slack : candidates outside the range by up to this fraction of the half widths are kept
        (the initial pose itself is noisy).

    Returns
    -------
    PoseEstimate
        ``residual_px`` is the chamfer RMS; ``candidates`` are the admissible poses, best
        first (the X/Y mislabelled twin among them).
    """
    return _initial("initial", points_px, camera, holder, motion_range or MotionRange(),
                    "sphere", slack)


def initial_pose_paper(points_px, camera: Camera, holder: Holder,
                       motion_range: MotionRange | None = None,
                       slack: float = 0.5) -> PoseEstimate:
    """The paper's initial pose: image-plane geometric median of pairwise vanishing points."""
    return _initial("initial-paper", points_px, camera, holder, motion_range or MotionRange(),
                    "paper", slack)


def solve(points_px, camera: Camera, model: Holder) -> PoseEstimate:
    """Registered method ``initial``: ``solve(points_px, camera, model) -> PoseEstimate``."""
    return initial_pose(points_px, camera, model)


def solve_paper(points_px, camera: Camera, model: Holder) -> PoseEstimate:
    """Registered method ``initial-paper``."""
    return initial_pose_paper(points_px, camera, model)


class Initial(ContourMethod):
    name = "initial"
    description = "initial pose from vanishing points and contour area (paper 2.2)"
    solve = staticmethod(solve)


class InitialPaper(ContourMethod):
    name = "initial-paper"
    description = "initial pose, the paper's image-plane vanishing-point median"
    solve = staticmethod(solve_paper)
