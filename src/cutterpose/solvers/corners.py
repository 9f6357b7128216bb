"""The detected corners against the holder model at a pose, and the corner methods' error
budget and check (``dm``, ``dm+``, ``initial``, the PnP methods:
:class:`cutterpose.solvers.method.CornerMethod`).

Correspondences for the PnP methods ("contour order"): the contour gives the corners in order up
to a cyclic shift and a direction. The direction is fixed by the sign of the polygon's area
(the holder is always seen from its front, so the image polygon turns the same way as the model
projected at the nominal pose), the shift by comparing the corner-to-corner vectors, normalised
by the perimeter, with those of the model at the nominal pose: within the working range
(+-10 deg, holder X axis along the image rows) this separates the holder's 180 deg symmetric
assignments, and the edge lengths separate the others (:func:`order_for_model`).

Per-DOF standard deviation (Gauss-Newton covariance at the estimate): with ``r`` the 40 residuals
(detected minus projected ideal pixels, corners matched by the best cyclic assignment) and ``J``
their Jacobian with respect to ``(alpha, beta, gamma, X, Y, Z)``,

    s^2 = |r|^2 / (40 - 6),        Cov = s^2 (J^T J)^-1,        std = sqrt(diag Cov).

The corner methods' budget (:func:`corner_budget`) holds that ``noise``; ``method``, the step
``d`` from the pose to the corners' least-squares pose (:func:`fit_offset`; a pose that does not
minimise the residuals, as ``dm``'s search or a linear PnP, is off by it), as 1 sigma of
``2 d / 3``; ``wear``, the square of the pose shift the edges' measured darkening may cause
(:func:`edge_wear_effect`); and ``edge break``, the break they cannot measure: the seen edge
lies anywhere from the design edge to ``b`` outside it (``b = QualityLimits.edge_break_mm``,
1.5 mm when not known), taken as ``s s^T`` with ``s`` the pose shift of a uniform outward offset
``b / 3`` (:func:`edge_break_effect`: its 3 sigma is the shift of the whole range, a bound rather
than a spread, since the seen edge's offset is one-sided and not corrected).

Convention:
    Pose as in :mod:`cutterpose.geometry.pose` (holder in camera frame, mm, Z-Y-X Euler angles in
    deg). Pixels: ``corners_px`` are observed (distorted) image pixels; residuals are in ideal
    pixels.
"""

from __future__ import annotations

import math
from typing import TYPE_CHECKING

import numpy as np

from ..budget import ErrorBudget, budget_from_dof_cov
from ..geometry.camera import Camera
from ..geometry.holder import Holder
from ..geometry.pose import Pose, pixel_jacobian, rotation_from_euler_deg
from ..verdict import Quality, QualityLimits
from .estimate import PoseEstimate

if TYPE_CHECKING:
    from ..image import Features

__all__ = ["order_for_model", "edge_wear_effect", "edge_break_effect", "fit_offset", "pose_std",
           "ambiguity_ratio", "worst_line_residual", "has_corners", "corner_budget",
           "corner_review"]


def order_for_model(corners_px: np.ndarray, camera: Camera, holder: Holder) -> np.ndarray:
    """Reorder corners from contour order (unknown start and direction) to ``holder.json``
    order, from the image alone (module doc).

    Returns
    -------
    (N, 2) the same corners, ``out[i]`` the image of model corner ``i``.
    """
    c = np.asarray(corners_px, float)
    nominal = camera.project(Pose.nominal().apply(holder.points_holder_mm))

    def area(p):
        return np.dot(p[:, 0], np.roll(p[:, 1], -1)) - np.dot(np.roll(p[:, 0], -1), p[:, 1])

    if np.sign(area(c)) != np.sign(area(nominal)):
        c = c[::-1]
    e_det = np.roll(c, -1, axis=0) - c
    e_nom = np.roll(nominal, -1, axis=0) - nominal
    e_det = e_det / np.linalg.norm(e_det, axis=1).sum()
    e_nom = e_nom / np.linalg.norm(e_nom, axis=1).sum()
    n = len(c)
    cost = [np.sum((np.roll(e_det, -k, axis=0) - e_nom) ** 2) for k in range(n)]
    return np.roll(c, -int(np.argmin(cost)), axis=0)


def _match_to_projection(ideal: np.ndarray, proj: np.ndarray,
                         order: str = "contour") -> np.ndarray:
    """Detected ideal corners reordered (cyclic shift and direction) to best fit ``proj``.
    In ``"holder"`` order (field chain: known correspondences, NaN rows for the corners not
    seen) they are returned as they are."""
    if order == "holder":
        return np.asarray(ideal, float)
    best, best_cost = ideal, np.inf
    for seq in (ideal, ideal[::-1]):
        for k in range(len(seq)):
            cand = np.roll(seq, -k, axis=0)
            cost = np.sum((cand - proj) ** 2)
            if cost < best_cost:
                best, best_cost = cand, cost
    return best


