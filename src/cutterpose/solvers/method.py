"""A pose method: one object that turns the image's features into a pose and says how far off
that pose may be (:class:`PoseMethod`).

Every method has

* ``estimate(features, camera, holder, context) -> PoseEstimate``: the pose from what the image
  stage found (:class:`cutterpose.image.Features`), ``context`` the measurement's limits and
  cell calibration (:class:`MethodContext`);
* ``budget(estimate, features, camera, holder, limits) -> ErrorBudget``: its error budget
  (:mod:`cutterpose.budget`), with the residuals the verdict judges;
* ``review(quality, ...)``: its own checks after the common verdict
  (:func:`cutterpose.verdict.verdict`), by default none;
* ``solve(points_px, camera, model) -> PoseEstimate``: the pose from the corners alone (the
  synthetic experiments);
* what the front ends and the tracker ask instead of testing names: ``needs_correspondences``
  (its ``solve`` gets the corners in model order), ``needs_corners`` (the image stage must find
  the corners for it), ``refines_design_edge`` (its pose is the design edge's, beyond the
  innermost rise the corners follow: the tracker measures the tracked edges' offsets from it)
  and ``reanchors`` (its design edge is measured again from a tracked pose and the image
  alone, by the band fit: the tracker's re-anchors, :mod:`cutterpose.tracking.anchoring`).

The families are small base classes: :class:`CorrespondenceMethod` (PnP: the corners with
their model points), :class:`ContourMethod` (correspondence-free, the corners in contour order:
``initial``), :class:`RangeSearchMethod` (correspondence-free searches of the rig's working
range: ``dm``, ``dm+``, ``dm-paper``), all three judged by the corners' budget
(:mod:`cutterpose.solvers.corners`), and :class:`RefinementMethod` (a method that refines
another method's pose with more than the corners: ``dm+r``, ``dm+b``, each with its own
budget). The registry (:mod:`cutterpose.methods`) maps names to classes; docs/pose_methods.md
shows how to add one.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import TYPE_CHECKING

import numpy as np

from ..budget import ErrorBudget
from ..geometry.camera import Camera
from ..geometry.holder import Holder
from ..geometry.pose import pose_from_plane_homography
from ..geometry.working_range import MotionRange
from ..verdict import Quality, QualityLimits
from .corners import corner_budget, corner_review, has_corners, order_for_model
from .estimate import PoseEstimate

if TYPE_CHECKING:
    from ..image import Features

__all__ = ["PoseMethod", "MethodContext", "CornerMethod", "CorrespondenceMethod",
           "ContourMethod", "RangeSearchMethod", "RefinementMethod", "FunctionMethod"]


@dataclass(frozen=True)
class MethodContext:
    """What a method may use beyond the features: the measurement's ``limits`` (working range,
    edge shape, ...), the ``edge_look`` calibrated in the cell
    (:class:`cutterpose.calibration.edge_look.EdgeLookCalibration`, or None) and, on a second
    attempt, why the first start failed (``start_failed``: :meth:`RefinementMethod.estimate`)."""

    limits: QualityLimits = field(default_factory=QualityLimits)
    edge_look: object = None
    start_failed: str | None = None


class PoseMethod:
    """The protocol every pose method follows (module doc). Subclasses set ``name`` and
    ``description`` and implement :meth:`estimate`, :meth:`budget` and :meth:`solve`."""

    name: str = ""
    description: str = ""
    #: the method class whose pose this one refines (:class:`RefinementMethod`), else None
    base: type[PoseMethod] | None = None
    needs_correspondences: bool = True
    needs_corners: bool = True
    refines_design_edge: bool = False
    reanchors: bool = False

    def solve(self, points_px, camera: Camera, model) -> PoseEstimate:
        """The pose from the corners alone (``points_px`` in model order when
        ``needs_correspondences``, else in contour order with an unknown start and
        direction)."""
        raise NotImplementedError

    def estimate(self, features: Features, camera: Camera, holder: Holder,
                 context: MethodContext) -> PoseEstimate:
        """The pose from the image's features (falsy with the reason when there is none)."""
        raise NotImplementedError

    def budget(self, estimate: PoseEstimate, features: Features, camera: Camera,
               holder: Holder, limits: QualityLimits) -> ErrorBudget:
        """The error budget of a (truthy) ``estimate`` of this method."""
        raise NotImplementedError

    def review(self, quality: Quality, estimate: PoseEstimate, features: Features,
               camera: Camera, holder: Holder, limits: QualityLimits) -> Quality:
        """The method's own checks after the common verdict (none by default)."""
        return quality

    def __repr__(self) -> str:
        return f"<pose method {self.name}>"


def _corners(features: Features) -> tuple[np.ndarray, np.ndarray]:
    c = np.asarray(features.corners_px, float)
    return c, np.isfinite(c).all(axis=1)


