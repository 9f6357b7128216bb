"""Anchoring: the tracker's full measurements and re-anchors, inline or beside the tracking.

A full measurement (first frame, a fall-back) sets the pose the tracking starts from and,
for a method that refines dm+'s pose with more than the corners (``dm+b``, ``dm+r``), the
offsets of the tracked edges from the design edge (:mod:`.moved_model`). ``dm+b`` measures the
offsets again (*re-anchors*) from a tracked pose as the view changes: a band fit
(:func:`band_fit`) judged by its own verdict and against the tracked pose.

**Jobs beside the tracking** (``TrackParams.anchor_lag = L > 0``): re-anchors and fall-backs
run on a worker (:class:`~cutterpose.tracking.worker.AnchorProcess`, a thread, or inline) and
are applied at the start of frame ``j + L``, fixed, so the poses do not depend on the worker
or the machine's speed; a fall-back's frame is answered at once without a pose and the frames
until ``j + L`` are tracked from the last pose (docs/tracking.md, "Jobs beside the tracking").
"""

from __future__ import annotations

import math
import time
from concurrent.futures import Future, ThreadPoolExecutor
from concurrent.futures.process import BrokenProcessPool
from dataclasses import dataclass

import numpy as np

from ..errors import CutterposeError
from ..geometry.camera import Camera
from ..geometry.holder import Holder
from ..geometry.pose import Pose, wrap_deg
from ..image import FeatureParams
from ..pipeline import (
    DOF_NAMES,
    Measurement,
    QualityLimits,
    band_verdict,
    corner_residual_px,
    measure,
)
from ..solvers.edge_band import as_band_looks
from ..solvers.estimate import PoseEstimate
from .result import TrackResult
from .worker import AnchorProcess

__all__ = ["band_fit", "full_measurement", "DeferredAnchor", "DeferredFull", "Anchoring"]


def band_fit(img: np.ndarray, camera: Camera, holder: Holder, pose: Pose,
             edges_used: np.ndarray, shapes, passes: int, looks, limits: QualityLimits):
    """A re-anchor's band fit from a tracked ``pose``
    (:func:`~cutterpose.solvers.edge_band.measure_band`) and its verdict (``dm+b``'s own,
    :func:`band_verdict`): ``(estimate, quality, ms)``."""
    # the band fit is looked up on the package at call time: ``cutterpose.tracking.
    # measure_band`` is the one seam through which a test replaces it
    from .. import tracking

    t = time.perf_counter()
    start = PoseEstimate("track", pose.R, pose.t_mm.copy())
    est = tracking.measure_band(img, camera, holder, start, edges_used, shapes, passes,
                                looks=looks)
    return est, band_verdict(est, limits), (time.perf_counter() - t) * 1e3


def full_measurement(img: np.ndarray, camera: Camera, holder: Holder, method: str,
                     params: FeatureParams, limits: QualityLimits, edge_look) -> Measurement:
    """A fall-back's full measurement (:func:`measure`, with the corners the tracker's
    offsets start from)."""
    return measure(img, camera, holder, method, params, limits, edge_look=edge_look,
                   corners=True)


@dataclass
class DeferredAnchor:
    """A re-anchor measured beside the tracking (docs/tracking.md, "Jobs beside the
    tracking")."""

    at: int                 #: the frame it is applied on
    future: Future          #: its band fit
    frame: int              #: the tracked frame it measures
    pose: Pose              #: that frame's tracked pose
    std: np.ndarray         #: and its std
    lines: np.ndarray       #: the lines tracking found there (ideal pixels)
    used: np.ndarray        #: which edges they are


@dataclass
class DeferredFull:
    """A fall-back measured beside the tracking (docs/tracking.md, "Jobs beside the
    tracking")."""

    at: int                 #: the frame it is applied on
    frame: int              #: the frame measured
    future: Future          #: its full measurement
    image: np.ndarray | None   #: that frame, for the offsets (methods that carry them)
    last: Pose | None       #: the last pose before it
    last_k: int             #: that pose's frame
    vel: tuple | None       #: the motion per unit of time then


