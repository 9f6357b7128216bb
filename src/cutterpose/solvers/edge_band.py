"""``dm+b``: the pose of the design edge from the measured band of the broken edge (issue 10).

The pose of the pocket outline's homography is the start on the field chain (``dm+``'s from
the corners on the paper's chain; both follow the innermost rise, biased by the edge break,
which the band's scan of radius and shift and its second pass take up); the band across
every edge segment is then fitted with the edge model (:mod:`cutterpose.image.edge_band`),
which puts a point on the *design* edge's image (the sharp intersection of face and wall) per
segment, and the pose minimises

    sum_s rho( n_s . (pi(R X_s + t) - p_s) )

over the six DOFs: ``X_s`` the segment's centre on the design edge (holder frame, ``Z = 0``),
``p_s`` its measured image (ideal px), ``n_s`` the edge's outward image normal, ``rho`` the
soft-L1 loss (a segment under slurry or on a chip is an outlier), scaled by the residuals' MAD.
Two passes: the first on half the segments chooses the look (shape, photometry, blur) and
brings the pose to within a fraction of a millimetre; the second samples again at that pose
(the sampling lines follow it) on all segments with the chosen and plausible looks.

The error budget (:mod:`cutterpose.budget`) gets these parts:

* ``noise``: the weighted fit's covariance with the residuals split into a part each edge's
  segments share and an independent part (:func:`edge_noise_cov`; both contain the variation
  of the break along the contour, which the model does not know: the residuals of one edge
  run together, 0.23 px between edges against 0.12 px within on new holders);
* ``edge model``: the poses of the other plausible looks (shape and photometry the profile fit
  cannot rule out), mean of their outer products about the chosen pose; with a look calibrated
  in the cell (:mod:`cutterpose.calibration.edge_look`) also the pose change for a uniform
  shift by the design-edge offsets' scatter measured over its reference images, and for the
  calibrated offset and depth moved along the main axes of their joint covariance (each
  segment by the offset minus the depth times its view lean);
* ``model floor``: the pose change for a uniform outward shift of every design point by
  :data:`SHIFT_FLOOR_MM` (the profile model's systematic error that no alternative look
  shows: a uniform shift is what the pose cannot tell from depth). Not with a calibrated look
  whose offsets were measured at known poses at this distance and on breaks like this one
  (``DesignEdgeOffsets.covers``): their
  scatter (in ``edge model``) is that error measured, where the floor guesses it (counting both
  would count it twice); farther or nearer than the reference poses the floor stays;
* ``calibration extrapolated``: where the calibration does not cover the pose (as above), the
  pose change for leaving its correction out (each segment's ``offset - depth tan(theta)``),
  as 1 sigma: how the correction carries beyond its reference poses and breaks was not
  measured, and its depth part moves the segments unevenly (a tilt: on an approach from 900
  mm the calibrated full measurement was 0.14 deg off in beta beyond 3 of its std on a third
  of the frames without this part).

Convention:
    Pose DOFs of :mod:`cutterpose.geometry.pose` (alpha, beta, gamma [deg], X, Y, Z [mm],
    ``x_cam = R x_holder + t``); pixels ideal (undistorted) of ``camera.K``.

References:
    Seed paper, sections 2.1-2.3; Triggs et al., "Bundle adjustment - a modern synthesis"
    (2000), section 6 (robust point-to-line costs); Huber (1964).
"""

from __future__ import annotations

import math
import time
from dataclasses import dataclass
from typing import NamedTuple

import numpy as np

from ..budget import ErrorBudget, budget_from_dof_cov
from ..errors import CutterposeError, InputError
from ..geometry.camera import Camera
from ..geometry.holder import Holder
from ..geometry.pose import Pose, pose_from_plane_homography, rotation_from_euler_deg
from ..image import edge_model as em
from ..image.edge_band import BandFit, BandLooks, fit_band, sample_band, view_lean
from ..verdict import Quality, QualityLimits, verdict
from .dm import DmPlus
from .estimate import PoseEstimate
from .method import RefinementMethod

