"""What a hand-eye calibration says about its stations: the target's base-frame spread against
the robot's stated error, and a Markdown report (per-station residuals, flagged stations, the
linear methods against the refinement).
"""

from __future__ import annotations

import math

import numpy as np

from ..geometry.pose import Pose, geodesic_deg
from .handeye_problem import HandEyeProblem

__all__ = ["plate_spread", "report_markdown"]


def plate_spread(prob: HandEyeProblem, A: list[Pose], B: list[Pose], X: Pose, Y: Pose,
                 used: np.ndarray) -> dict:
    """The target's base-frame pose over the stations, ``Y_i = A_i X B_i``, against ``Y``.

    Measured: RMS and largest position (mm) and angle (deg) deviation of the used stations.
    Explained: the RMS expected from the robot's stated pose error (``C_robot``, per axis) and
    the pixel noise (``sigma_px^2 (G_i^T G_i)^-1``, the same flange-pose coordinates): a flange
    error ``(dt, dphi)`` (base axes) moves ``Y_i`` by ``dt + dphi x (t_Y - t_A_i)`` and turns it
    by ``dphi``. Robot error estimate: the per-axis 1-sigma position and angle error of the
    robot that would explain the measured spread (what is left after the pixel noise).
    """
    prob.set_weights(X, Y)
    u = np.flatnonzero(used)
    Yk = [A[k] @ X @ B[k] for k in u]
    dpos = np.array([np.linalg.norm(y.t_mm - Y.t_mm) for y in Yk])
    dang = np.array([geodesic_deg(y.R, Y.R) for y in Yk])
    Cr = np.diag([prob.rep_mm ** 2] * 3 + [prob.rep_rad ** 2] * 3)
    e_pos, e_ang, pix_pos, pix_ang, lever2 = [], [], [], [], []
    for k in u:
        G = prob.G[k]
        Cp = prob.sigma_px ** 2 * np.linalg.pinv(G.T @ G)
        L = Y.t_mm - A[k].t_mm
        M = np.concatenate([np.eye(3), -_skew(L)], axis=1)
        pix_pos.append(np.trace(M @ Cp @ M.T))
        pix_ang.append(np.trace(Cp[3:, 3:]))
        e_pos.append(np.trace(M @ (Cr + Cp) @ M.T))
        e_ang.append(np.trace((Cr + Cp)[3:, 3:]))
        lever2.append(L @ L)
    rms = lambda v: float(np.sqrt(np.mean(np.square(v))))  # noqa: E731
    meas_pos, meas_ang = rms(dpos), rms(dang)
    exp_pos = float(np.sqrt(np.mean(e_pos)))
    exp_ang = math.degrees(float(np.sqrt(np.mean(e_ang))))
    sig_phi = math.sqrt(max(math.radians(meas_ang) ** 2 - np.mean(pix_ang), 0.0) / 3.0)
    sig_t = math.sqrt(max(meas_pos ** 2 - np.mean(pix_pos)
                          - 2.0 * sig_phi ** 2 * np.mean(lever2), 0.0) / 3.0)
    ratio = max(meas_pos / max(exp_pos, 1e-12), meas_ang / max(exp_ang, 1e-12))
    consistent = ratio <= 1.5
    verdict = (f"consistent with the robot's stated error ({meas_pos:.3f} mm / {meas_ang:.4f} "
               f"deg RMS, {exp_pos:.3f} mm / {exp_ang:.4f} deg expected)" if consistent else
               f"spread {ratio:.1f}x what the robot's stated error ({prob.rep_mm:g} mm / "
               f"{math.degrees(prob.rep_rad):g} deg per axis) and the pixel noise explain: "
               f"{meas_pos:.3f} mm / {meas_ang:.4f} deg RMS against {exp_pos:.3f} mm / "
               f"{exp_ang:.4f} deg; a robot error of ~{sig_t:.2f} mm / "
               f"{math.degrees(sig_phi):.3f} deg per axis would explain it (the robot's "
               "absolute accuracy, the intrinsics, or poses read while moving)")
    return {"position_rms_mm": meas_pos, "position_max_mm": float(dpos.max()),
            "angle_rms_deg": meas_ang, "angle_max_deg": float(dang.max()),
            "explained_position_rms_mm": exp_pos, "explained_angle_rms_deg": exp_ang,
            "robot_error_estimate_mm": sig_t, "robot_error_estimate_deg": math.degrees(sig_phi),
            "consistent": bool(consistent), "verdict": verdict}


def _skew(v) -> np.ndarray:
    x, y, z = v
    return np.array([[0.0, -z, y], [z, 0.0, -x], [-y, x, 0.0]])


def _rotvec_deg(R: np.ndarray) -> np.ndarray:
    from scipy.spatial.transform import Rotation

    return np.degrees(Rotation.from_matrix(R).as_rotvec())


def report_markdown(result, title: str = "Hand-eye calibration") -> str:
    """A Markdown report of a :class:`~cutterpose.calibration.handeye.HandEyeResult`."""
    X, Y = result.T_flange_cam, result.T_base_plate
    sd = np.sqrt(np.diag(result.handeye.covariance))
    lines = [f"# {title}", "", f"**{result.verdict}**", "",
             f"- T_flange_cam: t = {np.round(X.t_mm, 3).tolist()} mm, rotation vector "
             f"{np.round(_rotvec_deg(X.R), 4).tolist()} deg; 1-sigma {np.round(sd[:3], 3).tolist()}"
             f" mm, {np.round(np.degrees(sd[3:]), 4).tolist()} deg",
             f"- T_base_plate: t = {np.round(Y.t_mm, 3).tolist()} mm, rotation vector "
             f"{np.round(_rotvec_deg(Y.R), 4).tolist()} deg",
             f"- refined from: {result.start_method}; pixel noise {result.sigma_px:.3f} px; RMS "
             f"{result.rms_px:.3f} px over the used stations"]
    sp = result.plate_spread
    if sp:
        lines.append(f"- the target in the base frame over the stations: {sp['verdict']}")
    lines += [f"- {n}" for n in result.notes]
    lines += ["", "## Stations", "",
              "| station | used | RMS px | target mm | target deg | motion deg | motion mm "
              "| order | distrust |", "|---|---|---|---|---|---|---|---|---|"]
    for s in result.stations:
        lines.append(f"| {s.name} | {'yes' if s.used else '**no**'} | {s.rms_px:.3f} | "
                     f"{s.position_mm:.3f} | {s.angle_deg:.4f} | {s.motion_deg:.3f} | "
                     f"{s.motion_mm:.2f} | {s.order} | {s.distrust} |")
    lines += ["", "target mm / deg: the target's base-frame pose this station alone gives "
              "(T_base_flange X T_cam_plate) against the joint one; motion: how far the robot's "
              "and the camera's motion to the other stations disagree (median rotation angle "
              "and translation along the axis; independent of X).", "",
              "## Linear methods (starts) against the refined result", "",
              "| method | t mm | rotation vector deg | dt mm | dR deg |", "|---|---|---|---|---|"]
    for name, v in result.starts.items():
        if isinstance(v, str):
            lines.append(f"| {name} | {v} | | | |")
            continue
        Xm = v[0]
        lines.append(f"| {name} | {np.round(Xm.t_mm, 2).tolist()} | "
                     f"{np.round(_rotvec_deg(Xm.R), 3).tolist()} | "
                     f"{np.linalg.norm(Xm.t_mm - X.t_mm):.2f} | {geodesic_deg(Xm.R, X.R):.3f} |")
    return "\n".join(lines) + "\n"
