"""The verdict's error budget (issue 10, item 4): how far off the pose may be, from what, and
whether that is within the robot's tolerance.

Contributions, each a covariance of the estimate (the pose's six DOFs, and the edge radius
``r`` for ``dm+r``), summed:

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
* for methods without the edge model (``dm``, ``dm+``, PnP): ``noise`` is the 6-DOF Gauss-Newton
  covariance of :func:`cutterpose.pipeline.pose_std`, ``method`` the step ``d`` from the pose to
  the corners' least-squares pose (:func:`cutterpose.pipeline.fit_offset`; a pose that does not
  minimise the residuals, as ``dm``'s search or a linear PnP, is off by it), as 1 sigma of
  ``2 d / 3``, ``wear`` the square of the pose shift the
  edges' measured darkening may cause (:func:`cutterpose.pipeline.edge_wear_effect`), and
  ``edge break`` the break they cannot measure: the seen edge lies anywhere from the design edge
  to ``b`` outside it (``b = QualityLimits.edge_break_mm``, 1.5 mm when not known), taken as
  ``s s^T`` with ``s`` the pose shift of a uniform outward offset ``b / 3``
  (:func:`cutterpose.pipeline.edge_break_effect`: its 3 sigma is the shift of the whole range,
  a bound rather than a spread, since the seen edge's offset is one-sided and not corrected).

The 6 x 6 pose covariance is then given in the camera frame as ``covariance_cam`` in the order
``(x, y, z [mm], rx, ry, rz [rad])``: the translation ``t_cam_holder`` and a small rotation about
the holder frame's own axes, ``R_true = R_est exp([w]x)`` (the order of the hand-eye file's
covariance, PROTOCOL.md, Robot cell). At a grasp point ``p`` (holder frame; default the origin,
the centre of the pocket's top plane) the position ``R p + t`` has covariance
``A C A^T`` with ``A = [I, -R [p]x]``. The verdict takes the worst direction:
``position_3sigma_mm = 3 sqrt(lambda_max)`` of that 3 x 3 block and ``angle_3sigma_deg`` the same
of the rotation block, and refuses above the tolerance: 1 mm (the robot's, seed paper 2.3) and
0.3 deg (a rotation error of ``theta`` moves the pocket's ends, 200 mm from the origin, by
``200 theta``: 0.3 deg is 1 mm there, the same tolerance carried to the farthest point the
gripper's seats reach).

Convention:
    DOF covariances in (alpha, beta, gamma [deg], X, Y, Z [mm], r [mm]);
    ``covariance_cam`` as above. 3-sigma figures are of the worst direction.

References:
    Kay, *Fundamentals of Statistical Signal Processing I* (1993), ch. 3; Hartley & Zisserman,
    *Multiple View Geometry*, 2nd ed., 5.2 (forward propagation of covariance).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field, replace

import numpy as np

from .geometry.pose import rotation_from_euler_deg

__all__ = ["ErrorBudget", "Tolerance", "budget_from_fit", "budget_from_dof_cov",
           "dof_to_cam_jacobian", "edge_variation_mm", "radius_profile_cov", "COVARIANCE_CAM_ORDER",
           "KAPPA_EDGE_VARIATION"]

COVARIANCE_CAM_ORDER = ("x_mm", "y_mm", "z_mm", "rx_rad", "ry_rad", "rz_rad")
KAPPA_EDGE_VARIATION = 0.1


@dataclass(frozen=True)
class Tolerance:
    """When the budget refuses: 3-sigma position at the grasp point and rotation."""

    position_mm: float = 1.0
    angle_deg: float = 0.3
    k_sigma: float = 3.0


@dataclass
class ErrorBudget:
    """The budget of one measurement (module doc).

    Attributes
    ----------
    parts : name -> (6, 6) DOF covariance of each contribution (deg, mm).
    dof_cov : (6, 6) their sum; covariance_cam : (6, 6) the same in ``COVARIANCE_CAM_ORDER``.
    grasp_point_mm : (3,) holder-frame point the position figure is for.
    position_3sigma_mm, angle_3sigma_deg : worst-direction 3-sigma figures.
    radius_mm, radius_std_mm : the edge radius and its std (NaN without the edge model).
    """

    parts: dict
    dof_cov: np.ndarray
    covariance_cam: np.ndarray
    grasp_point_mm: np.ndarray
    position_3sigma_mm: float
    angle_3sigma_deg: float
    radius_mm: float = math.nan
    radius_std_mm: float = math.nan
    per_part_3sigma: dict = field(default_factory=dict)

    @property
    def std_dof(self) -> np.ndarray:
        return np.sqrt(np.clip(np.diag(self.dof_cov), 0, None))

    def exceeds(self, tol: Tolerance) -> str:
        """The reason for refusing, or '' when within the tolerance."""
        k = tol.k_sigma
        worst = max(self.per_part_3sigma.items(), key=lambda kv: kv[1][0] / tol.position_mm
                    + kv[1][1] / tol.angle_deg, default=("?", (0, 0)))[0]
        if not (self.position_3sigma_mm <= tol.position_mm):
            return (f"error budget: position at the grasp point uncertain by "
                    f"{self.position_3sigma_mm:.2f} mm ({k:g} sigma) > {tol.position_mm} mm; "
                    f"largest part: {worst}")
        if not (self.angle_3sigma_deg <= tol.angle_deg):
            return (f"error budget: rotation uncertain by {self.angle_3sigma_deg:.3f} deg "
                    f"({k:g} sigma) > {tol.angle_deg} deg; largest part: {worst}")
        return ""

    def to_dict(self) -> dict:
        def f(x):
            return None if not math.isfinite(float(x)) else float(x)

        names = ("alpha_deg", "beta_deg", "gamma_deg", "X_mm", "Y_mm", "Z_mm")
        return {"position_3sigma_mm": f(self.position_3sigma_mm),
                "angle_3sigma_deg": f(self.angle_3sigma_deg),
                "grasp_point_holder_mm": [float(v) for v in self.grasp_point_mm],
                "edge_radius_mm": f(self.radius_mm), "edge_radius_std_mm": f(self.radius_std_mm),
                "std": {n: f(v) for n, v in zip(names, self.std_dof)},
                "parts": {k: {"std": {n: f(v) for n, v in zip(
                    names, np.sqrt(np.clip(np.diag(c), 0, None)))},
                    "position_3sigma_mm": f(self.per_part_3sigma[k][0]),
                    "angle_3sigma_deg": f(self.per_part_3sigma[k][1])}
                    for k, c in self.parts.items()},
                "covariance_cam": {"order": list(COVARIANCE_CAM_ORDER),
                                   "matrix": self.covariance_cam.tolist()}}


def dof_to_cam_jacobian(dof) -> np.ndarray:
    """(6, 6) d (t [mm], w [rad]) / d (alpha, beta, gamma [deg], X, Y, Z [mm]) at ``dof``,
    ``w`` the rotation about the holder's own axes (``R(dof + e) = R exp([w]x)``)."""
    from scipy.spatial.transform import Rotation

    dof = np.asarray(dof, float)
    R = rotation_from_euler_deg(*dof[:3])
    A = np.zeros((6, 6))
    A[:3, 3:] = np.eye(3)
    h = 1e-4
    for k in range(3):
        e = dof[:3].copy()
        e[k] += h
        e2 = dof[:3].copy()
        e2[k] -= h
        w1 = Rotation.from_matrix(R.T @ rotation_from_euler_deg(*e)).as_rotvec()
        w2 = Rotation.from_matrix(R.T @ rotation_from_euler_deg(*e2)).as_rotvec()
        A[3:, k] = (w1 - w2) / (2 * h)
    return A


