"""What an image set draws per image besides the scene: the pose within the protocol's range
(:func:`random_pose`, PROTOCOL.md, real-image experiment), the light of an auto-exposing
camera at that distance (:func:`auto_exposed`), and the ``truth.json`` keys that say so
(:func:`distance_doc`)."""

from __future__ import annotations

import numpy as np

from ..geometry.pose import Pose
from .sensor import D_REF_MM

__all__ = ["random_pose", "auto_exposed", "distance_doc"]


def random_pose(rng: np.random.Generator, max_angle_deg: float = 10.0,
                max_shift_mm: float = 20.0, distance_mm: tuple[float, float] | None = None
                ) -> Pose:
    """A pose drawn uniformly within +-``max_angle_deg`` and +-``max_shift_mm`` of the nominal
    pose (PROTOCOL.md, real-image experiment); with ``distance_mm`` = (near, far) the depth is
    drawn uniformly in it instead (the same draws: the angles and sideways shifts do not
    change)."""
    ang = rng.uniform(-max_angle_deg, max_angle_deg, 3)
    sh = rng.uniform(-max_shift_mm, max_shift_mm, 3)
    if distance_mm is None:
        z = D_REF_MM + sh[2]
    else:
        lo, hi = distance_mm
        z = lo + (hi - lo) * (sh[2] + max_shift_mm) / (2 * max_shift_mm)
    return Pose.from_euler(*ang, sh[0], sh[1], z)


def auto_exposed(light_dn: float, pose: Pose) -> float:
    """The light level (DN) of an auto-exposing camera at ``pose``: ``light_dn`` at 600 mm,
    scaled by ``(Z / 600 mm)^2`` so that the face keeps its grey level (render-sequence's and
    render-set's ``--distance-mm``)."""
    return light_dn * (float(pose.t_mm[2]) / D_REF_MM) ** 2


def distance_doc(distance_mm: tuple[float, float] | None) -> dict:
    """The ``truth.json`` keys of a set drawn over ``distance_mm`` = (near, far) depths and lit
    by :func:`auto_exposed` (none for the default 600 mm sets)."""
    if distance_mm is None:
        return {}
    return {"distance_mm": list(distance_mm),
            "auto_exposure": f"light_dn * (Z / {D_REF_MM:g} mm)^2"}
