"""The robot's side: pose formats, frame-named transforms with covariance, the holder and the
grasp frame in the robot's base frame, and the grasp verdict."""