__all__ = ["BandPose", "EdgeBand", "as_band_looks", "band_budget", "band_verdict", "design_pose",
           "edge_noise_cov", "fit_pose_design_points", "measure_band", "outline_start",
           "refine_features", "solve", "variance_components", "SHIFT_FLOOR_MM"]

#: the band model's systematic uncertainty as a uniform outward shift of the design edge (mm
#: in the face plane, 1 sigma): on the development pbr sets at ~4 px/mm the design edge of
#: round fillets came out 0.2 px (0.05 mm) outside on average (Blinn-Phong against the
#: renderer's microfacet steel), of chamfers 0.05 px, of worn fillets 0.15 px inside
SHIFT_FLOOR_MM = 0.04
#: the soft-L1 scale of the whitened residuals (a segment beyond ~2 sigma is down-weighted)
ROBUST_SCALE = 2.0
#: the least std (px) a segment's design-edge point is given (the variance from the profile
#: fit knows the noise, not the model's local error)
MIN_SD_PX = 0.1
#: the robust pose fit's iteration limit and its converged step (deg and mm alike: far below
#: either's precision)
IRLS_MAX_ITER = 50
IRLS_STEP_TOL = 1e-6
#: sampling + fit passes (the last on all segments, the first on half)
PASSES = 2
#: segments per edge and normals per segment sampled across the band
SEGMENTS_PER_EDGE = 4
POSITIONS_PER_SEGMENT = 12
#: fewest valid segments for a pose (of 20 x SEGMENTS_PER_EDGE: 30 %)
MIN_SEGMENT_FRACTION = 0.3


@dataclass
class BandPose:
    """What :func:`measure_band` found (for the budget, the JSON and the overlay)."""

    dof: np.ndarray
    cov_parts: dict
    fit: BandFit
    residuals_px: np.ndarray      # (S,) along the normals, NaN for invalid segments
    weights: np.ndarray           # (S,) robust weights (0: not used)
    chi: float                    # root of the weighted chi-square per degree of freedom
    passes: int
    calibrated: bool = False      # the look was calibrated in the cell (BandLooks)
    #: the calibration's measured offset scatter stands for the model floor here (it has an
    #: offset for this shape, and its reference poses and breaks cover this distance and
    #: radius, ``DesignEdgeOffsets.covers``); None without a calibration
    calibration_covers: bool | None = None
    #: the weighted residuals' spread (px, 1 sigma) within an edge and of a part each edge's
    #: segments share (:func:`variance_components`): a large shared part says the edges
    #: disagree as wholes (a look or a break that the model does not fit on some edges)
    residual_within_edge_px: float = math.nan
    residual_shared_per_edge_px: float = math.nan

    @property
    def radius_mm(self) -> float:
        return self.fit.radius_median_mm

    def to_dict(self) -> dict:
        b = self.fit.best
        v = self.fit.profiles.valid
        return {"shape": b.look.shape, "blur_px": b.look.blur_sigma_px,
                "radius_median_mm": round(self.radius_mm, 3),
                "radius_per_segment_mm": [None if not ok else round(float(r), 3)
                                          for r, ok in zip(b.radius_mm, v)],
                "segments_used": int(np.count_nonzero(self.weights > 0.5)),
                "segments_valid": int(v.sum()), "residual_chi": round(self.chi, 3),
                "residual_within_edge_px": round(self.residual_within_edge_px, 3),
                "residual_shared_per_edge_px": round(self.residual_shared_per_edge_px, 3),
                "plausible_looks": len(self.fit.plausible), "passes": self.passes,
                "look": {"calibrated": self.calibrated,
                         "calibration_covers": self.calibration_covers,
                         "specular": b.look.specular,
                         "shininess": b.look.shininess, "face_albedo": b.look.face_albedo,
                         "wall_albedo": b.look.wall_albedo,
                         "pocket_level": b.look.pocket_level}}


def _residuals(dof, X, p, n, K):
    R = rotation_from_euler_deg(*dof[:3])
    Xc = X @ R.T + dof[3:]
    q = (Xc[:, :2] / Xc[:, 2:]) @ K[:2, :2].T + K[:2, 2]
    return np.sum((q - p) * n, axis=1)


