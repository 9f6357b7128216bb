"""The grasp frame and the grasp verdict: ``grasp`` or ``retake``, with the reason and a hint.

Grasp frame (``T_holder_grasp``): where the gripper's tool centre point must be, in the holder
frame, when it takes the cutter. The holder file may give it (``"grasp_frame"``, see
:func:`cutterpose.geometry.holder.holder_from_dict`); the default is the holder frame itself:
the TCP at the centre of the holder's top face (on the cutter's mid-plane, the holder's
symmetry centre), approaching along the holder's +Z (into the pocket), X along the pocket's
long side (the disc's plane holds X and Z), Y along the cutter's axle.

Tolerances:
    Position: 1 mm (the seed paper's requirement for the cutter-changing robot, section 1).
    Angle: an orientation error ``theta`` moves a point at radius ``r`` from the grasp point by
    ``r theta``; the farthest point of the cutter that must go into the holder's seat is the
    disc's rim, ``r = 216 mm`` for the common 17-inch (432 mm) disc cutter. Holding that rim to
    the same 1 mm gives ``theta = 1 / 216 rad = 0.265 deg``. The angle tolerance is therefore
    ``position tolerance / cutter radius`` and scales with it.

Verdict: ``grasp`` when the measurement was accepted and the 3-sigma bounds of the grasp
frame's position and orientation (:func:`cutterpose.robot.frames.bound_3sigma`) are both within
the tolerances; otherwise ``retake``, naming the bound that failed, its size along the camera's
axes, the share of each error source (measurement, hand-eye, robot) and a hint. A refused
measurement is never ``grasp``.

Convention:
    Frames and covariances as in :mod:`cutterpose.robot.frames` (mm, rad, parent axes).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np

from ..geometry.pose import Pose
from .frames import bound_3sigma

__all__ = ["GraspTolerance", "GraspVerdict", "grasp_frame", "judge", "CUTTER_RADIUS_MM",
           "refusal_hint"]

#: radius of a 17-inch disc cutter (432 mm diameter), the common size on shield machines
CUTTER_RADIUS_MM = 216.0


def grasp_frame(holder) -> Pose:
    """``T_holder_grasp`` of the holder (its file's ``grasp_frame``, else the identity)."""
    g = getattr(holder, "grasp_frame", None)
    return g if g is not None else Pose(np.eye(3), np.zeros(3), "holder", "grasp")


@dataclass(frozen=True)
class GraspTolerance:
    """How well the grasp frame must be known: 3-sigma bounds (module doc)."""

    position_mm: float = 1.0
    cutter_radius_mm: float = CUTTER_RADIUS_MM
    angle_deg: float | None = None  #: default: position_mm / cutter_radius_mm

    @property
    def angle_limit_deg(self) -> float:
        if self.angle_deg is not None:
            return float(self.angle_deg)
        return math.degrees(self.position_mm / self.cutter_radius_mm)


@dataclass
class GraspVerdict:
    """``grasp`` or ``retake`` with the reason, a hint and the figures it rests on."""

    verdict: str
    reason: str = ""
    hint: str = ""
    position_3sigma_mm: float = math.nan
    angle_3sigma_deg: float = math.nan
    tolerance: GraspTolerance = field(default_factory=GraspTolerance)
    shares: dict = field(default_factory=dict)

    @property
    def ok(self) -> bool:
        return self.verdict == "grasp"

    def to_dict(self) -> dict:
        def f(x):
            return None if x is None or not math.isfinite(x) else float(x)

        return {"verdict": self.verdict, "reason": self.reason, "hint": self.hint,
                "position_3sigma_mm": f(self.position_3sigma_mm),
                "angle_3sigma_deg": f(self.angle_3sigma_deg),
                "position_tolerance_mm": self.tolerance.position_mm,
                "angle_tolerance_deg": self.tolerance.angle_limit_deg,
                "error_shares": self.shares}


_REFUSAL_HINTS = (
    ("working range", "move the robot so that the holder is about 600 mm in front of the "
                      "camera, facing it, and retake"),
    ("ambiguity", "tilt the camera by 5-10 deg against the holder's face and retake"),
    ("worn", "light the holder's edges evenly from the front (ring light) and retake"),
    ("residual", "light the lower edge and clean the holder's edges (a corner does not fit "
                 "the model), then retake"),
    ("off the model", "light the lower edge and clean the holder's edges (a corner does not "
                      "fit the model), then retake"),
    ("uncertain", "move the camera closer to the holder and retake"),
)


def refusal_hint(reason: str) -> str:
    """What to do after the measurement refused its pose, from the refusal's reason."""
    r = reason.lower()
    for key, hint in _REFUSAL_HINTS:
        if key in r:
            return hint
    return ("check that the whole holder is in view, lit and in focus, and retake from the "
            "nominal station")


def _axes_text(C3: np.ndarray, R_cam_base: np.ndarray, unit: str, scale: float = 1.0) -> str:
    Cc = R_cam_base @ C3 @ R_cam_base.T
    s = 3.0 * np.sqrt(np.clip(np.diag(Cc), 0, None)) * scale
    return f"camera x {s[0]:.2f}, y {s[1]:.2f}, z {s[2]:.2f} {unit}"


def _shares(parts: dict, C: np.ndarray) -> dict:
    """Share of each source's variance along the worst direction of ``C`` (none when ``C``
    is not finite: no direction is the worst)."""
    if not np.all(np.isfinite(C)):
        return {}
    w, V = np.linalg.eigh(C)
    v = V[:, -1]
    tot = max(float(v @ C @ v), 1e-300)
    return {k: round(float(v @ P @ v) / tot, 3) for k, P in parts.items()}


def judge(cov_grasp: np.ndarray, parts: dict, R_cam_base: np.ndarray,
          tolerance: GraspTolerance | None = None) -> GraspVerdict:
    """The verdict from the grasp frame's 6x6 covariance (mm, rad, base axes).

    Parameters
    ----------
    cov_grasp : total covariance of ``T_base_grasp``.
    parts : source name (``measurement``, ``hand-eye``, ``robot``) -> its 6x6 share (they sum
        to ``cov_grasp``).
    R_cam_base : to express the failing DOF in the camera's axes (what the hint acts on).
    """
    tol = tolerance or GraspTolerance()
    p3 = bound_3sigma(cov_grasp[:3, :3])
    a3 = math.degrees(bound_3sigma(cov_grasp[3:, 3:]))
    pos_sh = _shares({k: v[:3, :3] for k, v in parts.items()}, cov_grasp[:3, :3])
    ang_sh = _shares({k: v[3:, 3:] for k, v in parts.items()}, cov_grasp[3:, 3:])
    shares = {"position": pos_sh, "angle": ang_sh}
    if not (math.isfinite(p3) and math.isfinite(a3)):
        return GraspVerdict("retake", "the pose has no usable uncertainty",
                            refusal_hint("uncertain"), p3, a3, tol, shares)
    reasons, hints = [], []
    for name, bound, limit, C3, unit, scale, sh in (
            ("position", p3, tol.position_mm, cov_grasp[:3, :3], "mm", 1.0, pos_sh),
            ("angle", a3, tol.angle_limit_deg, cov_grasp[3:, 3:], "deg", 180 / math.pi,
             ang_sh)):
        if bound <= limit:
            continue
        src = max(sh, key=sh.get)
        reasons.append(f"{name} 3-sigma {bound:.3g} {unit} > {limit:.3g} {unit} ("
                       f"{_axes_text(C3, R_cam_base, unit, scale)}; "
                       + ", ".join(f"{k} {100 * v:.0f} %" for k, v in sh.items()) + ")")
        if src == "measurement":
            Cc = R_cam_base @ C3 @ R_cam_base.T
            worst = int(np.argmax(np.diag(Cc)))
            if name == "position" and worst == 2:
                hints.append("move the camera closer to the holder (depth is the weakest "
                             "direction)")
            elif name == "angle" and worst < 2:
                hints.append("move closer and light the lower edge evenly (the holder's tilt "
                             "comes from its edges)")
            else:
                hints.append("move closer, focus, and light the holder's edges evenly")
        elif src == "hand-eye":
            hints.append("redo the hand-eye calibration with more stations and more rotation")
        else:
            hints.append("the robot's stated accuracy alone exceeds the tolerance: calibrate "
                         "the robot or widen the tolerance")
    if reasons:
        return GraspVerdict("retake", "; ".join(reasons), "; ".join(dict.fromkeys(hints)),
                            p3, a3, tol, shares)
    return GraspVerdict("grasp", "", "", p3, a3, tol, shares)
