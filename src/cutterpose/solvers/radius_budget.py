"""``dm+r``: the method (:class:`EdgeRadius`) and its error budget (:func:`budget_from_fit`).

The radius fit itself is :mod:`cutterpose.solvers.edge_radius`. The budget's contributions,
each a covariance of the estimate (the pose's six DOFs and the edge radius ``r``), summed
(then carried to the grasp point and judged as every budget is, :mod:`cutterpose.budget`):

* ``radius``: the linearised marginal-minus-conditional above, or, when larger, the spread of
  the pose over the radius scan's profile (another radius that fits nearly as well gives
  another depth: :func:`radius_profile_cov`);
* ``noise``: Gauss-Newton, ``chi2_red H^-1`` with ``H = J^T W^T W J`` (+ the radius prior), the
  corners whitened by their noise and the edge model's uncertainty at each corner
  (:func:`cutterpose.solvers.edge_radius.fit_pose_radius`); its pose block is the marginal over
  ``r``, so the radius estimate's variance is in it (``radius`` reports how much: marginal minus
  the conditional ``r``-known covariance);
* ``model``: the edge model's photometric spread: the offsets under each plausible light and
  material (:data:`cutterpose.image.edge_model.LOOK_VARIANTS`, and the other edge shape, fillet
  or chamfer) minus the nominal ones, pushed
  through the estimator's linear sensitivity ``G = H^-1 J^T W^T W`` (``b_j = G D dDelta_j``), as
  ``sum_j p_j b_j b_j^T``, with ``p_j`` the looks' posterior weights given the fit's residual
  (equal prior weights, nominal included with ``b = 0``; under look ``j`` the whitened residual
  would be ``-(I - P) m_j`` plus noise, ``m_j`` the look's whitened corner shift and ``P`` the
  projection onto the fit's columns, so ``p_j ~ exp(-|z + (I - P) m_j|^2 / (2 chi2_red))``);
  plus the rival rise of each edge end (half the gap to it where it is at least 0.6 of the
  edge's, per edge);
* ``edge_variation``: the radius is one per image but varies along a worn contour: independent
  per-edge offsets of std ``max(sigma_e, kappa r |slope_k|)``, ``sigma_e`` measured from the
  residuals (:func:`edge_variation_mm`) and a floor of ``kappa = 0.1`` (a tenth of the radius
  per edge; the measured part covers larger variations as far as the corners show them);

Convention:
    DOF covariances in (alpha, beta, gamma [deg], X, Y, Z [mm], r [mm]).

References:
    Kay, *Fundamentals of Statistical Signal Processing I* (1993), ch. 3 (Fisher information,
    the CRLB with nuisance parameters).
"""

from __future__ import annotations

import math
from dataclasses import replace

import numpy as np

from ..budget import ErrorBudget, Tolerance, budget_from_dof_cov
from ..image.edge_model import LOOK_VARIANTS
from .dm import DmPlus
from .edge_radius import model_offset_spread, per_edge_jacobian, refine_features, solve
from .method import RefinementMethod

__all__ = ["EdgeRadius", "budget_from_fit", "edge_variation_mm", "radius_profile_cov",
           "KAPPA_EDGE_VARIATION"]

KAPPA_EDGE_VARIATION = 0.1


class EdgeRadius(RefinementMethod):
    """``dm+r``: ``dm+``'s pose refined with one radius of the broken pocket edge from the
    corners alone (:func:`~cutterpose.solvers.edge_radius.refine_radius`): the design edge's
    pose."""

    name = "dm+r"
    description = "dm+ + the radius of the broken pocket edge: the design edge's pose"
    base = DmPlus
    solve = staticmethod(solve)

    def refine(self, start, features, camera, holder, context):
        return refine_features(start, features, camera, holder, context.limits.edge_shape_fits)

    def budget(self, estimate, features, camera, holder, limits) -> ErrorBudget:
        return budget_from_fit(estimate.radius_fit, camera, holder, limits.grasp_point_mm,
                               limits.tolerance)


