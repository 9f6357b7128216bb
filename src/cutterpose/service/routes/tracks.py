"""``/v1/tracks``: tracking sessions of one approach (:mod:`..tracks`): open, read, close, and
the next frame of a session (answered, not stored)."""

from __future__ import annotations

import asyncio
import math
import time
from typing import Annotated

from fastapi import APIRouter, Query, Request
from fastapi.responses import JSONResponse, Response

from ...errors import CutterposeError, ImageError
from ..bodies import OPENAPI_BODY, check_body, check_holder, content_type, image_params, read_body
from ..config import ServiceSettings
from ..deps import AUTH, CellDep, TrackId, TracksDep
from ..http_errors import ApiError, finite, responses
from ..jobs import FORMATS, decode_image
from ..models import TrackCreate, TrackFrameOut, TrackFrameQuery, TrackInfo
from ..tracks import TooManyTracksError, TrackSessions, track_frame

__all__ = ["router"]

router = APIRouter(prefix="/v1/tracks", tags=["tracking"], dependencies=AUTH)

_FRAME_BODY = {"requestBody": {
    **OPENAPI_BODY["requestBody"],
    "content": {k: v for k, v in OPENAPI_BODY["requestBody"]["content"].items()
                if k != "application/json"}}}


def _session(tracks: TrackSessions, track_id: str, settings: ServiceSettings):
    s = tracks.get(track_id)
    if s is None:
        raise ApiError(404, "not_found", f"no tracking session {track_id} (closed, or idle "
                       f"for more than {settings.track_idle_s:g} s)")
    return s


@router.post("", response_model=TrackInfo, status_code=201,
             responses=responses(401, 422, 429))
async def create_track(body: TrackCreate, tracks: TracksDep, cell: CellDep):
    """Open a tracking session for one approach: send its frames in order to
    ``/v1/tracks/{id}/frames``; the first is measured in full."""
    check_holder(cell, body.holder)
    idle_s = cell.service.track_idle_s
    try:
        s = await asyncio.to_thread(tracks.create, body.holder, body.filter, body.anchor_lag)
    except TooManyTracksError as e:
        raise ApiError(429, "too_many_tracks", str(e), headers={
            "Retry-After": str(int(math.ceil(idle_s)))}) from None
    return JSONResponse(s.info(idle_s), status_code=201)


@router.get("/{track_id}", response_model=TrackInfo, responses=responses(401, 404, 422))
async def get_track(track_id: TrackId, tracks: TracksDep, cell: CellDep):
    """A session: frames answered, the last frame's mode."""
    settings = cell.service
    return JSONResponse(_session(tracks, track_id, settings).info(settings.track_idle_s))


@router.delete("/{track_id}", status_code=204, responses=responses(401, 404, 422),
               response_class=Response)
async def delete_track(track_id: TrackId, tracks: TracksDep, cell: CellDep):
    """Close a session (its tracker and the tracker's re-anchor worker, if any)."""
    s = _session(tracks, track_id, cell.service)
    async with s.lock:    # after a frame being tracked
        await asyncio.to_thread(tracks.close, track_id)
    return Response(status_code=204)


@router.post("/{track_id}/frames", response_model=TrackFrameOut,
             responses=responses(400, 401, 404, 408, 413, 415, 422, 500),
             openapi_extra=_FRAME_BODY)
async def post_frame(request: Request, track_id: TrackId,
                     q: Annotated[TrackFrameQuery, Query()], tracks: TracksDep, cell: CellDep):
    """The next frame of the session: its pose from the previous ones (or a full
    measurement, with the reason). Not stored."""
    t0 = time.perf_counter()
    s = _session(tracks, track_id, cell.service)
    ctype = content_type(request)
    if ctype not in FORMATS:
        raise ApiError(415, "unsupported_media_type",
                       f"content type {ctype or '(none)'!r} not accepted for frames: send "
                       "image/png, image/tiff, image/jpeg or application/octet-stream "
                       "(raw 8-bit, with width and height)")
    fmt = FORMATS[ctype]
    row = image_params(fmt, q.width, q.height, q.flange_pose)
    data = await read_body(request, cell.service)
    check_body(data, fmt)
    t1 = time.perf_counter()
    try:
        img = await asyncio.to_thread(decode_image, data, fmt, (q.width, q.height),
                                      tuple(cell.camera.image_size_px))
    except ImageError as e:
        raise ApiError(422, "image_unusable", str(e)) from None
    t2 = time.perf_counter()
    async with s.lock:
        if tracks.get(track_id) is not s:
            raise ApiError(404, "not_found", f"tracking session {track_id} was closed")
        t3 = time.perf_counter()
        try:
            out = await asyncio.to_thread(track_frame, s, cell, img, row, q.t_s, q.frame_id)
        except CutterposeError as e:
            raise ApiError(422, "bad_input", f"{type(e).__name__}: {e}") from None
        finally:
            s.last_used = time.monotonic()
    t4 = time.perf_counter()
    out = finite(out)
    out["track_id"] = s.id
    out["timings_ms"] = out.get("timings_ms", {}) | {
        "decode_ms": round((t2 - t1) * 1e3, 3), "wait_ms": round((t3 - t2) * 1e3, 3),
        "track_ms": round((t4 - t3) * 1e3, 3), "total_ms": round((t4 - t0) * 1e3, 3)}
    return JSONResponse(out)