def _jacobian(dof, X, n, K) -> np.ndarray:
    """(S, 6) derivative of :func:`_residuals` by the DOFs, in closed form: with
    ``R = Rz(gamma) Ry(beta) Rx(alpha)``, ``dR/dalpha = R [e_x]x``, ``dR/dbeta =
    R [Rx^T e_y]x``, ``dR/dgamma = [e_z]x R`` (per radian), and the projection's
    ``d(x/z, y/z)/dXc`` (cross products written out: these are 3-vectors per point)."""
    R = rotation_from_euler_deg(*dof[:3])
    RX = X @ R.T
    x, y, z = (RX + dof[3:]).T
    nk = n @ K[:2, :2]                                                  # (S, 2)
    g = np.column_stack([nk[:, 0] / z, nk[:, 1] / z,
                         -(nk[:, 0] * x + nk[:, 1] * y) / z ** 2])      # (S, 3) dr / dXc
    a = math.radians(dof[0])
    c, s_ = math.cos(a), math.sin(a)                                    # Rx^T e_y = (0, c, -s)
    X0, X1, X2 = X.T
    w_a = np.column_stack([np.zeros_like(X0), -X2, X1])                 # e_x x X
    w_b = np.column_stack([c * X2 + s_ * X1, -s_ * X0, -c * X0])        # (0, c, -s) x X
    w_g = np.column_stack([-RX[:, 1], RX[:, 0], np.zeros_like(X0)])     # e_z x (R X)
    k = math.pi / 180.0
    gR = g @ R                                                          # dr / d(X before R)
    J = np.empty((len(X), 6))
    J[:, 0] = k * np.sum(gR * w_a, axis=1)
    J[:, 1] = k * np.sum(gR * w_b, axis=1)
    J[:, 2] = k * np.sum(g * w_g, axis=1)
    J[:, 3:] = g
    return J


def fit_pose_design_points(points_ideal_px, normals, points_holder_mm, K, dof0,
                           sd_px=None, f_scale: float = ROBUST_SCALE):
    """Robust point-to-line pose (module doc).

    Parameters
    ----------
    sd_px : (S,) each point's std along its normal (px; default 1 for all): the residuals are
        whitened by it, and ``f_scale`` (soft-L1) is in those units.

    Returns
    -------
    dof, J, residuals_px, weights, chi : ``J`` (S, 6) the whitened residuals' Jacobian at
        the solution (not weighted: :func:`edge_noise_cov` takes it with the soft-L1
        ``weights``), ``chi`` the root of the weighted chi-square per degree of freedom.
    """
    p = np.asarray(points_ideal_px, float)
    n = np.asarray(normals, float)
    X = np.asarray(points_holder_mm, float)
    if len(p) < 6:
        raise InputError(f"fit_pose_design_points: {len(p)} points, at least 6 needed")
    sd = np.ones(len(p)) if sd_px is None else np.asarray(sd_px, float)
    dof0 = np.asarray(dof0, float)

    x, z, w = _irls_soft_l1(dof0, X, p, n, K, sd, f_scale)
    J = _jacobian(x, X, n, K) / sd[:, None]
    dof_n = max(int(np.count_nonzero(w > 0.5)) - 6, 1)
    chi = math.sqrt(float(np.sum(w * z ** 2) / dof_n))
    return x, J, z * sd, w, chi


def _soft_l1_cost(z, c: float) -> float:
    return float(np.sum(2.0 * c * c * (np.sqrt(1.0 + (z / c) ** 2) - 1.0)))


