"""The working range: where the holder can be relative to the camera when it is measured.

A box in the six protocol DOFs around the nominal pose. The initial pose (paper 2.2) picks the
candidate inside it, distance matching (paper 2.3) searches it, and the verdict refuses a pose
outside it.

Convention:
    DOFs ``(alpha, beta, gamma [deg], X, Y, Z [mm])`` of ``R_cam_holder = Rz(gamma) Ry(beta)
    Rx(alpha)``, ``t_cam_holder_mm = (X, Y, Z)`` (:mod:`cutterpose.geometry.pose`); angle
    differences are wrapped to (-180, 180].
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from ..errors import DegenerateInputError
from .pose import euler_deg_from_rotation, wrap_deg

__all__ = ["MotionRange", "PoseOutOfRangeError", "pose_dof"]


class PoseOutOfRangeError(DegenerateInputError):
    """A pose (e.g. the initial pose handed to distance matching) lies outside the motion range."""


@dataclass(frozen=True)
class MotionRange:
    """The known range of the holder's pose around its nominal pose (box in the six DOFs).

    Attributes
    ----------
    center_dof : (alpha, beta, gamma [deg], X, Y, Z [mm]) at the centre of the range.
    half_width_dof : half widths per DOF (deg, mm).
    """

    center_dof: tuple = (0.0, 0.0, 0.0, 0.0, 0.0, 600.0)
    half_width_dof: tuple = (60.0, 60.0, 60.0, 90.0, 90.0, 90.0)

    @classmethod
    def synthetic(cls) -> MotionRange:
        """The synthetic protocol: +-60 deg, +-90 mm around (0, 0, 600) mm."""
        return cls()

    @classmethod
    def real(cls) -> MotionRange:
        """The real-image range (paper Table 2): +-10 deg, +-20 mm around the nominal pose."""
        return cls(half_width_dof=(10.0, 10.0, 10.0, 20.0, 20.0, 20.0))

    @property
    def lower(self) -> np.ndarray:
        return np.asarray(self.center_dof, float) - np.asarray(self.half_width_dof, float)

    @property
    def upper(self) -> np.ndarray:
        return np.asarray(self.center_dof, float) + np.asarray(self.half_width_dof, float)

    def excess(self, dof) -> np.ndarray:
        """How far (in units of the half widths) each pose ``(..., 6)`` lies outside the box:
        0 inside, > 0 outside (max over the DOFs); angles are wrapped around the centre."""
        dof = np.asarray(dof, float)
        c = np.asarray(self.center_dof, float)
        h = np.asarray(self.half_width_dof, float)
        d = dof - c
        d[..., :3] = wrap_deg(d[..., :3])
        return np.maximum(np.abs(d) / h - 1.0, 0.0).max(axis=-1)

    def contains(self, dof, slack: float = 0.0) -> np.ndarray:
        """True for poses inside the box enlarged by ``slack`` (a fraction of the half widths)."""
        return self.excess(dof) <= slack


def pose_dof(R, t) -> np.ndarray:
    """(..., 6) protocol DOFs of poses."""
    return np.concatenate([euler_deg_from_rotation(R), np.asarray(t, float)], axis=-1)