def _figures(cov_cam: np.ndarray, R: np.ndarray, p: np.ndarray, k: float):
    if not np.all(np.isfinite(cov_cam)):  # a singular fit's part: refuse, not a LinAlgError
        return math.inf, math.inf
    px = np.array([[0, -p[2], p[1]], [p[2], 0, -p[0]], [-p[1], p[0], 0]])
    A = np.hstack([np.eye(3), -R @ px])
    Cp = A @ cov_cam @ A.T
    pos = k * math.sqrt(max(float(np.linalg.eigvalsh(Cp)[-1]), 0.0))
    ang = k * math.degrees(math.sqrt(max(float(np.linalg.eigvalsh(cov_cam[3:, 3:])[-1]), 0.0)))
    return pos, ang


def budget_from_dof_cov(parts: dict, dof, grasp_point_mm=None, tol: Tolerance = Tolerance(),
                        radius_mm: float = math.nan, radius_std_mm: float = math.nan
                        ) -> ErrorBudget:
    """An :class:`ErrorBudget` from named (6, 6) DOF covariances at the pose ``dof``."""
    p = np.zeros(3) if grasp_point_mm is None else np.asarray(grasp_point_mm, float).reshape(3)
    dof = np.asarray(dof, float)
    total = sum(parts.values()) if parts else np.zeros((6, 6))
    A = dof_to_cam_jacobian(dof)
    R = rotation_from_euler_deg(*dof[:3])
    with np.errstate(invalid="ignore"):  # inf * 0 in a non-finite part: NaN, refused below
        cam = A @ total @ A.T
        per = {k: _figures(A @ c @ A.T, R, p, tol.k_sigma) for k, c in parts.items()}
    pos, ang = _figures(cam, R, p, tol.k_sigma)
    return ErrorBudget(parts, total, cam, p, pos, ang, radius_mm, radius_std_mm, per)


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
    """The budget of a ``dm+r`` fit (:class:`cutterpose.solvers.edge_radius.RadiusFit`)."""
    from .image.edge_model import LOOK_VARIANTS
    from .solvers.edge_radius import model_offset_spread, per_edge_jacobian

    n = len(fit.residuals_px)
    Ww = fit.whitening * np.sqrt(fit.weights)[:, None, None]                 # (N, 2, 2)
    Jw = np.einsum("nij,njk->nik", Ww, fit.jacobian.reshape(n, 2, 7)).reshape(-1, 7)
    z = np.einsum("nij,nj->ni", Ww, fit.residuals_px).ravel()
    chi2 = float(z @ z) / max(2 * int(np.count_nonzero(fit.weights)) - 7, 1)
    try:
        Hinv = np.linalg.inv(fit.info)
    except np.linalg.LinAlgError:
        inf = np.full((6, 6), np.inf)
        return budget_from_dof_cov({"noise": inf}, fit.dof, grasp_point_mm, tol)
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
                               math.sqrt(max(r_var, 0.0)))
