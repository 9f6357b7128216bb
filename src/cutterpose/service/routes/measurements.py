"""``/v1/measurements``: measure an image (stored before it is answered), read the record, the
stored image and its overlay.

A measurement request is checked in this order, and the first failure answers: bearer token
(401: nothing is read, measured or stored), content type (415), room in the queue (503 with
``Retry-After``, before the body is read), size while the body streams in
(413 as soon as it passes the limit, so a 200 MB body is never held), empty body (400),
parameters and flange pose (422), the image's format and truncation (422), the client's request
id (an earlier answer is replayed, 409 if the request differs); then the image is queued for a
worker (503 with ``Retry-After`` when the queue is full), measured within the deadline (504),
and the answer stored (SQLite, committed) before it is sent.
"""

from __future__ import annotations

import asyncio
import base64
import binascii
import hashlib
import json
import sqlite3
import time
import uuid
from datetime import UTC, datetime
from typing import Annotated

from fastapi import APIRouter, Query, Request
from fastapi.responses import FileResponse, JSONResponse, Response
from pydantic import ValidationError

from ..bodies import (
    OPENAPI_BODY,
    check_body,
    check_holder,
    content_type,
    image_params,
    queue_full,
    read_body,
    shutting_down,
)
from ..config import Cell
from ..deps import AUTH, CellDep, MeasurementId, MetricsDep, PoolDep, StoreDep
from ..http_errors import ApiError, finite, responses
from ..jobs import FORMATS, MEDIA_TYPES, measure_job, overlay_job
from ..models import MeasureJSON, MeasurementList, MeasurementRecord, MeasureQuery
from ..store import Store, StoreError
from ..workers import (
    DeadlineExceededError,
    JobError,
    PoolClosedError,
    QueueFullError,
    WorkerCrashedError,
    WorkerPool,
)

__all__ = ["router"]

router = APIRouter(prefix="/v1/measurements", tags=["measurements"], dependencies=AUTH)


def _utc_now() -> str:
    return datetime.now(UTC).isoformat(timespec="microseconds")


def _admit(pool: WorkerPool, deadline_s: float) -> None:
    try:
        pool.admit(deadline_s)
    except QueueFullError as e:
        raise queue_full(e) from None
    except PoolClosedError as e:
        raise shutting_down(e) from None


def _from_json(body: bytes, q: MeasureQuery):
    """(data, format, width, height, flange pose, request id, holder) of a JSON body."""
    if any(v is not None for v in q.model_dump().values()):
        raise ApiError(422, "validation_error", "with a JSON body, give every "
                       "parameter in the body, not in the query string")
    try:
        obj = json.loads(body)
    except (json.JSONDecodeError, UnicodeDecodeError) as e:
        raise ApiError(400, "bad_json", f"body is not valid JSON ({e})") from None
    try:
        j = MeasureJSON.model_validate(obj)
    except ValidationError as e:
        errs = [{"loc": list(x["loc"]), "msg": x["msg"], "type": x["type"]}
                for x in e.errors()]
        where = ".".join(str(p) for p in errs[0]["loc"]) or "body"
        raise ApiError(422, "validation_error", f"{where}: {errs[0]['msg']}",
                       detail=errs) from None
    try:
        data = base64.b64decode(j.image_base64, validate=True)
    except (binascii.Error, ValueError):
        raise ApiError(422, "validation_error", "image_base64 is not valid base64") from None
    if not data:
        raise ApiError(400, "empty_body", "image_base64 is empty")
    return data, j.format, j.width, j.height, j.flange_pose, j.request_id, j.holder


async def _input(request: Request, q: MeasureQuery, cell: Cell, store: Store,
                 pool: WorkerPool):
    """(data, format, (w, h) or None, flange row or None, request id, holder)."""
    settings = cell.service
    ctype = content_type(request)
    if ctype != "application/json" and ctype not in FORMATS:
        raise ApiError(415, "unsupported_media_type",
                       f"content type {ctype or '(none)'!r} not accepted: send image/png, "
                       "image/tiff, image/jpeg, application/octet-stream (raw 8-bit, with "
                       "width and height) or application/json")
    # busy: refuse before the body is read (a client sending "Expect: 100-continue", as
    # curl does for large bodies, then never uploads it), unless this is a repeat of an
    # answered request, which the store answers without a worker
    if q.request_id is None or await asyncio.to_thread(store.row, q.request_id) is None:
        _admit(pool, settings.deadline_s)
    body = await read_body(request, settings)
    if ctype == "application/json":
        data, fmt, w, h, pose, rid, holder = _from_json(body, q)
    else:
        data, fmt = body, FORMATS[ctype]
        w, h, pose, rid, holder = q.width, q.height, q.flange_pose, q.request_id, q.holder
    check_holder(cell, holder)
    row = image_params(fmt, w, h, pose)
    check_body(data, fmt)
    return data, fmt, (w, h) if fmt == "raw" else None, row, rid, holder or \
        cell.default_holder


