"""Geometry: camera models and their files, the holder model, poses and the working range.

:mod:`.camera` (pinhole, division, OpenCV models), :mod:`.camera_files` (JSON, OpenCV YAML,
HALCON, ROS), :mod:`.holder` (the holder's design geometry), :mod:`.pose` (the pose convention
and the protocol's error figures), :mod:`.working_range` (where the holder can be).
"""
