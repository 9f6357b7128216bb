"""The robot's side (issue 11): pose formats, frame-named transforms with covariance, the
holder and the grasp frame in the robot's base frame, and the grasp verdict.

Python API::

    from cutterpose.robot import locate, load_handeye, RobotAccuracy
    res = locate(measurement, load_handeye("handeye.json"), T_base_flange,
                 RobotAccuracy(0.03, 0.005))
    res.T_base_grasp.pose, res.T_base_grasp.cov, res.grasp.verdict, res.to_dict()
"""

from ..calibration.handeye import HandEye, load_handeye
from .frames import PoseCov
from .grasp import GraspTolerance, GraspVerdict, grasp_frame
from .locate import RobotAccuracy, RobotResult, locate, measurement_covariance
from .poses import load_flange_pose, parse_pose_row, read_poses, write_poses

__all__ = ["HandEye", "load_handeye", "PoseCov", "GraspTolerance", "GraspVerdict",
           "grasp_frame", "RobotAccuracy", "RobotResult", "locate", "measurement_covariance",
           "load_flange_pose", "parse_pose_row", "read_poses", "write_poses"]
