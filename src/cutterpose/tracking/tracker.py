"""The tracker: one pose per frame while the robot approaches the holder, composed of its parts.

:class:`Tracker` puts together the prediction (:mod:`.prediction`), the line step
(:mod:`.line_step`) on the moved model (:mod:`.moved_model`), the full measurements and
re-anchors (:mod:`.anchoring`, on the worker of :mod:`.worker`) and the temporal filter
(:mod:`.filter`); each part is a class of its module holding that part's methods, and the
tracker is the one object whose state they share (each part's docstring lists the state it
keeps). Here: the frame loop (:meth:`Tracker.update`) that decides, per frame, between the
tracked pose, a re-anchor and a full measurement.
"""

from __future__ import annotations

import time
from concurrent.futures import ThreadPoolExecutor

import numpy as np

from ..errors import CutterposeError, InputError
from ..frames import load_frame
from ..geometry.camera import Camera, default_camera
from ..geometry.holder import Holder, default_holder
from ..geometry.pose import Pose
from ..image import FeatureParams, as_grey_u8
from ..image.region import prepare_outline_search
from ..methods import get_method
from ..pipeline import Measurement, QualityLimits
from .anchoring import Anchoring, DeferredAnchor, DeferredFull, full_measurement
from .filter import PoseFilter
from .line_step import LineStep
from .moved_model import MovedModel
from .parameters import TrackParams, approach_limits, approach_params
from .prediction import Prediction
from .result import TrackResult
from .worker import AnchorProcess

__all__ = ["Tracker"]


