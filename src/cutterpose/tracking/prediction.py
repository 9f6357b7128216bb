"""Prediction: where the holder is on the next frame, and the frames' times and numbers.

Constant velocity on SE(3): with ``T_k = (R_k, t_k)`` the pose of the holder in the camera
frame at frame ``k``, the camera's motion over one frame is ``D = T_k T_{k-1}^{-1}`` (its body
velocity, in the camera frame); the prediction is ``T_pred = D T_k``; without two consecutive
tracked poses, ``T_pred = T_k``. With frame times (``update(image, t_s=)``) the motion is per
second and carried over skipped frames on its twist (:mod:`cutterpose.geometry.se3`).
"""

from __future__ import annotations

import math
import operator

from ..errors import InputError
from ..geometry.pose import Pose
from ..geometry.se3 import compose, relative, se3_exp, se3_log

__all__ = ["Prediction"]


class Prediction:
    """The prediction of :class:`~cutterpose.tracking.Tracker` (module doc). State: the last
    pose ``_last`` on frame ``_last_k``, the motion per unit of time ``_vel`` (None: not
    known), the frame times ``_frame_t`` (``_timed``) and camera numbers ``_frame_ids``
    (``_named``), the update count ``_n``."""

    def _stamp(self, k: int, t_s: float | None, frame_id: int | None = None) -> None:
        """Keep frame ``k``'s time (its index without timestamps) and camera frame number,
        both checked before either is kept: given for every frame or none, increasing."""
        if frame_id is not None:
            try:
                frame_id = operator.index(frame_id)
            except TypeError:
                raise InputError(f"frame_id must be an integer, got {frame_id!r}") from None
        t = None if t_s is None else float(t_s)
        checks = (("frame_id", frame_id, "_named", self._frame_ids, 0),
                  ("t_s", t, "_timed", self._frame_t, -math.inf))
        for name, value, flag, store, low in checks:
            given = value is not None
            if k > 0 and given != getattr(self, flag):
                raise InputError(f"give {name} for every frame of a track or for none (frame "
                                 f"{k}: {'given' if given else 'missing'})")
            prev = store.get(k - 1)
            if given and not (math.isfinite(value) and value >= low
                              and (prev is None or value > prev)):
                floor = f", >= {low}" if low > -math.inf else ""
                raise InputError(f"{name} must be finite{floor} and increase: frame {k} has "
                                 f"{value} after {prev}")
        for _, value, flag, store, _ in checks:
            setattr(self, flag, value is not None)
            if value is not None:
                store[k] = value
        self._prune_times(k)

    def _prune_times(self, k: int) -> None:
        """Keep the times of the frames something refers to (this and the previous frame,
        the last pose's, the filter's, the deferred jobs'), however far back they lie (a
        holder out of sight for minutes while a fall-back is pending); forget the rest."""
        keep = {k, k - 1, self._last_k, self._filter_k}
        if self._pending is not None:
            keep.add(self._pending.frame)
        if self._pending_full is not None:
            keep |= {self._pending_full.frame, self._pending_full.last_k}
        keep.discard(None)
        if len(self._frame_t) > len(keep):
            self._frame_t = {x: t for x, t in self._frame_t.items() if x in keep}
        if len(self._frame_ids) > len(keep):
            self._frame_ids = {x: i for x, i in self._frame_ids.items() if x in keep}

    def _name(self, j: int) -> str:
        """Frame ``j`` (update count) as the messages name it: by the camera's number when
        the frames have them."""
        return f"frame {self._frame_ids.get(j, j)}" if self._named else f"frame {j}"

    def _due(self, at: int, k: int) -> str:
        """When a job due on update ``at`` is taken up, seen from update ``k``: the frame
        (update count), or with camera numbers, whose future ones are not known, how many
        frames on."""
        return f"{at - k} frames later" if self._named else f"at frame {at}"

    def _time(self, k: int) -> float:
        """Frame ``k``'s time: its timestamp (s) or, without timestamps, its index."""
        return self._frame_t[k] if self._timed else float(k)

    def _motion(self, a: Pose, ka: int, b: Pose, kb: int) -> tuple | None:
        """The motion per unit of time (a frame, or a second with timestamps) from pose
        ``b`` on frame ``kb`` to pose ``a`` on frame ``ka``: the same twist in each unit."""
        gap = self._time(ka) - self._time(kb)
        if not gap > 0:
            return None
        R, t = relative(a, b)
        return (R, t) if gap == 1.0 else se3_exp(se3_log(R, t) / gap)

    def _moved_to(self, pose: Pose, k: int) -> None:
        """``pose`` on frame ``k`` is the last one; the motion since the one before (over a
        gap of frames without a pose: the same twist in each unit of time)."""
        if self._last is not None and k > self._last_k:
            self._vel = self._motion(pose, k, self._last, self._last_k)
        self._last, self._last_k = pose, k
        self._after_full = False

    def predict(self, t_s: float | None = None) -> Pose | None:
        """The pose predicted for the next frame, or (a track with timestamps) at time
        ``t_s``: the last pose moved on by the last motion, when that is known."""
        if self._timed != (t_s is not None):
            raise InputError("predict: give t_s exactly when the frames have timestamps")
        if self._last is None:
            return None
        dt = (float(t_s) if self._timed else float(self._n)) - self._time(self._last_k)
        return self._carried(dt)

    def _predict(self, k: int) -> Pose | None:
        """The pose predicted for frame ``k`` (already stamped)."""
        return self._carried(self._time(k) - self._time(self._last_k))

    def _carried(self, dt: float) -> Pose:
        """The last pose moved on by the last motion over ``dt`` units of time (whole frames
        one step at a time, as the motion was measured; else on the twist)."""
        pose = self._last
        if self._vel is None or not dt > 0:
            return pose
        if float(dt).is_integer() and dt <= 64:
            for _ in range(int(dt)):
                pose = compose(*self._vel, pose)
            return pose
        R, t = se3_exp(se3_log(*self._vel) * dt)
        return compose(R, t, pose)
