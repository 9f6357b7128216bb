"""Pose solvers, all ``solve(points_px, camera, model) -> PoseEstimate``.

:mod:`.vanishing` (initial pose, paper 2.2), :mod:`.matching` (distance matching ``dm`` and
``dm+``, paper 2.3), :mod:`.pnp` (the PnP baselines), :mod:`.estimate` (their common result).
"""