class Anchoring:
    """The full measurements and re-anchors of :class:`~cutterpose.tracking.Tracker` (module
    doc). State: the anchor (``_anchor_t_mm``, ``_anchor_frame``, ``_anchor_std``, the
    measurements ``_anchors`` and attempts ``_attempts`` since the last full measurement), the
    jobs pending beside the tracking (``_pending``, ``_pending_full``) and their worker
    (``_executor``)."""

    def _accept_full(self, img: np.ndarray, k: int, m: Measurement) -> None:
        """Start again from an accepted full measurement of frame ``k`` (``img``): its pose,
        the velocity unknown."""
        # a method that refines dm+'s pose with more than the corners (dm+b: the design
        # edge from the bands): the tracker follows the edges the corners come from (the
        # innermost rise), so it measures here, at the measured design pose, how far
        # each of them lies from the design edge (docs/tracking.md, "Broken edges")
        refines = self._refines
        start = m.estimate.start if refines and m.estimate else None
        # the residual the tracked edges are held to: the corners' (dm+'s, for dm+b,
        # which starts from the outline and fits no corners itself)
        rms = start.residual_px if start is not None else m.quality.rms_px
        if refines and not np.isfinite(rms) and m.features is not None:
            rms = corner_residual_px(m.features, self.camera, self.holder, self.limits)
        self._rms_ref = float(rms) if np.isfinite(rms) else 0.0
        if refines:
            self._anchor_full(img, k, m)
        self._last, self._last_k, self._vel = m.pose, k, None
        self._after_full = True

    def _start_full(self, img: np.ndarray, k: int, reason: str, timings: dict,
                    t0: float) -> TrackResult:
        """A fall-back measured beside the tracking (docs/tracking.md, "Jobs beside the
        tracking"): this frame is answered at once without a pose, the next ones are tracked
        from the last pose meanwhile."""
        at = k + self.tp.anchor_lag
        fut = self._submit(full_measurement, img, self.camera, self.holder, self.method,
                           self.params, self.limits, self.edge_look)
        # the last pose and motion before the failure carry the measured pose to frame ``at``;
        # the frame itself is kept for the offsets of a method that has them (dm+b, dm+r)
        keep = np.array(img, copy=True) if self._refines else None
        self._pending_full = DeferredFull(at, k, fut, keep, self._last, self._last_k,
                                           self._vel)
        return self._no_pose(k, f"{reason}; full measurement started (applied "
                                f"{self._due(at, k)})", None, timings, t0, forget=False)

    def _take_full(self, k: int, timings: dict) -> tuple[str, Measurement | None]:
        """Take up the deferred full measurement due on frame ``k`` (waiting for it):
        ``("", measurement)`` with the offsets measured from its frame at its pose, and the
        frame tracked from that pose carried to it by the motion per frame of the poses
        tracked since (or before the failure; or, unknown, from the last pose before it to
        the measured one); or ``(reason, measurement or None)`` when it cannot be applied."""
        p, self._pending_full = self._pending_full, None
        j, fut, img_j, last, last_k, vel = p.frame, p.future, p.image, p.last, p.last_k, p.vel
        t = time.perf_counter()
        try:
            m = fut.result()
        except CutterposeError as e:
            return f"full measurement ({self._name(j)}): {type(e).__name__}: {e}", None
        except BrokenProcessPool as e:
            self.close()
            return (f"full measurement ({self._name(j)}): the worker process failed ({e})",
                    None)
        finally:
            timings["full_wait"] = (time.perf_counter() - t) * 1e3
        timings["full"] = float(m.timings_ms.get("total", math.nan))
        if not m.ok:
            return f"full measurement ({self._name(j)}): {m.quality.reason}", m
        # the poses tracked since frame j rest on the offsets before it: their motion per
        # frame carries the measured pose (a pose of theirs with the new offsets would be
        # off by the offsets' change: 2-3 px on worn holders)
        since = self._vel if self._last is not None and self._last_k > j else None
        self._accept_full(img_j, j, m)
        if since is not None:
            self._vel = since
        elif vel is not None:
            self._vel = vel
        elif last is not None and j > last_k:
            self._vel = self._motion(m.pose, j, last, last_k)
        return "", m

    def _anchor_full(self, img: np.ndarray, k: int, m: Measurement) -> None:
        """The offsets from the tracker's own edges in this frame, found from the fully
        measured design pose (the innermost rise of a broken edge, as tracking will see it).
        When those edges fail tracking's checks, the previous offsets are kept and the next
        tracked frame measures them again. With none yet, the lines found round the measured
        pose give them: the checks fit the model, and without offsets the model is what is
        off (a chipped edge's line 2.6 mm out of the design edge sat 8 px off it at 900 mm,
        and no frame could be tracked until a second full measurement's anchor passed)."""
        self._last, self._last_k, self._vel = m.pose, k, None
        self._set_view_model(m.edge_band)
        try:
            res = self._track(img, k, {})
        except CutterposeError:
            res = None
        self._anchors = self._attempts = 0
        if isinstance(res, TrackResult):
            self._set_offsets(m.pose, *self._anchor_lines(res), m.std_dof, k, 1.0)
            return
        self._anchor_t_mm = None
        if self._offset_mm is None:
            tp = self.tp
            found = self._lines_at(img, m.pose, tp.band_half_width_px * tp.cold_band_factor)
            if isinstance(found, str):
                return
            lines, seen, _ = found
            fam = np.bincount(np.nonzero(seen)[0] % 2, minlength=2)
            if seen.sum() >= tp.lines_needed(len(seen)) and fam.min() >= 2:
                self._set_offsets(m.pose, lines, seen, m.std_dof, k, 1.0)

    def _anchor_due(self, pose: Pose, k: int) -> bool:
        """A re-anchor on this tracked frame (a method that ``reanchors``, ``dm+b``: its band
        fit needs nothing but the image and a close pose)?"""
        if not self._method.reanchors or self._pending is not None or \
                self._pending_full is not None:
            return False
        tp = self.tp
        if self._anchor_t_mm is None or self._attempts < tp.anchor_warmup:
            return True
        scale = float(np.linalg.norm(pose.t_mm) / np.linalg.norm(self._anchor_t_mm))
        return (abs(scale - 1.0) > tp.anchor_scale_change
                or (tp.anchor_every > 0 and k - self._anchor_frame >= tp.anchor_every))

    def _anchor_lines(self, res: TrackResult) -> tuple[np.ndarray, np.ndarray]:
        """The lines an anchor measures the offsets of: the edges the tracked pose rests on
        and every edge found whose offset has not been measured yet (fitted by its direction
        until then, :meth:`_weigh_unmeasured`; one left out as an outlier keeps its offset)."""
        new = res.edges_found & ~(self._measured if self._measured is not None
                                  else np.zeros_like(res.edges_found))
        return res.lines_found, res.edges_used | new

    def _band_args(self, pose: Pose, edges_used: np.ndarray) -> tuple:
        """The arguments of :func:`band_fit` after the image (all picklable)."""
        return (self.camera, self.holder, pose, edges_used,
                self.limits.edge_shape_fits, self.tp.anchor_passes,
                as_band_looks(self.edge_look), self.limits)

    def _band_fit(self, img: np.ndarray, pose: Pose, edges_used: np.ndarray):
        """The re-anchor's band fit here (:func:`band_fit`)."""
        return band_fit(img, *self._band_args(pose, edges_used))

    def _apply_band(self, est, q, frame: int, pose: Pose, std_dof: np.ndarray,
                    lines: np.ndarray, edges_used: np.ndarray) -> tuple[str, str]:
        """Take up a re-anchor's band fit of frame ``frame`` (tracked ``pose``, ``lines``):
        ``("", "re-anchored")`` with the offsets measured, ``("", "re-anchor refused ...")``
        with the offsets kept, or ``(reason, "")`` when the band's design edge and the
        tracked pose disagree (the frame is then measured in full)."""
        if not q.ok:
            return "", f"re-anchor refused ({q.reason}): the last offsets kept"
        band = Pose(est.R_cam_holder, est.t_cam_holder_mm)
        std_band = q.budget.std_dof
        diff = band.dof - pose.dof
        diff[:3] = wrap_deg(diff[:3])
        z = np.abs(diff) / np.hypot(std_band, std_dof)
        j = int(np.argmax(z))
        if not z[j] <= self.tp.anchor_gate_sigma:
            return (f"re-anchor: the band's design edge and the tracked pose differ by "
                    f"{diff[j]:.3g} {DOF_NAMES[j].split('_')[1]} in {DOF_NAMES[j]} ({z[j]:.1f} "
                    f"std > {self.tp.anchor_gate_sigma}): the tracking or the band fit is "
                    "wrong"), ""
        self._set_offsets(band, lines, edges_used, std_band, frame,
                          max(self.tp.anchor_gain, 1.0 / (self._anchors + 1)),
                          est.band)
        return "", "re-anchored"

    def _reanchor(self, img: np.ndarray, res: TrackResult, timings: dict) -> TrackResult | str:
        """Measure the design edge again on a tracked frame (docs/tracking.md, "Broken
        edges"): the band fit from the tracked pose, judged by its own verdict and against the
        tracked pose; the offsets measured from this frame's tracked edges at the band's pose
        and the edges fitted again with them. The tracked frame (or, when the two poses
        disagree, the reason for a full measurement)."""
        t = time.perf_counter()
        # whatever the outcome, the next attempt after the view has changed as much again
        self._anchor_t_mm, self._anchor_frame = res.pose.t_mm.copy(), res.frame
        self._attempts += 1
        lines, used = self._anchor_lines(res)
        est, q, timings["anchor"] = self._band_fit(img, res.pose, used)
        why, note = self._apply_band(est, q, res.frame, res.pose, res.std_dof, lines, used)
        if why:
            return why
        if note != "re-anchored":
            res.anchor = note
            return res
        # the same edges fitted again with the new offsets, and checked as every tracked frame
        fit = self._fit_lines_pose(res.pose, lines, used)
        if isinstance(fit, str):
            return f"re-anchor: {fit}"
        pose, r, _, J, J2 = fit
        why = self._check(pose, r, J, J2, used)
        if isinstance(why, str):
            return f"re-anchor: {why}"
        res.rms_px, std = why
        res.pose, res.std_dof = pose, np.hypot(std, self._anchor_std)
        res.edges_used, res.lines_seen = used, int(used.sum())
        res.lines_ideal = np.where(used[:, None], lines, np.nan)
        res.anchor = "re-anchored"
        timings["anchor"] = (time.perf_counter() - t) * 1e3
        return res

    def _start_anchor(self, img: np.ndarray, res: TrackResult) -> None:
        """A deferred re-anchor of this tracked frame (docs/tracking.md): the band fit started
        (in the background thread, or here), its result applied ``anchor_lag`` frames on."""
        self._anchor_t_mm, self._anchor_frame = res.pose.t_mm.copy(), res.frame
        self._attempts += 1
        lines, used = self._anchor_lines(res)
        lines, used = lines.copy(), used.copy()
        fut = self._submit(band_fit, img, *self._band_args(res.pose, used))
        at = res.frame + self.tp.anchor_lag
        self._pending = DeferredAnchor(at, fut, res.frame, res.pose, res.std_dof.copy(),
                                        lines, used)
        res.anchor = "; ".join(filter(None, [res.anchor,
                                             "re-anchor started (applied "
                                             f"{self._due(at, res.frame)})"]))

    def _submit(self, fn, img: np.ndarray, *args) -> Future:
        """``fn(img, *args)`` (:func:`band_fit` or :func:`full_measurement`) on the
        ``anchor_worker``: its future."""
        if self.anchor_worker == "process":
            if self._executor is not None and self._executor.shape != img.shape:
                self.close()     # frames of another size than the camera's (a test's crop)
            if self._executor is None:
                self._executor = AnchorProcess(img.shape, self.camera, self.holder,
                                               self.params)
            return self._executor.submit(fn, img, *args)
        if self.anchor_worker == "thread":
            if self._executor is None:
                self._executor = ThreadPoolExecutor(1, thread_name_prefix="cutterpose-anchor")
            # the caller may reuse its frame buffer (a camera driver's): the thread reads a copy
            return self._executor.submit(fn, np.array(img, copy=True), *args)
        fut = Future()
        try:
            fut.set_result(fn(img, *args))
        except CutterposeError as e:
            fut.set_exception(e)
        return fut

    def _take_anchor(self, k: int, timings: dict) -> tuple[str, str]:
        """Take up the deferred re-anchor due on frame ``k`` (waiting for its band fit):
        ``(reason for a full measurement or "", note for this frame)``."""
        if self._pending is None or k < self._pending.at:
            return "", ""
        p, self._pending = self._pending, None
        fut, j, pose, std, lines, used = p.future, p.frame, p.pose, p.std, p.lines, p.used
        t = time.perf_counter()
        try:
            est, q, fit_ms = fut.result()
        except CutterposeError as e:
            return f"re-anchor ({self._name(j)}): {type(e).__name__}: {e}", ""
        except BrokenProcessPool as e:   # the worker died: a new one at the next re-anchor
            self.close()
            return (f"re-anchor ({self._name(j)}): the band fit's worker process failed "
                    f"({e})", "")
        finally:
            timings["anchor_wait"] = (time.perf_counter() - t) * 1e3
        timings["anchor_fit"] = fit_ms
        why, note = self._apply_band(est, q, j, pose, std, lines, used)
        name = self._name(j)
        if why:
            return why.replace("re-anchor:", f"re-anchor ({name}):", 1), ""
        return "", note.replace("re-anchor", f"re-anchor ({name})", 1) \
            if note != "re-anchored" else f"re-anchored ({name})"