def _project_ideal(dof: np.ndarray, camera: Camera, holder: Holder) -> np.ndarray:
    R = rotation_from_euler_deg(*dof[:3])
    X = holder.points_holder_mm @ R.T + dof[3:]
    x = X[:, :2] / X[:, 2:3]
    K = camera.K
    return x @ K[:2, :2].T + K[:2, 2]


def _jacobian(pose: Pose, camera: Camera, holder: Holder) -> np.ndarray:
    """(2N, 6) Jacobian of the ideal pixels w.r.t. the DOFs (analytic, :func:`pixel_jacobian`)."""
    return pixel_jacobian(pose.R, pose.t_mm, holder.points_holder_mm, camera.K)[0]


def edge_wear_effect(pose: Pose, features: Features, camera: Camera, holder: Holder
                     ) -> tuple[np.ndarray, float]:
    """Pose shift (6,) if every line moved inwards by the median of the lines' possible wear
    offsets (``features.edge_offset_px``), linearised at ``pose``; and that offset (px).

    The residuals cannot show this: a uniform offset of the edges is close to a change of scale
    (depth), so the shift is a systematic error the residual-based std misses.
    """
    off = features.edge_offset_px
    if off is None or features.inward_ideal is None or not np.any(np.isfinite(off)):
        return np.zeros(6), 0.0
    # wear acts on the whole outline: the median offset, moved uniformly (one line darkened by
    # an occluder or a stain beside it is not wear, and the corner checks see local defects)
    off = np.full(len(off), float(np.nanmedian(off)))
    from ..image.edges import intersect_consecutive

    L = np.array(features.lines_ideal, float)
    # moving the line by off along the inward normal n: c' = c - off (a, b) . n
    L[:, 2] -= off * (L[:, :2] * features.inward_ideal).sum(axis=1)
    moved = intersect_consecutive(L)
    if features.order == "holder":  # corner i: lines i - 1 and i (NaN where not seen)
        moved = np.roll(moved, 1, axis=0)
    elif not np.all(np.isfinite(moved)):
        return np.full(6, np.nan), float(np.median(off))
    dof = pose.dof
    proj = _project_ideal(dof, camera, holder)
    J = _jacobian(pose, camera, holder)
    a = _match_to_projection(np.asarray(features.corners_ideal_px, float), proj, features.order)
    b = _match_to_projection(moved, proj, features.order)
    seen = np.repeat(np.isfinite(a).all(axis=1) & np.isfinite(b).all(axis=1), 2)
    shift = np.linalg.lstsq(J[seen], (b - a).ravel()[seen], rcond=None)[0]
    return np.abs(shift), float(np.median(off))


def edge_break_effect(pose: Pose, camera: Camera, holder: Holder, seen: np.ndarray,
                      offset_mm: float, J: np.ndarray | None = None) -> np.ndarray:
    """Signed pose shift (6,: deg, mm) of a corner method's fit when every pocket edge is seen
    ``offset_mm`` outside the design edge, linearised at ``pose`` over the ``seen`` corners.

    A broken edge (fillet or chamfer of size ``b``) images its intensity step somewhere
    between the design edge and the break's line on the face, ``b`` outside it, depending on
    the light and the view (issue 10): the corners of the seen lines are the design corners
    moved by ``offset (o_(i-1) + o_i)`` (:func:`cutterpose.image.edge_model.model_corners_mm`).
    A uniform offset is nearly a change of scale: at 600 mm, 1 mm moves the depth by ~4.5 mm,
    and at a 10 deg tilt the tilt by ~0.7 deg (``docs/RESULTS.md``, section 11). ``J``: the
    (2N, 6) :func:`_jacobian` at ``pose`` when already computed.
    """
    from ..image.edge_model import model_corners_mm

    dof = pose.dof
    seen = np.asarray(seen, bool)
    o_edge = holder.edge_normals
    outward = np.stack([np.roll(o_edge, 1, axis=0), o_edge], axis=1)
    moved = model_corners_mm(holder, np.full((holder.n_corners, 2), float(offset_mm)), outward)
    X = moved @ pose.R.T + pose.t_mm
    b = X[:, :2] / X[:, 2:3] @ camera.K[:2, :2].T + camera.K[:2, 2]
    a = _project_ideal(dof, camera, holder)
    J = _jacobian(pose, camera, holder) if J is None else J
    rows = np.repeat(seen, 2)
    return np.linalg.lstsq(J[rows], (b - a).ravel()[rows], rcond=None)[0]