def edge_variation_mm(fit, D_edge: np.ndarray) -> float:
    """The std (mm) of independent per-edge offsets that the fit's residuals show.

    With ``Q = I - J (J^T J)^-1 J^T`` (the fit's residual projector, 7 columns), the residual is
    ``Q (D e + n)``: ``e`` per-edge offsets (std ``sigma_e``), ``n`` corner noise (std
    ``sigma_c``). Split it on ``U = range(Q D)``: the part off ``U`` holds noise only,
    ``sigma_c^2 = |r_perp|^2 / tr(Q - P_U)``; the part on ``U`` gives
    ``sigma_e^2 = (|r_U|^2 - sigma_c^2 tr(P_U)) / tr(Q D D^T Q)`` (method of moments; the part
    of ``D e`` the pose and radius absorb is extrapolated from the visible part).
    """
    keep = np.repeat(fit.weights > 0, 2)        # corners not seen carry no residual
    J = (fit.jacobian * np.repeat(np.sqrt(fit.weights), 2)[:, None])[keep]
    r = (fit.residuals_px.ravel() * np.repeat(np.sqrt(fit.weights), 2))[keep]
    Dw = (D_edge * np.repeat(np.sqrt(fit.weights), 2)[:, None])[keep]
    Qj, _ = np.linalg.qr(J)
    Q = np.eye(len(r)) - Qj @ Qj.T
    QD = Q @ Dw
    U, sv, _ = np.linalg.svd(QD, full_matrices=False)
    U = U[:, sv > 1e-9 * sv.max()]
    rU = U.T @ r
    r_perp2 = float(r @ Q @ r - rU @ rU)
    dof_perp = float(np.trace(Q)) - U.shape[1]
    if dof_perp < 1:
        return 0.0
    s_c2 = r_perp2 / dof_perp
    num = float(rU @ rU) - s_c2 * U.shape[1]
    return float(np.sqrt(max(num, 0.0) / float(np.sum(QD * QD))))


def radius_profile_cov(fit) -> np.ndarray:
    """(6, 6) spread of the pose over the radius scan's profile (:class:`RadiusFit`
    ``profile``), weighted by ``exp(-(cost - cost_min) / (2 s_eff^2))`` with
    ``s_eff^2 = cost_min / (2N - 7)``, about the fitted pose: the non-linear counterpart of the
    radius term, for when another radius fits nearly as well with another depth."""
    if not fit.profile:
        return np.zeros((6, 6))
    cost = np.array([c for _, c, _ in fit.profile])
    d = np.array([x for _, _, x in fit.profile]) - fit.dof
    s_eff2 = max(cost.min() / max(2 * int(np.count_nonzero(fit.weights)) - 7, 1), 1e-12)
    w = np.exp(-0.5 * (cost - cost.min()) / s_eff2)
    w /= w.sum()
    return (d * w[:, None]).T @ d