@router.post("", response_model=MeasurementRecord,
             responses=responses(400, 401, 408, 409, 413, 415, 422, 500, 503, 504),
             openapi_extra=OPENAPI_BODY)
async def post_measurement(request: Request, q: Annotated[MeasureQuery, Query()],
                           cell: CellDep, store: StoreDep, pool: PoolDep, metrics: MetricsDep):
    """Measure the holder's pose in one image; the answer is stored before it is sent."""
    data, fmt, size, row, rid, holder = await _input(request, q, cell, store, pool)
    t0 = time.perf_counter()
    sha = hashlib.sha256(data).hexdigest()
    flange_text = json.dumps(row) if row is not None else None
    inflight: dict = request.app.state.inflight
    mine = None
    try:
        while rid is not None:
            prev = await asyncio.to_thread(store.row, rid)
            if prev is not None:
                if (prev["image_sha256"], prev["flange_pose"], prev["holder"]) != (
                        sha, flange_text, holder):
                    raise ApiError(409, "conflict", f"request_id {rid!r} was used for a "
                                   "different image, flange pose or holder")
                rec = await asyncio.to_thread(store.by_request_id, rid)
                return JSONResponse(rec, headers={"Idempotent-Replay": "true"})
            other = inflight.get(rid)
            if other is None:
                mine = inflight[rid] = asyncio.get_running_loop().create_future()
                break
            await asyncio.shield(other)  # the same request is being measured: wait for it
        record, row_cols = await _measure(cell, pool, data, fmt, size, holder, row, rid, sha,
                                          flange_text, t0)
        stored = await _store(cell, store, record, row_cols, data, fmt)
        metrics.measurements.labels(str(record["ok"]).lower()).inc()
        metrics.measure_s.observe((record["timings_ms"]["decode_ms"]
                                   + record["timings_ms"]["measure_ms"]) / 1e3)
        return JSONResponse(stored)
    finally:
        if mine is not None:
            inflight.pop(rid, None)
            mine.set_result(None)


async def _store(cell: Cell, store: Store, record: dict, row_cols: dict, data: bytes,
                 fmt: str) -> dict:
    keep = data if cell.service.image_cap_bytes > 0 else None
    try:
        return await asyncio.to_thread(store.insert, record, row_cols, keep, MEDIA_TYPES[fmt][1])
    except StoreError as e:
        if not e.transient:
            raise ApiError(500, "store_failed", f"the measurement could not be recorded ({e}); "
                           "nothing was answered") from None
        raise ApiError(503, "storage_unavailable", f"the measurement was not recorded: {e}; "
                       "nothing was stored, retry once the data directory can be written",
                       headers={"Retry-After": "30"}) from None
    except (sqlite3.Error, OSError) as e:
        raise ApiError(500, "store_failed", f"the measurement could not be recorded "
                       f"({type(e).__name__}: {e}); nothing was answered") from None


async def _run(pool: WorkerPool, deadline_s: float, *args):
    """The worker's answer to ``measure_job(*args)``, its failures as :class:`ApiError`."""
    try:
        fut = pool.submit(measure_job, *args, deadline_s=deadline_s)
    except QueueFullError as e:
        raise queue_full(e) from None
    except PoolClosedError as e:
        raise shutting_down(e) from None
    try:
        return await asyncio.wait_for(asyncio.wrap_future(fut), deadline_s + 5.0)
    except (TimeoutError, DeadlineExceededError) as e:
        raise ApiError(504, "deadline_exceeded", str(e) or "no answer within "
                       f"{deadline_s} s") from None
    except WorkerCrashedError as e:
        raise ApiError(500, "worker_crashed", str(e)) from None
    except PoolClosedError as e:
        raise shutting_down(e) from None
    except JobError as e:
        if e.internal:
            raise ApiError(500, "internal_error", f"measurement failed: {e}") from None
        code = "image_unusable" if e.kind == "ImageError" else "bad_input"
        raise ApiError(422, code, str(e)) from None


