"""The registered distance-matching methods ``dm``, ``dm+`` and ``dm-paper``
(:class:`~cutterpose.solvers.method.RangeSearchMethod`): the initial pose (paper 2.2) or a close
start, then distance matching (paper 2.3, :mod:`cutterpose.solvers.matching`) in the rig's
working range.
"""

from __future__ import annotations

import time

import numpy as np

from ..geometry.camera import Camera
from ..geometry.holder import Holder
from ..geometry.working_range import MotionRange, pose_dof
from .estimate import PoseEstimate
from .matching import distance_match, refine_from_close_start
from .method import RangeSearchMethod
from .vanishing import initial_pose, initial_pose_paper

__all__ = ["Dm", "DmPlus", "DmPaper", "solve_dm", "solve_dm_plus", "solve_dm_paper"]


# ---- registered methods --------------------------------------------------------------------
def _search_range(motion_range: MotionRange) -> MotionRange:
    """The initial pose's search range: the synthetic protocol's wide range, widened to cover
    ``motion_range`` where it reaches beyond it (an approach from 900 mm)."""
    wide = MotionRange()
    lo = np.minimum(np.subtract(wide.center_dof, wide.half_width_dof), motion_range.lower)
    hi = np.maximum(np.add(wide.center_dof, wide.half_width_dof), motion_range.upper)
    return MotionRange(center_dof=tuple((lo + hi) / 2), half_width_dof=tuple((hi - lo) / 2))


def _solve(points_px, camera: Camera, model: Holder, refine: bool,
           paper_initial: bool = False, *, motion_range: MotionRange | None = None,
           start=None, partial: bool = False, close_start_rms_px: float | None = None
           ) -> PoseEstimate:
    """``dm``, ``dm+``, ``dm-paper`` (:class:`~cutterpose.solvers.method.RangeSearchMethod`).
    Without the keywords: the synthetic protocol's range. With them (the pipeline):
    ``motion_range`` the rig's; ``start`` a close pose ``(R, t_mm)`` (the field chain's
    outline homography): ``dm+`` refines from it directly when its check passes
    (``close_start_rms_px``, :func:`refine_from_close_start`); a ``partial`` corner set
    matches from ``start`` (or the range's centre); otherwise the initial pose (section 2.2)
    searches the range widened by :func:`_search_range`."""
    t0 = time.perf_counter()
    name = "dm-paper" if paper_initial else ("dm+" if refine else "dm")

    def done(est):
        est.method = name
        est.time_ms = (time.perf_counter() - t0) * 1e3
        return est

    if refine and start is not None and close_start_rms_px is not None:
        est = refine_from_close_start(points_px, camera, model, start,
                                      motion_range=motion_range, partial=partial,
                                      max_rms_px=close_start_rms_px)
        if est:
            return done(est)
    if partial:
        return done(distance_match(points_px, camera, model, start, motion_range=motion_range,
                                   refine=refine, partial=True))
    first = initial_pose_paper if paper_initial else initial_pose
    init = (first(points_px, camera, model) if motion_range is None
            else first(points_px, camera, model, _search_range(motion_range)))
    if not init:
        return PoseEstimate.failure(name, f"initial pose: {init.reason}", info=init.info,
                                    time_ms=(time.perf_counter() - t0) * 1e3)
    est = distance_match(points_px, camera, model, init, motion_range=motion_range,
                         refine=refine)
    est.info["initial_dof"] = pose_dof(init.R_cam_holder, init.t_cam_holder_mm).tolist()
    return done(est)


def solve_dm(points_px, camera: Camera, model: Holder, **context) -> PoseEstimate:
    """Registered method ``dm``: initial pose (sphere) + the paper's distance matching
    (``context``: :func:`_solve`'s keywords)."""
    return _solve(points_px, camera, model, refine=False, **context)


def solve_dm_paper(points_px, camera: Camera, model: Holder, **context) -> PoseEstimate:
    """Registered method ``dm-paper``: the paper as written, its own initial pose (image-plane
    vanishing points, section 2.2) + its distance matching (section 2.3)."""
    return _solve(points_px, camera, model, refine=False, paper_initial=True, **context)


def solve_dm_plus(points_px, camera: Camera, model: Holder, **context) -> PoseEstimate:
    """Registered method ``dm+``: ``dm`` + continuous one-to-one least-squares refinement."""
    return _solve(points_px, camera, model, refine=True, **context)


class Dm(RangeSearchMethod):
    name = "dm"
    description = "distance matching (paper 2.3)"
    solve = staticmethod(solve_dm)


class DmPaper(RangeSearchMethod):
    name = "dm-paper"
    description = "the paper as written: its initial pose (2.2) + distance matching (2.3)"
    solve = staticmethod(solve_dm_paper)


class DmPlus(RangeSearchMethod):
    name = "dm+"
    description = "distance matching + continuous correspondence-free refinement"
    solve = staticmethod(solve_dm_plus)