class Tracker(Prediction, LineStep, MovedModel, Anchoring):
    """Pose of the holder in a sequence of frames (module doc).

    Parameters
    ----------
    camera, holder : defaults: the Table 1 camera and ``holder.json``.
    method : the full measurement's pose method (first frame and fall-backs; default ``dm+b``,
        as :func:`~cutterpose.pipeline.measure`'s). With ``dm+b`` (and ``dm+r``) the tracker
        fits the design contour moved edge by edge onto the edges it tracks (the innermost
        rise of the broken edge), the offsets measured at the full measurement; ``dm+b``
        measures them again from the tracked pose as the view changes (docs/tracking.md, "Broken
        edges").
    params, limits : the full measurement's image parameters and quality limits (default: an
        approach from 940 to 580 mm, :func:`approach_params` and :func:`approach_limits`).
    track : :class:`TrackParams`.
    filter : also report the temporal filter's pose.
    edge_look : the edge look calibrated in the cell
        (:func:`cutterpose.calibration.edge_look.load_edge_look`): ``dm+b``'s full measurements
        and re-anchors fit it instead of the generic looks.
    anchor_worker : with ``TrackParams.anchor_lag > 0``, where the deferred re-anchors' band
        fits run: ``"process"`` (a worker process, started with the tracker), ``"thread"`` or
        ``"inline"`` (on the frame they are measured on); the same poses with each.
        :meth:`close` (or ``with Tracker(...)``) ends the worker.

    Examples
    --------
    >>> tracker = Tracker(camera, holder, filter=True)          # doctest: +SKIP
    >>> for frame in frames:                                    # doctest: +SKIP
    ...     r = tracker.update(frame)
    ...     print(r.mode, r.pose.dof, r.fallback_reason)
    """

    def __init__(self, camera: Camera | None = None, holder: Holder | None = None,
                 method: str = "dm+b", params: FeatureParams | None = None,
                 limits: QualityLimits | None = None, track: TrackParams | None = None,
                 filter: bool = False, edge_look=None, anchor_worker: str = "process"):
        if anchor_worker not in ("process", "thread", "inline"):
            raise InputError(f"anchor_worker must be process, thread or inline, got "
                             f"{anchor_worker!r}")
        self.camera = camera or default_camera("table1")
        self.anchor_worker = anchor_worker
        self._executor: ThreadPoolExecutor | AnchorProcess | None = None
        self.edge_look = edge_look
        self.holder = holder or default_holder()
        self.method = method
        self._method = get_method(method)
        #: the method's pose is the design edge's, beyond the innermost rise the corners follow
        #: (dm+b, dm+r): the tracker carries its edges' offsets from the design edge
        self._refines = self._method.refines_design_edge
        self.params = params or approach_params(self.camera)
        self.limits = limits or approach_limits()
        self.tp = (track or TrackParams()).for_camera(self.camera)
        self.K = np.array(self.camera.K, float)
        self._refine_params = FeatureParams.for_camera(
            self.camera, refine_half_width_px=self.tp.band_half_width_px,
            refine_step_px=self.tp.profile_step_px, refine_passes=self.tp.passes,
            refine_trim_px=self.tp.end_trim_px)
        self._line_cache: dict = {}
        self.filter = PoseFilter(self.tp.filter_alpha, self.tp.filter_beta, self.tp.gate_mm,
                                 self.tp.gate_deg) if filter else None
        self.reset()
        # the full measurement's outline templates (~190 ms for the approach's five depths,
        # once per process): built now, before the first frame arrives
        prepare_outline_search(self.camera, self.holder, self.params)
        if anchor_worker == "process" and self.tp.anchor_lag > 0 and (
                self._method.reanchors or self.tp.defer_fallbacks):
            # started now: the spawn and its imports (~1 s) run beside the first frame's full
            # measurement instead of delaying the first re-anchor
            w, h = self.camera.image_size_px
            self._executor = AnchorProcess((h, w), self.camera, self.holder, self.params)

    def reset(self) -> None:
        """Forget the past: the next frame is measured in full."""
        self._reset_model()
        self._anchor_t_mm: np.ndarray | None = None   # where the offsets were measured
        self._anchor_frame = -1
        self._anchor_std = np.zeros(6)   # std of the pose the offsets were measured at
        self._anchors = 0   # measurements of the offsets since the last full measurement
        self._attempts = 0  # re-anchors tried since then
        self._last: Pose | None = None
        self._last_k = -1   # its frame
        #: the motion per frame (R, t) that carries _last on (None: not known)
        self._vel: tuple | None = None
        self._after_full = False   # no frame tracked since the last full measurement
        #: frame times (``update(..., t_s=)``); without them a frame's time is its index
        self._frame_t: dict[int, float] = {}
        self._timed = False
        #: the camera's frame numbers (``update(..., frame_id=)``): messages name frames by
        #: them; without them by the update count
        self._frame_ids: dict[int, int] = {}
        self._named = False
        self._filter_k: int | None = None   # the frame the filter last took
        self._rms_ref = 0.0   # corner RMS of the last accepted full measurement (px)
        self._n = 0
        self._pending: DeferredAnchor | None = None
        self._pending_full: DeferredFull | None = None
        if self.filter is not None:
            self.filter.reset()

    def ready(self, timeout_s: float | None = None) -> bool:
        """Wait until the worker process (``anchor_worker="process"`` with ``anchor_lag > 0``)
        has started and imported what it runs (~1-2 s after the tracker was made): call it
        before the approach begins, so that the first deferred job does not queue behind the
        start-up. True when ready (at once without a worker process); False after
        ``timeout_s``, or when the worker failed to start (its jobs then fail and fall back
        with the reason)."""
        warm = getattr(self._executor, "warm", None)
        if warm is None:
            return True
        try:
            warm.result(timeout_s)
        except Exception:  # noqa: BLE001 - a timeout or a dead worker: not ready
            return False
        return True

    @classmethod
    def from_station(cls, station, track: TrackParams | None = None, filter: bool = False,
                     anchor_worker: str = "process") -> Tracker:
        """A tracker at a measuring station (:class:`cutterpose.station.Station`: its camera,
        holder, method, image parameters, limits and edge look; for an approach build it with
        ``params=approach_params(camera)`` and ``limits=approach_limits()``)."""
        return cls(station.camera, station.holder, station.method, station.params,
                   station.limits, track, filter, station.edge_look, anchor_worker)

    def close(self) -> None:
        """End the deferred re-anchors' worker (process or thread), if one was started."""
        if self._executor is not None:
            ex, self._executor = self._executor, None
            ex.shutdown(wait=True, cancel_futures=True)

    def __enter__(self) -> Tracker:
        return self

    def __exit__(self, *exc) -> None:
        self.close()

    # -- one frame ---------------------------------------------------------------------
    def update(self, image, t_s: float | None = None,
               frame_id: int | None = None) -> TrackResult:
        """Pose in the next frame (array, raw buffer of the camera's size, or a file).

        ``t_s``: the frame's time (s, the camera's timestamp), for a driver that hands over
        the newest frame and skips those that came while the tracker was busy: the motion is
        then predicted per second, not per frame. ``frame_id``: the camera's frame number
        (increasing; frames skipped by such a driver leave gaps): the result carries it
        (``TrackResult.frame_id``) and the messages name frames by it (a job's take-up, due
        a number of updates on, by that number). Give each for every frame or for none."""
        k = self._n
        res = self._update(image, t_s, frame_id)
        res.frame_id = self._frame_ids.get(k, k)
        return res

    def _update(self, image, t_s, frame_id) -> TrackResult:
        t0 = time.perf_counter()
        img = as_grey_u8(load_frame(image, self.camera))
        k = self._n
        self._stamp(k, t_s, frame_id)
        self._n += 1
        timings: dict[str, float] = {}
        reason = "first frame" if k == 0 else "no previous pose"
        full, note_full, fresh, why = self._take_due_full(k, timings)
        reason = why or reason
        pending = self._pending_full
        if pending is not None:
            note_full = (f"full measurement of {self._name(pending.frame)} pending "
                         f"(applied {self._due(pending.at, k)})")
        # a deferred re-anchor due on this frame is taken up before the frame is tracked
        why, note = self._take_anchor(k, timings) if self._last is not None else ("", "")
        if why:
            reason = why
        elif self._last is not None:
            try:
                res = self._track(img, k, timings)
            except CutterposeError as e:
                res = None
                reason = f"{type(e).__name__}: {e}"
            else:
                if isinstance(res, str):
                    reason, res = res, None
            if res is not None:
                res.anchor = "; ".join(filter(None, [note_full, note]))
                res.measurement = full
                # the offsets were measured at a pose with its own error, which every tracked
                # pose inherits (zero without offsets)
                if self._offset_mm is not None:
                    res.std_dof = np.hypot(res.std_dof, self._anchor_std)
                if self._anchor_due(res.pose, k):
                    if self.tp.anchor_lag > 0:
                        self._start_anchor(img, res)
                    else:
                        try:
                            res = self._reanchor(img, res, timings)
                        except CutterposeError as e:
                            res = f"re-anchor: {type(e).__name__}: {e}"
                        if isinstance(res, str):
                            reason, res = res, None
            if res is not None:
                self._moved_to(res.pose, k)
                res.timings_ms = timings | {"total": (time.perf_counter() - t0) * 1e3}
                self._filter(res, f"fall-back: {note_full}" if fresh else "")
                return res
            if note_full:
                reason = f"tracking after the {note_full}: {reason}" if fresh else \
                    f"{reason} ({note_full})"
        if pending is not None:
            # its full measurement is on its way: this frame goes without a pose
            return self._no_pose(k, reason, None, timings, t0, forget=False)
        # full measurement (a pending re-anchor belongs to the poses before it: a band fit
        # still queued on the worker is not run, one running is left to finish unread)
        if self._pending is not None:
            self._pending.future.cancel()
        self._pending = None
        if k > 0 and self.tp.anchor_lag > 0 and self.tp.defer_fallbacks:
            return self._start_full(img, k, reason, timings, t0)
        t1 = time.perf_counter()
        m = full_measurement(img, self.camera, self.holder, self.method, self.params,
                             self.limits, self.edge_look)
        timings["full"] = (time.perf_counter() - t1) * 1e3
        if not m.ok:
            return self._no_pose(k, f"{reason}; full measurement: {m.quality.reason}", m,
                                 timings, t0)
        self._accept_full(img, k, m)
        res = TrackResult(k, "full", m.pose, m.std_dof, True, reason,
                          rms_px=m.quality.rms_px, corners_px=m.corners_px, measurement=m)
        self._filter(res, f"fall-back: {reason}" if k else "first pose")
        res.timings_ms = timings | {"total": (time.perf_counter() - t0) * 1e3}
        return res

    def _take_due_full(self, k: int, timings: dict):
        """A deferred fall-back (docs/tracking.md) due on frame ``k``, taken up: ``(measurement,
        note, fresh, reason)``: ``fresh`` when it was applied; ``reason`` (the last pose
        forgotten) when it could not be and nothing was tracked since its frame."""
        full, note_full, fresh, reason = None, "", False, ""
        if self._pending_full is not None and k >= self._pending_full.at:
            j = self._pending_full.frame
            why, full = self._take_full(k, timings)
            if not why:
                note_full, fresh = f"full measurement of {self._name(j)} applied", True
            elif self._last is not None and self._last_k > j:
                # tracked since frame j: the tracking goes on with the offsets it has
                note_full = f"full measurement of {self._name(j)} not applied ({why})"
            else:
                self._last, reason = None, why
        return full, note_full, fresh, reason

    def _no_pose(self, k: int, reason: str, m: Measurement | None, timings: dict,
                 t0: float, forget: bool = True) -> TrackResult:
        """A frame without a pose ("lost"): the filter forgets its state, and with ``forget``
        the tracker its last pose (without: a deferred fall-back is on its way, and the next
        frames are tracked from the last pose meanwhile)."""
        if forget:
            self._last = None
        res = TrackResult(k, "lost", None, np.full(6, np.nan), False, reason, measurement=m)
        if self.filter is not None:
            self.filter.reset()
            self._filter_k = None
            res.filter_reset = "lost"
        res.timings_ms = timings | {"total": (time.perf_counter() - t0) * 1e3}
        return res

    def _filter(self, res: TrackResult, force: str) -> None:
        if self.filter is not None and res.pose is not None:
            k0 = self._filter_k
            dt = self._time(res.frame) - self._time(k0) if k0 is not None else 1.0
            res.filtered_pose, res.filter_reset = self.filter.update(res.pose, force, dt)
            self._filter_k = res.frame

    def track(self, frames) -> list[TrackResult]:
        """:meth:`update` over an iterable of frames."""
        return [self.update(f) for f in frames]