async def _measure(cell, pool, data, fmt, size, holder, row, rid, sha, flange_text, t0):
    res = await _run(pool, cell.service.deadline_s, data, fmt, size, holder, row)
    total_ms = (time.perf_counter() - t0) * 1e3
    w = res["worker"]
    meas, robot = finite(res["measurement"]), finite(res["robot"])
    q_ok = bool(meas["quality"]["ok"])
    if robot.get("available"):
        grasp_ok = (robot.get("grasp") or {}).get("verdict") == "grasp"
        ok, basis = q_ok and grasp_ok, "grasp_check"
    else:
        ok, basis = q_ok, "camera_quality"
    mid = uuid.uuid4().hex
    created = _utc_now()
    record = {
        "id": mid, "request_id": rid, "created_at": created, "cell": cell.name,
        "holder": holder, "flange_pose": row, "ok": ok,
        "verdict": "grasp" if ok else "retake", "verdict_basis": basis,
        "measurement": meas, "robot": robot,
        "image": {"sha256": sha, "bytes": len(data), "format": fmt, **res["image"]},
        "timings_ms": {"queue_ms": round(max(total_ms - w["decode_ms"] - w["measure_ms"],
                                             0.0), 3),
                       "decode_ms": w["decode_ms"], "measure_ms": w["measure_ms"],
                       "total_ms": round(total_ms, 3)}}
    cols = {"id": mid, "request_id": rid, "created_at": created, "image_sha256": sha,
            "image_bytes": len(data), "image_format": fmt,
            "width_px": res["image"]["width_px"], "height_px": res["image"]["height_px"],
            "holder": holder, "flange_pose": flange_text, "ok": int(ok),
            "verdict": record["verdict"], "method": meas.get("method"),
            "total_ms": total_ms}
    return record, cols


@router.get("/{measurement_id}", response_model=MeasurementRecord,
            responses=responses(401, 404, 422))
async def get_measurement(measurement_id: MeasurementId, store: StoreDep):
    """One stored measurement, exactly as it was answered."""
    rec = await asyncio.to_thread(store.get, measurement_id)
    if rec is None:
        raise ApiError(404, "not_found", f"no measurement {measurement_id}")
    return JSONResponse(rec)


@router.get("", response_model=MeasurementList, responses=responses(401, 422))
async def list_measurements(
        store: StoreDep,
        since: Annotated[datetime | None, Query(description="ISO 8601 time (UTC when no "
                                                "zone is given); inclusive.")] = None,
        limit: Annotated[int, Query(ge=1, le=1000, description="At most this many.")] = 100):
    """Stored measurements from ``since`` on, oldest first."""
    if since is None:
        since_text = ""
    else:
        try:
            s = since if since.tzinfo else since.replace(tzinfo=UTC)
            since_text = s.astimezone(UTC).isoformat(timespec="microseconds")
        except (OverflowError, ValueError) as e:
            raise ApiError(422, "validation_error", f"since: {e}") from None
    recs = await asyncio.to_thread(store.since, since_text, limit)
    return JSONResponse({"measurements": recs,
                         "next_since": recs[-1]["created_at"] if recs else None})


@router.get("/{measurement_id}/image",
            responses={200: {"content": {t: {} for t, _ in MEDIA_TYPES.values()},
                             "description": "The image as received."},
                       **responses(401, 404, 422)},
            response_class=Response)
async def get_image(measurement_id: MeasurementId, store: StoreDep):
    """The stored image (404 ``image_not_kept`` once evicted by the folder's size cap)."""
    found = await asyncio.to_thread(store.image, measurement_id)
    if found is None:
        await _not_kept(store, measurement_id)
    path, fmt, _, _ = found
    return FileResponse(path, media_type=MEDIA_TYPES[fmt][0])


async def _not_kept(store: Store, measurement_id: str):
    if await asyncio.to_thread(store.get, measurement_id) is None:
        raise ApiError(404, "not_found", f"no measurement {measurement_id}")
    raise ApiError(404, "image_not_kept", f"the image of {measurement_id} is no longer "
                   "kept (image folder size cap)")


@router.get("/{measurement_id}/overlay.png",
            responses={200: {"content": {"image/png": {}}, "description": "Overlay picture."},
                       **responses(401, 404, 422, 503, 504)},
            response_class=Response)
async def get_overlay(measurement_id: MeasurementId, cell: CellDep, store: StoreDep,
                      pool: PoolDep):
    """What was detected and what the pose predicts, drawn on the stored image."""
    found = await asyncio.to_thread(store.image, measurement_id)
    if found is None:
        await _not_kept(store, measurement_id)
    path, fmt, size, holder = found
    try:
        fut = pool.submit(overlay_job, str(path), fmt, size, holder,
                          deadline_s=cell.service.deadline_s)
    except QueueFullError as e:
        raise queue_full(e) from None
    try:
        png = await asyncio.wrap_future(fut)
    except DeadlineExceededError as e:
        raise ApiError(504, "deadline_exceeded", str(e)) from None
    except WorkerCrashedError as e:
        raise ApiError(500, "worker_crashed", str(e)) from None
    except JobError as e:
        raise ApiError(422 if not e.internal else 500,
                       "image_unusable" if not e.internal else "internal_error",
                       str(e)) from None
    return Response(png, media_type="image/png")