def _corner_fit(pose: Pose, corners_ideal_px: np.ndarray, camera: Camera, holder: Holder,
                order: str = "contour") -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The corners against the model at ``pose``: which are seen (N,), the (2N, 6)
    :func:`_jacobian` of all of them, and the seen ones' residuals (n, 2: detected minus
    projected ideal px, model order)."""
    proj = _project_ideal(pose.dof, camera, holder)
    det = _match_to_projection(np.asarray(corners_ideal_px, float), proj, order)
    seen = np.isfinite(det).all(axis=1)
    return seen, _jacobian(pose, camera, holder), (det - proj)[seen]


def _least_squares_step(J_seen: np.ndarray, r: np.ndarray) -> np.ndarray:
    """(6,) Gauss-Newton step ``(J^T J)^-1 J^T r`` (NaN with fewer than 4 corners)."""
    if len(r) < 4:
        return np.full(6, np.nan)
    return np.linalg.lstsq(J_seen, r.ravel(), rcond=None)[0]


def fit_offset(pose: Pose, corners_ideal_px: np.ndarray, camera: Camera, holder: Holder,
               order: str = "contour") -> np.ndarray:
    """(6,) DOF step (deg, mm) from ``pose`` to the least-squares pose of the seen corners: one
    Gauss-Newton step, ``(J^T J)^-1 J^T r`` with ``r`` the residuals (detected minus
    projected ideal px). Near zero for a pose that minimises them (``dm+``, PnP + LM); NaN
    with fewer than 4 corners."""
    seen, J, r = _corner_fit(pose, corners_ideal_px, camera, holder, order)
    return _least_squares_step(J[np.repeat(seen, 2)], r)


def _noise_cov(J_seen: np.ndarray, r: np.ndarray) -> np.ndarray:
    """(6, 6) ``s^2 (J^T J)^-1`` (module doc), NaN when ``J`` is singular."""
    s2 = float(np.sum(r ** 2)) / max(r.size - 6, 1)
    try:
        return s2 * np.linalg.inv(J_seen.T @ J_seen)
    except np.linalg.LinAlgError:
        return np.full((6, 6), np.nan)


def _pose_cov(pose: Pose, corners_ideal_px: np.ndarray, camera: Camera, holder: Holder,
              order: str = "contour") -> tuple[np.ndarray, np.ndarray]:
    """(6, 6) ``s^2 (J^T J)^-1`` over the seen corners (module doc) and the residuals."""
    seen, J, r = _corner_fit(pose, corners_ideal_px, camera, holder, order)
    return _noise_cov(J[np.repeat(seen, 2)], r), r


def pose_std(pose: Pose, corners_ideal_px: np.ndarray, camera: Camera, holder: Holder,
             order: str = "contour") -> tuple[np.ndarray, np.ndarray]:
    """Per-DOF standard deviations from the residuals, ``s^2 (J^T J)^-1`` (module doc).

    ``order="holder"``: corners in model order, NaN rows (not seen) left out.

    Returns
    -------
    std : (6,) deg and mm.
    residuals : (n, 2) detected minus projected ideal pixels, model order (seen corners).
    """
    cov, r = _pose_cov(pose, corners_ideal_px, camera, holder, order)
    return np.sqrt(np.clip(np.diag(cov), 0, None)), r


def has_corners(features: Features) -> bool:
    """Whether ``features`` carry at least one detected corner."""
    return bool(np.isfinite(np.asarray(features.corners_px, float)).all(axis=1).any())


def ambiguity_ratio(est: PoseEstimate, corners_ideal_px, camera: Camera, holder: Holder,
                    min_rotation_deg: float = 1.0, order: str = "contour") -> float:
    """RMS residual of the best pose over that of the best *different* candidate (rotation
    at least ``min_rotation_deg`` away; the planar two-fold ambiguity); NaN without one."""
    from ..geometry.pose import geodesic_deg

    if not est or not est.candidates:
        return math.nan
    R0 = est.R_cam_holder
    others = [(R, t) for R, t in est.candidates
              if geodesic_deg(R0, np.asarray(R, float)) > min_rotation_deg]
    if not others:
        return math.nan

    def rms(R, t):
        dof = Pose(np.asarray(R, float), np.asarray(t, float).reshape(3)).dof
        proj = _project_ideal(dof, camera, holder)
        det = _match_to_projection(np.asarray(corners_ideal_px, float), proj, order)
        return float(np.sqrt(np.nanmean(np.sum((det - proj) ** 2, axis=1))))

    e0 = rms(R0, est.t_cam_holder_mm)
    e1 = min(rms(R, t) for R, t in others)
    return e0 / e1 if e1 > 0 else 1.0



def worst_line_residual(pose: Pose, features: Features, camera: Camera, holder: Holder
                        ) -> tuple[int, float]:
    """The seen edge line (field chain, holder order) farthest from the model edge projected at
    ``pose``: its index and the larger distance (ideal px) of the model edge's two ends from
    the line; ``(-1, 0.0)`` without seen lines."""
    L = np.asarray(features.lines_ideal, float)
    seen = np.asarray(features.lines_visible, bool) & np.isfinite(L).all(axis=1)
    if not seen.any():
        return -1, 0.0
    q = _project_ideal(pose.dof, camera, holder)
    a, b = q, np.roll(q, -1, axis=0)                 # edge k runs from corner k to k + 1
    n = L[:, :2] / np.linalg.norm(L[:, :2], axis=1, keepdims=True)
    off = L[:, 2] / np.linalg.norm(L[:, :2], axis=1)
    d = np.maximum(np.abs(np.sum(n * a, axis=1) + off), np.abs(np.sum(n * b, axis=1) + off))
    d = np.where(seen, d, -np.inf)
    k = int(np.argmax(d))
    return k, float(d[k])



def corner_budget(estimate: PoseEstimate, features: Features, camera: Camera, holder: Holder,
                  limits: QualityLimits) -> ErrorBudget:
    """The corner methods' error budget at ``estimate``'s pose (module doc): ``noise``,
    ``method``, ``wear`` and ``edge break``, with the seen corners' residuals."""
    pose = estimate.pose
    bias, _ = edge_wear_effect(pose, features, camera, holder)
    seen, J_all, r = _corner_fit(pose, features.corners_ideal_px, camera, holder, features.order)
    J_seen = J_all[np.repeat(seen, 2)]
    cov = _noise_cov(J_seen, r)
    parts = {"noise": np.where(np.isfinite(cov), cov, np.inf)}
    off_fit = _least_squares_step(J_seen, r)              # fit_offset
    if np.all(np.isfinite(off_fit)):
        # a method that does not minimise the corners' residuals (dm's search, the linear PnP)
        # is off their least-squares pose by more than the noise: that step d is an error of
        # its own (~0 for dm+ and the +lm methods). As 1 sigma of 2/3 d, the 3-sigma figure
        # sqrt(9 s^2 + 4 d^2) is at least |d| + 3 s whenever |d| >= 2 s (s the noise's sigma),
        # and within 10 % of it below
        parts["method"] = (4.0 / 9.0) * np.outer(off_fit, off_fit)
    if bias is not None and np.all(np.isfinite(bias)):
        # a systematic error the residuals do not show
        parts["wear"] = np.diag(bias ** 2)
    brk = limits.assumed_edge_break_mm
    if brk > 0:
        # the seen edge lies 0..brk outside the design edge, the pose bias with it: a 1 sigma of
        # brk / 3 makes the 3-sigma figure that whole range's shift (rank one: the one offset
        # moves every DOF)
        s = edge_break_effect(pose, camera, holder, seen, brk / 3.0, J_all)
        parts["edge break"] = np.outer(s, s)
    return budget_from_dof_cov(parts, pose.dof, limits.grasp_point_mm, limits.tolerance,
                               residuals_px=r)


