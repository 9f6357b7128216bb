"""One frame's answer of the tracker (:class:`TrackResult`)."""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np

from ..geometry.pose import Pose
from ..pipeline import DOF_NAMES, Measurement

__all__ = ["TrackResult"]


@dataclass
class TrackResult:
    """One frame's answer.

    Attributes
    ----------
    frame : the frame's index (0-based, in the order given to the tracker); ``frame_id``
        the camera's frame number given with it (:meth:`Tracker.update`), else ``frame``.
    mode : ``"track"`` (predicted edges), ``"full"`` (the full measurement: first frame or a
        fall-back) or ``"lost"`` (no pose; also a deferred fall-back's frame, docs/tracking.md).
    pose : the raw per-frame pose (None when lost); ``std_dof`` its std per DOF (tracking
        with ``dm+b``: the fit's and the last anchor's in quadrature, docs/tracking.md).
    ok : the pose passed the checks (tracking) or the verdict (full).
    fallback_reason : why tracking was not used on this frame ("" when tracked).
    filtered_pose : the temporal filter's pose (None without filter or pose); ``filter_reset``
        the reason it was reset on this frame ("" otherwise).
    rms_px : RMS residual (tracking: model-to-edge distances; full: corners);
        ``edge_support`` the lowest inlier share of a seen edge.
    corners_px : (20, 2) corners, model order with NaN where an edge is not seen (tracking),
        or those of the full measurement.
    measurement : the full measurement when one was made (on the frame that takes up a
        deferred fall-back: that of the frame it was started on).
    timings_ms : wall time per stage.
    """

    frame: int
    mode: str
    pose: Pose | None
    std_dof: np.ndarray
    ok: bool
    fallback_reason: str = ""
    filtered_pose: Pose | None = None
    filter_reset: str = ""
    rms_px: float = math.nan
    edge_support: float = math.nan
    corners_px: np.ndarray | None = None
    measurement: Measurement | None = None
    timings_ms: dict = field(default_factory=dict)
    passes: int = 0   #: edge passes (tracking: 2 when the first pass's fit moved the bands)
    lines_seen: int = 0    #: tracking: edges with enough inlier support (of the holder's)
    corners_used: int = 0  #: tracking: corners whose two lines were seen
    lines_dropped: int = 0  #: tracking: seen edges left out as off the fitted model
    #: ``dm+b`` tracking: "re-anchored" when the edges' offsets from the design edge were
    #: measured again on this frame, "re-anchor refused: ..." when the band fit was refused
    #: (the previous offsets kept); deferred (``TrackParams.anchor_lag``): "re-anchor
    #: started" on the frame measured, "re-anchored (frame j)" / "re-anchor (frame j)
    #: refused ..." on the frame its result is applied on; "" otherwise
    anchor: str = ""
    #: tracking: the (N, 3) edge lines (ideal px, NaN where not seen) and which edges the pose
    #: rests on (after the outliers were left out)
    lines_ideal: np.ndarray | None = field(default=None, repr=False)
    edges_used: np.ndarray | None = field(default=None, repr=False)
    #: tracking: every edge line found (before the outlier test) and which edges they are:
    #: an anchor measures the offsets of the edges used and of those found whose offset no
    #: anchor has measured yet
    lines_found: np.ndarray | None = field(default=None, repr=False)
    edges_found: np.ndarray | None = field(default=None, repr=False)
    frame_id: int = -1

    def to_dict(self) -> dict:
        """One JSON object of ``cutterpose track --json-lines``."""
        def f(x):
            return None if x is None or not math.isfinite(float(x)) else float(x)

        return {"frame": self.frame, "frame_id": self.frame_id, "mode": self.mode,
                "ok": self.ok,
                "fallback_reason": self.fallback_reason,
                "pose": None if self.pose is None else self.pose.to_dict(),
                "std": {k: f(v) for k, v in zip(DOF_NAMES, self.std_dof)},
                "filtered_pose": None if self.filtered_pose is None
                else self.filtered_pose.to_dict(),
                "filter_reset": self.filter_reset, "rms_residual_px": f(self.rms_px),
                "edge_support": f(self.edge_support), "passes": self.passes,
                "lines_seen": self.lines_seen, "corners_used": self.corners_used,
                "lines_dropped": self.lines_dropped, "anchor": self.anchor,
                "timings_ms": {k: round(float(v), 3) for k, v in self.timings_ms.items()}}
