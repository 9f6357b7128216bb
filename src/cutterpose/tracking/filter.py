"""The temporal filter: a constant-velocity alpha-beta filter on SE(3), reported beside the raw
pose, never instead of it, and reset at a jump (docs/tracking.md, "Temporal filter").

References: P. Kalata, "The tracking index", IEEE TAES 20(2), 1984 (alpha-beta filter);
Benedict & Bordner (1962) for ``beta = alpha^2 / (2 - alpha)``.
"""

from __future__ import annotations

import math

import numpy as np

from ..errors import InputError
from ..geometry.pose import Pose
from ..geometry.se3 import compose, relative, se3_exp, se3_log

__all__ = ["PoseFilter"]



class PoseFilter:
    """Constant-velocity alpha-beta filter on SE(3) (docs/tracking.md, "Temporal filter")."""

    def __init__(self, alpha: float = 0.5, beta: float = 0.5 ** 2 / 1.5, gate_mm: float = 5.0,
                 gate_deg: float = 2.0):
        if not (0 < alpha <= 1 and 0 <= beta < 2):
            raise InputError(f"filter gains need 0 < alpha <= 1, 0 <= beta < 2; got "
                             f"{alpha}, {beta}")
        self.alpha, self.beta = float(alpha), float(beta)
        self.gate_mm, self.gate_deg = float(gate_mm), float(gate_deg)
        self.reset()

    def reset(self, pose: Pose | None = None) -> None:
        self.pose, self.xi = pose, np.zeros(6)
        self._fresh = True   # one pose since the reset: the velocity is not known yet

    def update(self, z: Pose, force_reset: str = "", dt: float = 1.0) -> tuple[Pose, str]:
        """Filter the measured pose ``z``, ``dt`` after the last one (in the twist's unit: a
        frame, or a second with frame times); returns the filtered pose and the reset
        reason."""
        if self.pose is None or force_reset:
            self.reset(z)
            return z, force_reset or "first pose"
        if not dt > 0:
            raise InputError(f"filter: the time step must be > 0, got {dt}")
        if self._fresh:
            # two-point start: the velocity from the first two poses, the state on the second
            Rn, tn = relative(z, self.pose)
            self.xi = se3_log(Rn, tn) / dt
            self.pose, self._fresh = z, False
            return z, ""
        Rp, tp = se3_exp(self.xi * dt)
        pred = compose(Rp, tp, self.pose)
        nu = se3_log(*relative(z, pred))
        # gate on what a jump looks like: the holder's displacement and rotation angle
        rot_deg = math.degrees(float(np.linalg.norm(nu[:3])))
        trans_mm = float(np.linalg.norm(z.t_mm - pred.t_mm))
        if rot_deg > self.gate_deg or trans_mm > self.gate_mm:
            self.reset(z)
            return z, (f"innovation {trans_mm:.1f} mm / {rot_deg:.2f} deg beyond the gate "
                       f"({self.gate_mm} mm / {self.gate_deg} deg)")
        Ru, tu = se3_exp(self.alpha * nu)
        self.pose = compose(Ru, tu, pred)
        self.xi = self.xi + self.beta * nu / dt
        return self.pose, ""