class CornerMethod(PoseMethod):
    """A method that fits the detected corners: judged by the corners' budget and checks
    (:func:`~cutterpose.solvers.corners.corner_budget`,
    :func:`~cutterpose.solvers.corners.corner_review`)."""

    def budget(self, estimate, features, camera, holder, limits) -> ErrorBudget:
        return corner_budget(estimate, features, camera, holder, limits)

    def review(self, quality, estimate, features, camera, holder, limits) -> Quality:
        return corner_review(self.name, quality, estimate, features, camera, holder, limits)


class CorrespondenceMethod(CornerMethod):
    """PnP: the seen corners with their model points, in model order (on the paper's chain
    the contour order made model order: :func:`~cutterpose.solvers.corners.order_for_model`).
    A subclass gives ``solve(points_px, camera, model)``, ``model`` a holder or (n, 3)
    points."""

    def estimate(self, features, camera, holder, context) -> PoseEstimate:
        corners, seen = _corners(features)
        if features.order != "holder":
            return self.solve(order_for_model(corners, camera, holder), camera, holder)
        if seen.all():
            return self.solve(corners, camera, holder)
        return self.solve(corners[seen], camera, holder.points_holder_mm[seen])


class FunctionMethod(CorrespondenceMethod):
    """A correspondence method made from a function ``solve(points_px, camera, model)`` (an
    experiment's or a test's solver, not registered)."""

    def __init__(self, name: str, solve, needs_correspondences: bool = True,
                 description: str = ""):
        self.name, self.description = name, description
        self.needs_correspondences = needs_correspondences
        self._solve = solve

    def solve(self, points_px, camera, model) -> PoseEstimate:
        return self._solve(points_px, camera, model)


class ContourMethod(CornerMethod):
    """Correspondence-free on the full contour (``initial``): all corners, in contour order
    with an unknown start and direction."""

    needs_correspondences = False

    def estimate(self, features, camera, holder, context) -> PoseEstimate:
        corners, seen = _corners(features)
        if features.order == "holder" and not seen.all():
            return PoseEstimate.failure(self.name, f"needs all {holder.n_corners} corners, "
                                        f"{int(seen.sum())} seen")
        return self.solve(corners, camera, holder)


class RangeSearchMethod(CornerMethod):
    """Correspondence-free search of the rig's working range (``dm``, ``dm+``, ``dm-paper``).
    A subclass gives ``solve(points_px, camera, model, **search)`` taking the keywords
    ``motion_range`` (the working range), ``start`` (a close ``(R, t_mm)`` or None),
    ``partial`` (some corners missing or spurious) and ``close_start_rms_px``. On the field
    chain it gets the seen corners, unordered, and the pose of the outline's homography as its
    start."""

    needs_correspondences = False

    def estimate(self, features, camera, holder, context) -> PoseEstimate:
        limits = context.limits
        corners, seen = _corners(features)
        rng = MotionRange(center_dof=limits.range_center_dof,
                          half_width_dof=limits.range_half_width_dof)
        field_chain = features.order == "holder"
        H = features.H_ideal_holder
        start = pose_from_plane_homography(H, camera.K) if field_chain and H is not None \
            else None
        return self.solve(corners[seen] if field_chain else corners, camera, holder,
                          motion_range=rng, start=start, partial=field_chain and not seen.all(),
                          close_start_rms_px=limits.max_rms_px if field_chain else None)


class RefinementMethod(PoseMethod):
    """A method that refines the pose of ``base`` (a method class) with more than the corners
    (the edge model, the image). A subclass gives :meth:`refine` and :meth:`budget`, and may
    give :meth:`first_start`: a start of its own (the pocket outline's pose for ``dm+b``),
    tried before ``base``'s pose. When the refinement from it gives no pose, it starts from
    ``base``'s pose on the corners; without corners in the features it returns the failure, and
    :func:`cutterpose.pipeline.measure` detects them and calls again with the first attempt's
    reason in ``context.start_failed`` (so that it is not repeated)."""

    needs_correspondences = False
    refines_design_edge = True

    def refine(self, start: PoseEstimate, features: Features, camera: Camera, holder: Holder,
               context: MethodContext) -> PoseEstimate:
        raise NotImplementedError

    def first_start(self, features: Features, camera: Camera) -> PoseEstimate | None:
        """A start of the method's own, tried before ``base``'s pose (None: none)."""
        return None

    def estimate(self, features, camera, holder, context) -> PoseEstimate:
        failed = context.start_failed
        if failed is None:
            first = self.first_start(features, camera)
            if first is not None:
                est = self.refine(first, features, camera, holder, context)
                if est or not has_corners(features):
                    return est
                failed = est.reason
        start = self.base().estimate(features, camera, holder, context)
        est = self.refine(start, features, camera, holder, context)
        if failed is not None:
            est.start_failed = failed
        return est
