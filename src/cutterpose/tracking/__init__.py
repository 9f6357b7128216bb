"""Tracking the holder while the robot approaches it: one pose per frame, fast.

The first frame (and any frame where tracking fails) is measured in full
(:func:`cutterpose.pipeline.measure`: region search, threshold, contour segmentation, dm+).
From the second frame on, the previous poses predict where every edge of the holder's inner
contour lies, and the region search, threshold and contour segmentation are skipped:

1. **prediction** (:mod:`.prediction`): constant velocity on SE(3) (:mod:`cutterpose.geometry.se3`);
2. **edges, pose and checks** (:mod:`.line_step`): the field chain's line step on the model
   edges projected with the prediction, Gauss-Newton on the distances of the projected ends
   of every seen edge to its line, and the checks that send a frame to the full measurement
   with the reason;
3. **broken edges** (:mod:`.moved_model`, ``method="dm+b"``, the default): the tracker fits the
   design contour moved edge by edge onto the innermost rise it tracks, the offsets measured at
   full measurements and re-measured (*re-anchored*, :mod:`.anchoring`) by the band fit as the
   view changes; a tracked pose is then the design edge's;
4. **jobs beside the tracking** (:mod:`.anchoring`, :mod:`.worker`): re-anchors and fall-backs
   on a worker process, applied a fixed number of frames later;
5. **temporal filter** (:mod:`.filter`, optional): an alpha-beta filter on SE(3), reported
   beside the raw pose.

:class:`Tracker` (:mod:`.tracker`) composes them; :class:`TrackParams` (:mod:`.parameters`)
holds the 31 parameters, :class:`TrackResult` (:mod:`.result`) one frame's answer. All of this
in detail, with the conventions of frames, times and deferred jobs: ``docs/tracking.md``.

Convention:
    Poses ``T_cam_holder`` as in :mod:`cutterpose.geometry.pose` (``x_cam = R x_holder + t``,
    mm, deg). Twists ``xi = (omega [rad], rho [mm])`` with ``Exp(xi) = (Exp(omega),
    V(omega) rho)``. Pixels: ``*_px`` observed, ``*_ideal_px`` undistorted (ideal pinhole ``K``).
    Edge ``k`` of the model runs from corner ``k`` to corner ``k + 1`` (``holder.json``
    order) and corner ``i`` is the intersection of edges ``i - 1`` and ``i``, as in the field
    chain (:func:`cutterpose.image.features.detect_features_field`).

References:
    T. Drummond, R. Cipolla, "Real-time visual tracking of complex structures", PAMI 24(7),
    2002; T. Barfoot, *State Estimation for Robotics*, 2017, sec. 7.1; P. Kalata, "The
    tracking index", IEEE TAES 20(2), 1984.
"""

from ..geometry.se3 import se3_exp, se3_log

# the re-anchor's band fit, looked up here at call time (:func:`.anchoring.band_fit`)
from ..solvers.edge_band import measure_band
from .filter import PoseFilter
from .line_step import bands_moved_px
from .line_step import bands_moved_px as _bands_moved_px  # noqa: F401 - its tests' name
from .moved_model import line_offsets_mm, offset_edge_ends_mm, offset_polygon_mm
from .parameters import TrackParams, approach_limits, approach_params
from .result import TrackResult
from .tracker import Tracker

__all__ = ["TrackParams", "TrackResult", "Tracker", "PoseFilter", "approach_limits",
           "approach_params", "se3_exp", "se3_log", "offset_polygon_mm",
           "offset_edge_ends_mm", "line_offsets_mm", "bands_moved_px", "measure_band"]