def budget_from_fit(fit, camera, holder, grasp_point_mm=None, tol: Tolerance = Tolerance(),
                    kappa: float = KAPPA_EDGE_VARIATION) -> ErrorBudget:
    """The budget of a ``dm+r`` fit (:class:`~cutterpose.solvers.edge_radius.RadiusFit`,
    module doc), with the fit's corner residuals."""
    n = len(fit.residuals_px)
    Ww = fit.whitening * np.sqrt(fit.weights)[:, None, None]                 # (N, 2, 2)
    Jw = np.einsum("nij,njk->nik", Ww, fit.jacobian.reshape(n, 2, 7)).reshape(-1, 7)
    z = np.einsum("nij,nj->ni", Ww, fit.residuals_px).ravel()
    chi2 = float(z @ z) / max(2 * int(np.count_nonzero(fit.weights)) - 7, 1)
    try:
        Hinv = np.linalg.inv(fit.info)
    except np.linalg.LinAlgError:
        inf = np.full((6, 6), np.inf)
        return budget_from_dof_cov({"noise": inf}, fit.dof, grasp_point_mm, tol,
                                   residuals_px=fit.residuals_px)
    C_noise = chi2 * Hinv
    # sensitivity of the estimate to the raw corner pixels: dtheta = G dpx
    Wbig = np.zeros((2 * n, 2 * n))
    for i in range(n):
        Wbig[2 * i:2 * i + 2, 2 * i:2 * i + 2] = Ww[i]
    G = Hinv @ Jw.T @ Wbig                                                  # (7, 2N)
    D_edge = per_edge_jacobian(fit, camera, holder)                         # (2N, N)
    # per edge end: corner i's ends are edges i-1 and i
    # the plausible looks for the fitted shape, and the other shape at the nominal look
    shape = fit.table.look.shape
    looks = tuple(replace(v, shape=shape) for v in LOOK_VARIANTS) + (
        replace(fit.table.look, shape="chamfer" if shape == "round" else "round"),)
    deltas, sig_end = model_offset_spread(fit.table, fit.radius_mm, camera, holder, fit.dof,
                                          looks)
    idx_prev = (np.arange(n) - 1) % n

    def end_px(d_end):  # (N, 2) offsets per edge end -> (2N,) pixel shifts
        out = np.zeros((n, 2))
        Dr = D_edge.reshape(n, 2, n)
        out += Dr[np.arange(n), :, idx_prev] * d_end[:, 0:1]
        out += Dr[np.arange(n), :, np.arange(n)] * d_end[:, 1:2]
        return out.ravel()

    B = np.array([G @ end_px(d) for d in deltas]) if len(deltas) else np.zeros((0, 7))
    # the data weigh the looks: under look j the fit's residual would be -(I - P) m_j plus
    # noise (m_j the look's whitened corner shift, P the projection onto the fit's columns)
    P = Jw @ Hinv @ Jw.T
    zf = z
    chi = [float(zf @ zf)]
    for d in deltas:
        m = (Wbig @ end_px(d))
        e = zf + m - P @ m
        chi.append(float(e @ e))
    chi = np.array(chi) / max(chi2, 1.0)
    post = np.exp(-0.5 * (chi - chi.min()))
    post /= post.sum()
    C_model = (B * post[1:, None]).T @ B if len(B) else np.zeros((7, 7))
    # rival rises: per edge, the mean of its two ends' extra uncertainty (the whole line jumps)
    rival_end = np.sqrt(np.clip(sig_end ** 2 - np.mean(deltas ** 2, axis=0), 0, None)) \
        if len(deltas) else sig_end
    rival_edge = 0.5 * (rival_end[:, 1] + rival_end[(np.arange(n) + 1) % n, 0])
    GD = G @ D_edge
    C_rival = GD @ np.diag(rival_edge ** 2) @ GD.T
    sig_e = edge_variation_mm(fit, D_edge)
    slope = fit.table(fit.radius_mm)[1]
    slope_edge = 0.5 * (slope[:, 1] + slope[(np.arange(n) + 1) % n, 0])
    floor = kappa * fit.radius_mm * np.abs(slope_edge)
    var_edge = np.maximum(floor, sig_e) ** 2
    C_var = GD @ np.diag(var_edge) @ GD.T
    H66 = fit.info[:6, :6]
    C_known = chi2 * np.linalg.inv(H66)
    C_radius = C_noise[:6, :6] - C_known
    C_valleys = radius_profile_cov(fit)
    if np.trace(C_valleys) > np.trace(C_radius):
        C_radius = C_valleys
    parts = {"noise": C_known, "radius": C_radius,
             "model": (C_model + C_rival)[:6, :6], "edge_variation": C_var[:6, :6]}
    r_var = C_noise[6, 6] + C_model[6, 6] + C_rival[6, 6] + C_var[6, 6]
    return budget_from_dof_cov(parts, fit.dof, grasp_point_mm, tol, fit.radius_mm,
                               math.sqrt(max(r_var, 0.0)), residuals_px=fit.residuals_px)