def _irls_soft_l1(dof0, X, p, n, K, sd, c: float, max_iter: int = IRLS_MAX_ITER):
    """Minimise ``sum rho(z_s)``, ``z_s`` the whitened point-to-line residuals and ``rho`` the
    soft-L1 loss ``2 c^2 (sqrt(1 + (z / c)^2) - 1)``, by Gauss-Newton with the loss's own
    curvature.

    With ``u = (z / c)^2`` the gradient is ``2 J^T W z``, ``W = diag((1 + u)^-1/2)`` (the IRLS
    weights), and the Gauss-Newton Hessian ``2 J^T W' J`` with ``W' = diag(rho' + 2 rho'' z^2)
    = diag((1 + u)^-3/2)`` (Triggs et al. 2000, section 6: the robustified Hessian; positive
    here, unlike a Huber's or Cauchy's, so the system stays positive definite). That converges
    in a few steps near the minimum, where plain reweighting (``W`` in both) crawls; far from
    it, where the loss's curvature all but vanishes, the reweighting step is the better one:
    each iteration tries both, halves each until it lowers the cost, and keeps the lower. The
    minimum is the one SciPy's trust-region solver finds (tested); written out because on ~80
    points and 6 unknowns that solver's per-call overhead was most of the pose fit's time.

    Returns ``(dof, z, w)`` at the solution.
    """
    x = np.asarray(dof0, float).copy()
    z = _residuals(x, X, p, n, K) / sd
    cost = _soft_l1_cost(z, c)
    for _ in range(max_iter):
        w = 1.0 / np.sqrt(1.0 + (z / c) ** 2)
        J = _jacobian(x, X, n, K) / sd[:, None]
        g = -(J.T @ (w * z))
        best = None
        # the robustified step, and the reweighting one (better far from the minimum, where
        # the curvature of the loss all but vanishes): the lower cost of the two, halved
        # until it descends
        for wh in (w ** 3, w):
            try:
                step = np.linalg.solve((J * wh[:, None]).T @ J, g)
            except np.linalg.LinAlgError:
                raise InputError("fit_pose_design_points: the design-edge points do not fix "
                                 "the pose (degenerate geometry)") from None
            for _half in range(12):
                z_new = _residuals(x + step, X, p, n, K) / sd
                cost_new = _soft_l1_cost(z_new, c)
                if cost_new <= cost:
                    break
                step = 0.5 * step
            else:
                continue
            if best is None or cost_new < best[2]:
                best = (step, z_new, cost_new)
        if best is None:
            break                                       # no descent left: at the minimum
        step, z, cost_new = best
        x = x + step
        done = cost - cost_new <= 1e-10 * max(cost, 1.0)
        cost = cost_new
        if done or np.all(np.abs(step) <= IRLS_STEP_TOL):
            break
    w = 1.0 / np.sqrt(1.0 + (z / c) ** 2)
    return x, z, w


def variance_components(e, edge, n_params: int = 6) -> tuple[float, float]:
    """``(s_w^2, s_u^2)``: the variance of residuals ``e`` (S,) within a group (``edge`` (S,))
    and that of a part shared by a group, from the one-way ANOVA of a fit's residuals
    (:func:`edge_noise_cov`): ``s_w^2`` the pooled within-group mean square, ``s_u^2 =
    max(0, (MS_b - s_w^2) / n_0)`` with ``MS_b`` the groups' mean squares about zero on
    ``E - n_params`` degrees of freedom (the fit's parameters absorb group-level patterns) and
    ``n_0 = (N - sum n_e^2 / N) / (E - 1)``. ``s_u^2 = 0`` with ``n_params + 1`` groups or
    fewer.

    References:
        Searle, Casella, McCulloch, *Variance Components* (1992), ch. 3.
    """
    e = np.asarray(e, float)
    labels, idx = np.unique(np.asarray(edge), return_inverse=True)
    E, N = len(labels), len(e)
    n_e = np.bincount(idx, minlength=E).astype(float)
    mean_e = np.bincount(idx, weights=e, minlength=E) / n_e
    s_w2 = float(np.sum((e - mean_e[idx]) ** 2)) / max(N - E, 1)
    s_u2 = 0.0
    if E > n_params + 1 and N > E:
        ms_b = float(np.sum(n_e * mean_e ** 2)) / (E - n_params)
        n0 = (N - float(np.sum(n_e ** 2)) / N) / (E - 1)
        s_u2 = max(0.0, (ms_b - s_w2) / max(n0, 1.0))
    return s_w2, s_u2


