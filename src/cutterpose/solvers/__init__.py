"""Pose methods and their solvers: the protocol and its families (:mod:`.method`), the
methods' estimates (:mod:`.estimate`), the corners at a pose and the corner methods' budget
(:mod:`.corners`), the initial pose (:mod:`.vanishing`, paper 2.2), distance matching
(:mod:`.matching`, :mod:`.dm`: ``dm``, ``dm+``, paper 2.3), the design edge's pose
(:mod:`.edge_band`: ``dm+b``; :mod:`.edge_radius` and :mod:`.radius_budget`: ``dm+r``) and the
PnP baselines (:mod:`.pnp`).
"""