def corner_review(name: str, quality: Quality, estimate: PoseEstimate, features: Features,
                  camera: Camera, holder: Holder, limits: QualityLimits) -> Quality:
    """The corner method ``name``'s own checks after the verdict: a refusal the edge break alone
    causes says what would make the pose measurable; and on the field chain every seen edge,
    with or without its corners, must lie on the model at an accepted pose (the corners may
    fit a wrong pose when few are seen: dm and dm+ need no correspondences)."""
    q = quality
    b = q.budget
    brk = b.per_part_3sigma.get("edge break") if b is not None else None
    tol = limits.tolerance
    if not q.ok and brk is not None and (brk[0] > tol.position_mm or brk[1] > tol.angle_deg):
        # the break alone exceeds the tolerance: say what would make it measurable
        q.reason += (f" ({name} sees the broken edge, not the design edge: a break up to "
                     f"{limits.assumed_edge_break_mm:g} mm; dm+b measures it, or give the "
                     "holder's break, 0 for a sharp edge)")
    if q.ok and estimate and features.order == "holder":
        k, off = worst_line_residual(estimate.pose, features, camera, holder)
        if off > limits.max_corner_residual_px:
            q.ok, q.reason = False, (f"pocket edge {k} is {off:.1f} px off the model at this "
                                     f"pose (> {limits.max_corner_residual_px} px): the corners "
                                     "fit a wrong pose")
    return q
