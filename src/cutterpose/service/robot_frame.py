"""The robot-frame step of a measurement: the holder and grasp frames in the robot's base frame
and the grasp verdict (:func:`cutterpose.robot.locate`, issue 11), from the camera-frame
measurement, the cell's hand-eye file and the flange pose sent with the request.

Without a flange pose or without a hand-eye file in the cell there is no base frame: the answer
says why (``available: false``), and the camera-frame pose and ``quality`` stand in
(PROTOCOL.md "Measurement JSON").

Convention:
    ``T_base_flange`` (mm) maps flange to base coordinates (PROTOCOL.md "Robot cell"), sent as
    the pose row ``x_mm,y_mm,z_mm,qx,qy,qz,qw``; the answer's ``T_base_holder`` /
    ``T_base_grasp`` likewise (4x4, mm); covariances as in :mod:`cutterpose.robot.frames`.
"""

from __future__ import annotations

__all__ = ["robot_frame"]


def robot_frame(measurement, cell, holder, flange_row) -> dict:
    """The ``robot`` object of the service's answer.

    Parameters
    ----------
    measurement : the :class:`cutterpose.pipeline.Measurement` (camera frame).
    cell : the :class:`~cutterpose.service.config.Cell` (hand-eye, robot accuracy, grasp
        tolerance, camera).
    holder : the holder model measured.
    flange_row : the request's flange pose as a PROTOCOL row (7 numbers), or ``None``.

    Returns
    -------
    dict : ``{"available": bool, "reason": str}``, and when available the fields of
        :meth:`cutterpose.robot.RobotResult.to_dict` (``T_base_holder``, ``T_base_grasp``,
        ``grasp`` with the verdict, ...).
    """
    if flange_row is None:
        return {"available": False, "reason": "no flange pose in the request"}
    if cell.handeye is None:
        return {"available": False, "reason": "the cell file names no hand-eye file"}
    from ..robot import parse_pose_row

    T_base_flange = parse_pose_row(",".join(repr(float(x)) for x in flange_row))
    res = cell.station.locate(measurement, T_base_flange, holder=holder)
    return {"available": True, "reason": ""} | res.to_dict()