def edge_noise_cov(J, z, w, edge) -> np.ndarray:
    """(6, 6) covariance of the pose fitted to design-edge points whose errors share a part
    per edge (variance components: a random effect per edge).

    At its solution the robust fit is a weighted least-squares fit with the soft-L1 weights
    ``w``: with ``e = sqrt(w) z`` (``z`` (S,) the whitened residuals) and ``Jt = sqrt(w) J``
    (``J`` (S, 6) the whitened Jacobian) the pose is ``(Jt^T Jt)^-1 Jt^T e``, so its covariance
    is ``A^-1 Jt^T V Jt A^-1``, ``A = Jt^T Jt``, ``V`` the covariance of ``e``. The ``e_s``
    are modelled as ``u_e + eps_s``: ``eps_s`` independent, variance ``s_w^2``, and one ``u_e``
    per edge (``edge`` (S,)), variance ``s_u^2``: what the segments of one edge share (the
    break's radius there, a chip, the light on that edge), both estimated from the residuals
    (:func:`variance_components`); the total per segment is kept >= 1 (the profile fits' own
    variances). Then
    ``Jt^T V Jt = s_w^2 A + s_u^2 sum_e g_e g_e^T``, ``g_e`` the sum of the edge's rows of
    ``Jt``.

    Independent segments (``s_u = 0``) give the weighted fit's usual ``s_w^2 A^-1``; a shared
    part gives more, as it must: four segments of one edge are not four independent looks at
    the pose.

    References:
        Cameron, Miller, "A practitioner's guide to cluster-robust inference", J. Human
        Resources 50 (2015) (clustered errors in a sandwich).
    """
    sw = np.sqrt(np.asarray(w, float))
    Jt = sw[:, None] * np.asarray(J, float)
    labels, idx = np.unique(np.asarray(edge), return_inverse=True)
    E = len(labels)
    s_w2, s_u2 = variance_components(sw * np.asarray(z, float), edge)
    s_w2 = max(s_w2, 1.0 - s_u2)
    g = np.zeros((E, J.shape[1]))
    np.add.at(g, idx, Jt)
    A = Jt.T @ Jt
    Ai = np.linalg.inv(A)
    return Ai @ (s_w2 * A + s_u2 * (g.T @ g)) @ Ai


def _sd(lf) -> np.ndarray:
    return np.maximum(np.sqrt(lf.shift_var_px2), MIN_SD_PX)


def design_pose(fit: BandFit, lf, K, dof0, valid=None) -> np.ndarray:
    """(6,) pose (dof) fitted from ``dof0`` to the design-edge points of the look fit ``lf``
    of ``fit`` (its ``valid`` segments with a finite shift variance, weighted by it); inf with
    fewer than 6 such segments."""
    bp = fit.profiles
    v = (bp.valid if valid is None else valid) & np.isfinite(lf.shift_var_px2)
    if v.sum() < 6:
        return np.full(6, np.inf)
    p = fit.design_points_px(lf)[v]
    return fit_pose_design_points(p, bp.normals_ideal[v], bp.points_holder_mm[v], K, dof0,
                                  _sd(lf)[v])[0]


def _look_spread(fit: BandFit, K, dof, valid) -> np.ndarray:
    """(6, 6) second moment of the plausible looks' poses about the chosen one, each weighted
    by its relative likelihood with the segments as independent observations of the look:
    ``w_l = (C_best / C_l)^(n / 2)``, ``n`` the segments in the trimmed cost (a BIC-style
    model average; the chosen look has ``w = 1`` and no deviation)."""
    if not fit.plausible:
        return np.zeros((6, 6))
    n = max(1, int(np.ceil(0.75 * int(valid.sum()))))
    d = np.array([design_pose(fit, lf, K, dof, valid) - dof for lf in fit.plausible])
    ratio = np.array([fit.best.total / lf.total for lf in fit.plausible])
    w = np.exp(0.5 * n * np.log(np.clip(ratio, 1e-12, 1.0)))
    return np.einsum("l,li,lj->ij", w, d, d) / (1.0 + w.sum())


class _Passes(NamedTuple):
    """The band's last pass: the pose fitted to the design-edge points and what it was fitted
    on (:func:`_fit_passes`)."""

    dof: np.ndarray
    fit: BandFit
    bp: object          # the sampled band (BandProfiles)
    valid: np.ndarray   # (S,) the segments the pose was fitted on
    J: np.ndarray
    r: np.ndarray
    w: np.ndarray
    s: float
    sd: np.ndarray
    passes: int


