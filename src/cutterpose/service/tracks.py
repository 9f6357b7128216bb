"""Tracking sessions of the service: one :class:`cutterpose.tracking.Tracker` per approach.

A robot that approaches the holder sends the camera's frames one after the other; the tracker
answers each from the previous poses in ~15 ms (:mod:`cutterpose.tracking`). The full
measurements (first frame, fall-backs) use the approach's working range and error budget
(:func:`cutterpose.tracking.approach_limits`) with the cell file's edge break and shape. A
tracker has state (the last poses, the edges' offsets from the design edge, a deferred
re-anchor), so a session lives in the service process itself, not in the measurement workers
(which are stateless and interchangeable): frames of one session are answered in the order
they arrive, one at a time, in a thread beside the event loop. Sessions idle for longer than
``track_idle_s`` are closed, and at most ``max_tracks`` exist at once.

Tracked frames are answered, not stored: the record of the grasp is the measurement at the
stop (``POST /v1/measurements``).

Convention:
    Poses, flange pose rows and frames as in :mod:`.models` and :mod:`.robot_frame`.
"""

from __future__ import annotations

import asyncio
import threading
import time
import uuid
from dataclasses import dataclass, field
from datetime import UTC, datetime
from types import SimpleNamespace

from .config import Cell

__all__ = ["TrackSession", "TrackSessions", "TooManyTracksError"]


class TooManyTracksError(Exception):
    """``max_tracks`` sessions are open and none is idle."""


@dataclass
class TrackSession:
    """One approach: its tracker and what the API reports of it."""

    id: str
    holder: str
    tracker: object
    created_at: str
    last_used: float = field(default_factory=time.monotonic)
    frames: int = 0
    last_mode: str | None = None
    #: frames of one session one at a time, in arrival order (asyncio.Lock is FIFO)
    lock: asyncio.Lock = field(default_factory=asyncio.Lock)

    def info(self, idle_s: float) -> dict:
        return {"id": self.id, "created_at": self.created_at, "holder": self.holder,
                "method": self.tracker.method, "frames": self.frames,
                "last_mode": self.last_mode, "idle_timeout_s": idle_s,
                "filter": self.tracker.filter is not None,
                "anchor_lag": self.tracker.tp.anchor_lag}


class TrackSessions:
    """The open sessions of one service process.

    Parameters
    ----------
    cell : the cell (camera, holders, method, edge look).
    max_tracks : sessions open at once.
    idle_s : a session unused for this long is closed (its next frame gets 404).
    """

    def __init__(self, cell: Cell, max_tracks: int, idle_s: float):
        self.cell, self.max_tracks, self.idle_s = cell, max_tracks, idle_s
        self._sessions: dict[str, TrackSession] = {}
        self._guard = threading.Lock()

    def __len__(self) -> int:
        return len(self._sessions)

    def create(self, holder: str | None, filter: bool, anchor_lag: int | None
               ) -> TrackSession:
        """A new session (the tracker's first frame is measured in full).

        Raises
        ------
        TooManyTracksError
            ``max_tracks`` sessions are open and none has been idle for ``idle_s``.
        """
        from dataclasses import replace

        from ..tracking import Tracker, TrackParams, approach_limits, approach_params

        self.expire()
        name = holder or self.cell.default_holder
        tp = TrackParams() if anchor_lag is None else replace(TrackParams(),
                                                               anchor_lag=anchor_lag)
        with self._guard:
            if len(self._sessions) >= self.max_tracks:
                raise TooManyTracksError(f"{len(self._sessions)} tracking sessions are open "
                                         f"(service.max_tracks = {self.max_tracks}): close one "
                                         "(DELETE /v1/tracks/{id}) or wait "
                                         f"{self.idle_s:g} s for an idle one to expire")
            # the cell's station on an approach: the approach's image parameters, range and
            # budget; what the cell file says of the edge
            limits = replace(approach_limits(), edge_break_mm=self.cell.limits.edge_break_mm,
                             edge_shape=self.cell.limits.edge_shape)
            station = replace(self.cell.station, holder=self.cell.holder(name),
                              params=approach_params(self.cell.camera), limits=limits)
            tracker = Tracker.from_station(station, track=tp, filter=filter)
            s = TrackSession(uuid.uuid4().hex, name, tracker,
                             datetime.now(UTC).isoformat(timespec="microseconds"))
            self._sessions[s.id] = s
        return s

    def get(self, track_id: str) -> TrackSession | None:
        self.expire()
        return self._sessions.get(track_id)

    def close(self, track_id: str) -> bool:
        with self._guard:
            s = self._sessions.pop(track_id, None)
        if s is not None:
            s.tracker.close()
        return s is not None

    def close_all(self) -> None:
        for k in list(self._sessions):
            self.close(k)

    def expire(self) -> None:
        """Close the sessions idle for longer than ``idle_s`` (none while a frame of theirs is
        being tracked)."""
        now = time.monotonic()
        for k, s in list(self._sessions.items()):
            if now - s.last_used > self.idle_s and not s.lock.locked():
                self.close(k)


def track_frame(session: TrackSession, cell: Cell, img, flange_row,
                t_s: float | None = None, frame_id: int | None = None) -> dict:
    """One frame through the session's tracker (blocking: run it in a thread), with the base
    frame when the request has a flange pose and the cell a hand-eye file; ``t_s`` the
    frame's time and ``frame_id`` the camera's frame number
    (:meth:`~cutterpose.tracking.Tracker.update`).

    Returns
    -------
    dict : ``TrackResult.to_dict()`` and ``robot`` (:func:`.robot_frame.robot_frame`).
    """
    from .robot_frame import robot_frame

    r = session.tracker.update(img, t_s=t_s, frame_id=frame_id)
    session.frames += 1
    session.last_mode = r.mode
    # the full measurement carries its error budget's covariance; a tracked frame its std
    m = r.measurement if r.mode == "full" else SimpleNamespace(
        pose=r.pose, std_dof=r.std_dof, ok=r.ok, covariance_cam=None,
        quality=SimpleNamespace(reason=r.fallback_reason if not r.ok else ""))
    hol = cell.holder(session.holder)
    out = r.to_dict()
    out["robot"] = robot_frame(m, cell, hol, flange_row)
    return out
