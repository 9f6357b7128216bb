"""The robot-frame step of a measurement: the holder and grasp frames in the robot's base frame
and the grasp verdict, from the camera-frame measurement, the cell's hand-eye file and the
flange pose sent with the request.

That step belongs to :mod:`cutterpose.robot` (issue 11). Until it is on main, :data:`ENABLED`
is False and :func:`robot_frame` answers ``available: false`` with the reason, so the answer's
camera-frame pose and ``quality`` stand in (PROTOCOL.md "Measurement JSON"). Switching it on is
this one function.

Convention:
    ``T_base_flange`` (4x4, mm) maps flange to base coordinates (PROTOCOL.md "Robot cell");
    the answer's ``T_base_holder`` / ``T_base_grasp`` likewise.
"""

from __future__ import annotations

import numpy as np

__all__ = ["ENABLED", "robot_frame", "flange_matrix"]

#: True once cutterpose.robot (issue 11) provides the base-frame pose and grasp verdict
ENABLED = False


def flange_matrix(row) -> np.ndarray:
    """``T_base_flange`` (4x4, mm) from a PROTOCOL pose row ``x_mm,y_mm,z_mm,qx,qy,qz,qw``
    (unit quaternion, scalar last; already checked by the request model)."""
    from scipy.spatial.transform import Rotation

    r = np.asarray(row, float)
    T = np.eye(4)
    T[:3, :3] = Rotation.from_quat(r[3:7]).as_matrix()  # scipy's order is scalar-last too
    T[:3, 3] = r[:3]
    return T


def robot_frame(measurement, handeye: dict | None, flange_row) -> dict:
    """The ``robot`` object of the service's answer.

    Parameters
    ----------
    measurement : the :class:`cutterpose.pipeline.Measurement` (camera frame).
    handeye : the cell's hand-eye file (``None`` when the cell names none).
    flange_row : the request's flange pose as a PROTOCOL row, or ``None``.

    Returns
    -------
    dict : ``{"available": bool, "reason": str}``, and when available ``T_base_holder``,
        ``T_base_grasp`` (4x4, mm) and ``grasp`` (PROTOCOL.md "Measurement JSON").
    """
    if flange_row is None:
        return {"available": False, "reason": "no flange pose in the request"}
    if handeye is None:
        return {"available": False, "reason": "the cell file names no hand-eye file"}
    if not ENABLED:
        return {"available": False,
                "reason": "base-frame step not in this build yet (issue 11): use the "
                          "camera-frame pose and quality"}
    if measurement.pose is None:  # pragma: no cover - switched on with issue 11
        return {"available": False, "reason": "no camera-frame pose"}
    raise NotImplementedError  # pragma: no cover - replaced by the cutterpose.robot call
