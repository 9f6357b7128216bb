"""The result every solver returns: :class:`PoseEstimate`.

A solver either raises a typed :mod:`cutterpose.errors` exception for bad input, or returns a
``PoseEstimate``. A failed estimate is *falsy* and carries the reason, never a pose that looks
valid (the scikit-image estimator convention)::

    est = solve(points_px, camera, holder)
    if not est:
        print("no pose:", est.reason)
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np

from ..geometry.pose import Pose

__all__ = ["PoseEstimate"]


@dataclass
class PoseEstimate:
    """A solver's answer.

    Attributes
    ----------
    method : name of the solver.
    R_cam_holder, t_cam_holder_mm : the pose (holder in camera frame), or None on failure.
    reason : why there is no pose (empty when there is one).
    residual_px : RMS reprojection error of the selected pose, in ideal pixels.
    ambiguity_ratio : RMS error of the best candidate over that of the second best (in [0, 1]);
        close to 1 means two candidates explain the data almost equally well (the planar
        two-fold ambiguity); NaN when the solver produced a single candidate.
    candidates : every admissible candidate as ``(R, t)``, best first.
    time_ms : wall time of the solve.
    info : solver-specific diagnostics for people (counts, iterations...); no caller reads
        what it needs from it: the evidence a method's budget or the tracker uses is typed
        below.
    assignment : the corners' one-to-one assignment (``dm+``): per model corner the index of
        its detected corner (a full set), or ``(k, 2)`` rows ``(model, detected)`` of a
        partial one; None when the method made none.
    start : the estimate a refinement started from (``dm+b``: the outline's or ``dm+``'s pose),
        or None.
    start_failed : why a refinement's first start (the outline's pose) gave no pose, when it
        then started from the corners' pose ('' otherwise).
    band : ``dm+b``'s band fit (:class:`cutterpose.solvers.edge_band.BandPose`), else None.
    radius_fit : ``dm+r``'s radius fit (:class:`cutterpose.solvers.edge_radius.RadiusFit`),
        else None.
    """

    method: str
    R_cam_holder: np.ndarray | None = None
    t_cam_holder_mm: np.ndarray | None = None
    reason: str = ""
    residual_px: float = math.nan
    ambiguity_ratio: float = math.nan
    candidates: list = field(default_factory=list)
    time_ms: float = math.nan
    info: dict = field(default_factory=dict)
    assignment: list | None = None
    start: PoseEstimate | None = None
    start_failed: str = ""
    band: object | None = None
    radius_fit: object | None = None

    @property
    def ok(self) -> bool:
        return self.R_cam_holder is not None and not self.reason

    def __bool__(self) -> bool:
        return self.ok

    @property
    def pose(self) -> Pose:
        if not self.ok:
            raise ValueError(f"{self.method} found no pose: {self.reason}")
        return Pose(self.R_cam_holder, self.t_cam_holder_mm)

    @classmethod
    def failure(cls, method: str, reason: str, **kw) -> PoseEstimate:
        return cls(method=method, reason=reason or "failed", **kw)

    def to_dict(self) -> dict:
        d = {"method": self.method, "ok": self.ok, "reason": self.reason,
             "residual_px": _f(self.residual_px), "ambiguity_ratio": _f(self.ambiguity_ratio),
             "time_ms": _f(self.time_ms)}
        if self.ok:
            d["pose"] = self.pose.to_dict()
        return d


def _f(x):
    return None if x is None or not math.isfinite(x) else float(x)
