"""PnP solvers with known 2D-3D correspondences, one module per solver.

Every solver has the signature ``solve(points_px, camera, model) -> PoseEstimate``; see
:mod:`cutterpose.solvers.pnp.base`.
"""