def _fit_passes(image, camera: Camera, holder: Holder, dof, edges_seen, shapes,
                max_passes: int, looks) -> _Passes | str:
    """Sample the band at ``dof`` and fit the pose to its design-edge points, ``max_passes``
    times (module doc); the last pass, or why the band cannot be measured."""
    K = camera.K
    fit = None
    for passes in range(1, max_passes + 1):
        R = rotation_from_euler_deg(*dof[:3])
        # the first pass (look choice, the pose to within a fraction of a millimetre) on half
        # the segments; the last on all of them with the looks chosen
        last = passes == max_passes
        n_seg = SEGMENTS_PER_EDGE if last else max(1, SEGMENTS_PER_EDGE // 2)
        bp = sample_band(image, camera, holder, R, dof[3:], edges_seen, n_seg=n_seg,
                         positions=POSITIONS_PER_SEGMENT * SEGMENTS_PER_EDGE // n_seg)
        valid = bp.valid.copy()
        if valid.sum() < MIN_SEGMENT_FRACTION * len(valid):
            return (f"the edge band was measured on {int(valid.sum())} of {len(valid)} edge "
                    f"segments (< {100 * MIN_SEGMENT_FRACTION:.0f} %): edges hidden")
        fit = fit_band(bp, camera, holder, R, dof[3:], shapes,
                       previous=fit if passes > 1 else None, fine_plausible=last, looks=looks)
        valid &= np.isfinite(fit.best.cost) & np.isfinite(fit.best.shift_var_px2)
        if valid.sum() < MIN_SEGMENT_FRACTION * len(valid):
            return (f"the band's profile fixes the design edge on {int(valid.sum())} of "
                    f"{len(valid)} edge segments only: edges hidden or featureless")
        p = fit.design_points_px()[valid]
        sd = _sd(fit.best)[valid]
        dof, J, r, w, s = fit_pose_design_points(
            p, bp.normals_ideal[valid], bp.points_holder_mm[valid], K, dof, sd)
    return _Passes(dof, fit, bp, valid, J, r, w, s, sd, passes)


def _calibration_parts(st: _Passes, K, holder: Holder, looks, cov_model: np.ndarray
                       ) -> tuple[np.ndarray, dict, bool | None]:
    """With a look calibrated in the cell (module doc, ``edge model``, ``model floor``,
    ``calibration extrapolated``): the edge-model covariance with the calibration's parts,
    the parts that replace or extend the model floor, and whether the calibration covers this
    pose (None without one)."""
    fit, bp, valid, dof = st.fit, st.bp, st.valid, st.dof

    def moved(shift) -> np.ndarray:
        """The pose change for an outward shift of every design point (mm, or per segment)."""
        return design_pose(fit, fit.best.moved(shift, bp.px_per_mm), K, dof, valid) - dof

    off = looks.offsets if looks is not None else None
    shape = fit.best.look.shape
    sc = dict(off.scatter_mm).get(shape) if off is not None else None
    lean = None
    if off:
        lean = view_lean(em.edge_views(rotation_from_euler_deg(*dof[:3]), dof[3:], K, holder),
                         bp.edge, bp.frac)
    if off is not None:
        # a calibrated look: the scatter of the design-edge offset over the reference images
        # (measured at their known poses) is this image's remaining look error
        if sc:
            d_s = moved(sc)
            cov_model = cov_model + np.outer(d_s, d_s)
        # and the calibrated offset's and depth's own uncertainty, jointly (they correlate
        # through the segments' mean lean): the pose change along each main axis of their
        # covariance, each segment moved by offset - depth x its view lean
        cov_od = dict(off.cov_mm2).get(shape)
        if cov_od is not None:
            val, vec = np.linalg.eigh(np.asarray(cov_od, float))
            for lam, u in zip(val, vec.T):
                if lam > 0:
                    o, d = math.sqrt(lam) * u
                    d_c = moved(o - d * lean)
                    cov_model = cov_model + np.outer(d_c, d_c)
    r_med = fit.radius_median_mm
    covers = None if off is None else bool(
        sc and off.covers(float(dof[5]), shape, r_med if np.isfinite(r_med) else None))
    parts = {}
    if not covers:
        # a uniform outward shift of the design edge by the model floor: what no look shows;
        # a calibration that measured the offsets' scatter at known poses at this distance
        # replaces the guess
        d_u = moved(SHIFT_FLOOR_MM)
        parts["model floor"] = np.outer(d_u, d_u)
        if off:
            # and its correction is extrapolated: how it carries to other distances or breaks
            # was not measured (its offset and depth, fitted at the reference poses, move each
            # segment by a different amount: a tilt as well as a depth), so the pose change
            # for leaving it out is 1 sigma of what it may be off by here
            d_x = moved(-off.offset(shape, lean))
            parts["calibration extrapolated"] = np.outer(d_x, d_x)
    return cov_model, parts, covers


def measure_band(image, camera: Camera, holder: Holder, start: PoseEstimate,
                 edges_seen=None, shapes=("round", "chamfer"), max_passes: int | None = None,
                 looks: BandLooks | None = None) -> PoseEstimate:
    """``dm+b`` from a start pose (module doc). A falsy estimate with the reason when the band
    cannot be measured. ``looks``: the edge look calibrated in the cell
    (:mod:`cutterpose.calibration.edge_look`) instead of the generic looks."""
    t0 = time.perf_counter()
    max_passes = PASSES if max_passes is None else max_passes
    if not start:
        return PoseEstimate.failure("dm+b", f"start: {start.reason}")
    try:
        st = _fit_passes(image, camera, holder, Pose(start.R_cam_holder,
                                                     start.t_cam_holder_mm).dof,
                         edges_seen, shapes, max_passes, looks)
    except CutterposeError as e:
        return PoseEstimate.failure("dm+b", f"edge band: {e}")
    if isinstance(st, str):
        return PoseEstimate.failure("dm+b", st)
    dof, valid, r, w = st.dof, st.valid, st.r, st.w
    try:
        # the segments' variances know the pixel noise; a larger scatter scales them up, and
        # what the segments of one edge share counts once per edge
        cov_noise = edge_noise_cov(st.J, r / st.sd, w, st.bp.edge[valid])
    except np.linalg.LinAlgError:
        cov_noise = np.full((6, 6), np.inf)
    cov_model, more, covers = _calibration_parts(st, camera.K, holder, looks,
                                                 _look_spread(st.fit, camera.K, dof, valid))
    parts = {"noise": cov_noise, "edge model": cov_model} | more
    res = np.full(len(valid), np.nan)
    res[valid] = r
    wt = np.zeros(len(valid))
    wt[valid] = w
    s_w2, s_u2 = variance_components(np.sqrt(w) * r, st.bp.edge[valid])
    band = BandPose(dof, parts, st.fit, res, wt, st.s, st.passes,
                    calibrated=looks is not None, calibration_covers=covers,
                    residual_within_edge_px=math.sqrt(s_w2),
                    residual_shared_per_edge_px=math.sqrt(s_u2))
    inl = w > 0.5
    rms = float(np.sqrt(np.mean(r[inl] ** 2))) if inl.any() else math.nan
    return PoseEstimate("dm+b", rotation_from_euler_deg(*dof[:3]), dof[3:].copy(),
                        residual_px=rms, time_ms=(time.perf_counter() - t0) * 1e3, band=band,
                        start=start)


def as_band_looks(edge_look) -> BandLooks | None:
    """What ``dm+b`` fits from what a caller holds: ``None`` (the generic looks), a
    :class:`~cutterpose.image.edge_band.BandLooks`, or a cell calibration (anything with a
    ``band_looks()``, e.g. :class:`cutterpose.calibration.edge_look.EdgeLookCalibration`)."""
    return edge_look.band_looks() if hasattr(edge_look, "band_looks") else edge_look


def refine_features(start: PoseEstimate, features, camera: Camera, model: Holder,
                    shapes=("round", "chamfer"), edge_look=None) -> PoseEstimate:
    """``dm+b`` on the image's features (:meth:`EdgeBand.refine`): the bands of every edge, in
    the image the features come from, from ``start`` (the outline's pose on the field chain,
    ``dm+``'s on the paper's). Every edge is sampled whether or not the line fits saw it: an
    edge under slurry or the cutter gives profiles that fit badly and weigh little (the robust
    pose fit), and the answer does not depend on whether the corners were detected at all
    (``measure`` skips them for ``dm+b``). ``edge_look``: a calibrated look
    (:class:`~cutterpose.image.edge_band.BandLooks`, or anything with a ``band_looks()``
    giving one: the calibration file's object)."""
    if features.image is None:
        return PoseEstimate.failure("dm+b", "the features carry no image to measure the band in")
    return measure_band(features.image, camera, model, start, None, shapes,
                        looks=as_band_looks(edge_look))


def solve(points_px, camera: Camera, model: Holder) -> PoseEstimate:
    """``dm+b`` on corners alone: the band needs the image, so this is a falsy estimate that
    says so (use :func:`cutterpose.pipeline.measure`)."""
    return PoseEstimate.failure("dm+b", "dm+b measures the band across the edges: it needs the "
                                "image (cutterpose.pipeline.measure / `cutterpose measure`)")


def outline_start(H_ideal_holder, camera: Camera, method: str = "outline"
                  ) -> PoseEstimate | None:
    """The pose of the pocket outline's homography (holder plane -> ideal px; Zhang's
    decomposition, :func:`~cutterpose.geometry.pose.pose_from_plane_homography`) as a start,
    or None when it is degenerate. Its residual is NaN: no corners were fitted."""
    rt = pose_from_plane_homography(H_ideal_holder, camera.K)
    if rt is None:
        return None
    return PoseEstimate(method, rt[0], np.asarray(rt[1], float))


def band_budget(band: BandPose, dof, limits: QualityLimits) -> tuple[ErrorBudget, np.ndarray]:
    """``dm+b``'s error budget at ``dof`` (the band fit's covariance parts, module doc) and its
    residuals: (M, 2) vectors (ideal px) along the edge normals of the inlier segments (dm+b
    has no corner residuals; they are also the budget's ``residuals_px``)."""
    inl = band.weights > 0.5
    r = band.residuals_px[inl, None] * band.fit.profiles.normals_ideal[inl]
    budget = budget_from_dof_cov(band.cov_parts, dof, limits.grasp_point_mm, limits.tolerance,
                                 band.radius_mm, residuals_px=r)
    return budget, r


def band_verdict(est: PoseEstimate, limits: QualityLimits) -> Quality:
    """The verdict on a ``dm+b`` estimate made without image features (the tracker's
    re-anchoring: :func:`measure_band` from a tracked pose): its residuals, working range and
    error budget, as :func:`cutterpose.pipeline.measure_features` judges it."""
    if not est:
        return verdict(est, None, limits)
    if est.band is None:
        return Quality(False, f"{est.method} carries no band fit to judge")
    return verdict(est, band_budget(est.band, est.pose.dof, limits)[0], limits)


class EdgeBand(RefinementMethod):
    """``dm+b`` (module doc): the design edge's pose from the band across every edge, from the
    pocket outline's pose (the field chain; no corners needed) or ``dm+``'s."""

    name = "dm+b"
    description = ("the band across every edge fitted with the edge model from the outline's "
                   "pose (dm+'s on the paper's chain): the design edge's pose (needs the image)")
    base = DmPlus
    needs_corners = False
    reanchors = True
    solve = staticmethod(solve)

    def first_start(self, features, camera) -> PoseEstimate | None:
        """The outline's pose (field chain): the band needs a start within a few pixels,
        which the outline fit gives without corners."""
        if features.order != "holder" or features.H_ideal_holder is None:
            return None
        return outline_start(features.H_ideal_holder, camera)

    def refine(self, start, features, camera, holder, context) -> PoseEstimate:
        return refine_features(start, features, camera, holder,
                               context.limits.edge_shape_fits, edge_look=context.edge_look)

    def budget(self, estimate, features, camera, holder, limits) -> ErrorBudget:
        return band_budget(estimate.band, estimate.pose.dof, limits)[0]
