"""The HTTP API of ``cutterpose serve`` (FastAPI): measurements in, records out.

A measurement request is checked in this order, and the first failure answers: bearer token
(401: nothing is read, measured or stored), content type (415), room in the queue (503 with
``Retry-After``, before the body is read), size while the body streams in
(413 as soon as it passes the limit, so a 200 MB body is never held), empty body (400),
parameters and flange pose (422), the image's format and truncation (422), the client's request
id (an earlier answer is replayed, 409 if the request differs); then the image is queued for a
worker (503 with ``Retry-After`` when the queue is full), measured within the deadline (504),
and the answer stored (SQLite, committed) before it is sent.

Convention:
    Units and frames as in :mod:`.models`; every error is an :class:`.models.ErrorBody`.
"""


import asyncio
import base64
import binascii
import hashlib
import hmac
import json
import math
import sqlite3
import time
import uuid
from contextlib import asynccontextmanager
from datetime import UTC, datetime
from typing import Annotated

from fastapi import Depends, FastAPI, Path, Query, Request
from fastapi.exceptions import RequestValidationError
from fastapi.responses import FileResponse, JSONResponse, Response
from fastapi.security import HTTPAuthorizationCredentials, HTTPBearer
from pydantic import ValidationError
from starlette.exceptions import HTTPException as StarletteHTTPException

from ..errors import CutterposeError, ImageError
from .config import Cell
from .jobs import (
    FORMATS,
    MEDIA_TYPES,
    check_encoded,
    decode_image,
    init_worker,
    measure_job,
    overlay_job,
)
from .metrics import CONTENT_TYPE_LATEST, Metrics, MetricsMiddleware
from .models import (
    ErrorBody,
    Health,
    MeasureJSON,
    MeasurementList,
    MeasurementRecord,
    MeasureQuery,
    Ready,
    TrackCreate,
    TrackFrameOut,
    TrackFrameQuery,
    TrackInfo,
    parse_flange_pose,
)
from .store import Store
from .tracks import TooManyTracksError, TrackSessions, track_frame
from .workers import (
    DeadlineExceededError,
    JobError,
    PoolClosedError,
    QueueFullError,
    WorkerCrashedError,
    WorkerPool,
)

__all__ = ["create_app", "ApiError"]

ID_PATTERN = r"^[0-9a-f]{32}$"
_ERRORS = {400: "Malformed request", 401: "Missing or wrong bearer token",
           404: "Not found", 409: "Request id reused for a different request",
           413: "Body larger than the limit", 415: "Unsupported content type",
           422: "Invalid parameters or unusable image",
           429: "Too many tracking sessions open (retry after Retry-After seconds)",
           500: "Service fault",
           503: "Busy (retry after Retry-After seconds) or not ready", 504: "Deadline exceeded"}


def _responses(*codes) -> dict:
    return {c: {"model": ErrorBody, "description": _ERRORS[c]} for c in codes}


class ApiError(Exception):
    """An HTTP error with a typed body (:class:`.models.ErrorBody`)."""

    def __init__(self, status: int, error: str, message: str, headers: dict | None = None,
                 detail: list | None = None):
        super().__init__(message)
        self.status, self.error, self.message = status, error, message
        self.headers, self.detail = headers, detail


def _error_response(status: int, error: str, message: str, headers=None, detail=None):
    body = {"error": error, "message": message}
    if detail is not None:
        body["detail"] = detail
    return JSONResponse(body, status_code=status, headers=headers)


def _finite(x):
    """JSON-safe copy: NaN / inf become null (the record is stored with allow_nan=False)."""
    if isinstance(x, float):
        return x if math.isfinite(x) else None
    if isinstance(x, dict):
        return {k: _finite(v) for k, v in x.items()}
    if isinstance(x, (list, tuple)):
        return [_finite(v) for v in x]
    return x


def _utc_now() -> str:
    return datetime.now(UTC).isoformat(timespec="microseconds")


_OPENAPI_BODY = {
    "requestBody": {
        "required": True,
        "description": "The image: a PNG, TIFF or JPEG file as the body (its content type), "
                       "raw 8-bit grey pixels (application/octet-stream with the width and "
                       "height parameters), or a JSON object with the image in base64. The "
                       "image must have the cell camera's size.",
        "content": {
            "image/png": {"schema": {"type": "string", "format": "binary"}},
            "image/tiff": {"schema": {"type": "string", "format": "binary"}},
            "image/jpeg": {"schema": {"type": "string", "format": "binary"}},
            "application/octet-stream": {"schema": {"type": "string", "format": "binary"}},
            "application/json": {"schema": MeasureJSON.model_json_schema()},
        },
    }
}


def create_app(cell: Cell, pool: WorkerPool | None = None) -> FastAPI:
    """The application for a loaded cell. The worker pool and the store start with the
    application's lifespan (``pool``: a ready-made pool, for tests)."""
    settings = cell.service
    token = cell.token.encode()
    bearer = HTTPBearer(auto_error=False, description="The cell's token (CUTTERPOSE_TOKEN or "
                        "service.token_file of the cell file).")

    @asynccontextmanager
    async def lifespan(app: FastAPI):
        store = Store(settings.data_dir, settings.image_cap_bytes)
        p = pool or WorkerPool(settings.workers, settings.queue_size, init_worker,
                               (cell.for_worker(),), preload=("cutterpose.service.jobs",))
        p.start()
        app.state.store, app.state.pool = store, p
        app.state.metrics = Metrics(p, store)
        app.state.inflight = {}
        app.state.tracks = TrackSessions(cell, settings.max_tracks, settings.track_idle_s)
        try:
            yield
        finally:
            await asyncio.to_thread(app.state.tracks.close_all)
            await asyncio.to_thread(p.close)
            store.close()

    app = FastAPI(
        title="cutterpose measurement service",
        version="1",
        summary="6-DOF pose of a disc cutter holder from one camera image, for the robot cell.",
        description="Poses in mm and degrees, frames as in PROTOCOL.md: `T_cam_holder` from the "
                    "image, `T_base_holder` with a flange pose and a hand-eye file. Every "
                    "error is a JSON object `{error, message}`. See docs/service.md.",
        lifespan=lifespan)
    app.add_middleware(MetricsMiddleware,
                       metrics_getter=lambda: getattr(app.state, "metrics", None))

    # -- errors --------------------------------------------------------------------------
    def refuse(reason: str) -> None:
        m = getattr(app.state, "metrics", None)
        if m is not None:
            m.refuse(reason)

    @app.exception_handler(ApiError)
    async def _api_error(request: Request, e: ApiError):
        refuse(e.error)
        return _error_response(e.status, e.error, e.message, e.headers, e.detail)

    @app.exception_handler(RequestValidationError)
    async def _validation_error(request: Request, e: RequestValidationError):
        refuse("validation_error")
        errs = [{"loc": list(x.get("loc", ())), "msg": x.get("msg", ""),
                 "type": x.get("type", "")} for x in e.errors()]
        first = errs[0] if errs else {"loc": [], "msg": "invalid request"}
        where = ".".join(str(p) for p in first["loc"])
        return _error_response(422, "validation_error", f"{where}: {first['msg']}",
                               detail=errs)

    @app.exception_handler(StarletteHTTPException)
    async def _http_error(request: Request, e: StarletteHTTPException):
        code = {404: "not_found", 405: "method_not_allowed"}.get(e.status_code, "http_error")
        return _error_response(e.status_code, code, str(e.detail),
                               getattr(e, "headers", None))

    @app.exception_handler(Exception)
    async def _internal(request: Request, e: Exception):
        refuse("internal_error")
        return _error_response(500, "internal_error", "internal error (see the service log)")

    # -- dependencies --------------------------------------------------------------------
    def get_store(request: Request) -> Store:
        return request.app.state.store

    def get_pool(request: Request) -> WorkerPool:
        return request.app.state.pool

    def require_token(cred: Annotated[HTTPAuthorizationCredentials | None, Depends(bearer)]
                      ) -> None:
        # constant-time: the comparison's duration does not tell how much of a guess was right
        if cred is None or not hmac.compare_digest(cred.credentials.encode(), token):
            raise ApiError(401, "unauthorized", "missing or wrong bearer token (header "
                           "'Authorization: Bearer <token>')",
                           headers={"WWW-Authenticate": "Bearer"})

    StoreDep = Annotated[Store, Depends(get_store)]
    PoolDep = Annotated[WorkerPool, Depends(get_pool)]
    auth = [Depends(require_token)]
    MeasurementId = Annotated[str, Path(pattern=ID_PATTERN, description="Measurement id.")]

    async def read_body(request: Request) -> bytes:
        limit = settings.max_body_bytes
        too_large = ApiError(413, "too_large", f"body larger than {limit} bytes (service."
                             "max_body_mb of the cell file)")
        cl = request.headers.get("content-length")
        if cl is not None:
            if not cl.isdigit():
                raise ApiError(400, "bad_request", "Content-Length is not a number")
            if int(cl) > limit:
                raise too_large
        buf = bytearray()
        async for chunk in request.stream():  # checked while it streams in
            buf += chunk
            if len(buf) > limit:
                raise too_large
        if not buf:
            raise ApiError(400, "empty_body", "empty body: send the image")
        return bytes(buf)

    def queue_full(e: QueueFullError) -> ApiError:
        return ApiError(503, "queue_full", f"busy: {e}; retry after {e.retry_after_s:.0f} s",
                        headers={"Retry-After": str(int(e.retry_after_s))})

    async def measurement_input(request: Request, q: MeasureQuery, store: Store,
                                pool: WorkerPool):
        """(data, format, (w, h) or None, flange row or None, request id, holder)."""
        ctype = request.headers.get("content-type", "").split(";")[0].strip().lower()
        if ctype != "application/json" and ctype not in FORMATS:
            raise ApiError(415, "unsupported_media_type",
                           f"content type {ctype or '(none)'!r} not accepted: send image/png, "
                           "image/tiff, image/jpeg, application/octet-stream (raw 8-bit, with "
                           "width and height) or application/json")
        # busy: refuse before the body is read (a client sending "Expect: 100-continue", as
        # curl does for large bodies, then never uploads it), unless this is a repeat of an
        # answered request, which the store answers without a worker
        if q.request_id is None or await asyncio.to_thread(store.row, q.request_id) is None:
            try:
                pool.admit(settings.deadline_s)
            except QueueFullError as e:
                raise queue_full(e) from None
            except PoolClosedError as e:
                raise ApiError(503, "shutting_down", str(e), headers={"Retry-After": "5"}
                               ) from None
        body = await read_body(request)
        if ctype == "application/json":
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
                raise ApiError(422, "validation_error", "image_base64 is not valid base64"
                               ) from None
            if not data:
                raise ApiError(400, "empty_body", "image_base64 is empty")
            fmt, w, h, pose, rid, holder = (j.format, j.width, j.height, j.flange_pose,
                                            j.request_id, j.holder)
        else:
            data, fmt = body, FORMATS[ctype]
            w, h, pose, rid, holder = q.width, q.height, q.flange_pose, q.request_id, q.holder
        check_holder(holder)
        row = image_params(fmt, w, h, pose)
        check_body(data, fmt)
        return data, fmt, (w, h) if fmt == "raw" else None, row, rid, holder or \
            cell.default_holder

    def check_holder(holder: str | None) -> None:
        if holder is not None and holder not in cell.holders:
            raise ApiError(422, "validation_error", f"holder {holder!r} is not in the cell "
                           f"file ({', '.join(sorted(cell.holders))})")

    def image_params(fmt: str, w, h, pose):
        """The checks of an image request's parameters (a raw body's size, the flange pose):
        the flange pose row, or None."""
        if fmt == "raw":
            if w is None or h is None:
                raise ApiError(422, "validation_error", "raw 8-bit images need width and "
                               "height")
        elif w is not None or h is not None:
            raise ApiError(422, "validation_error", "width and height are for raw images only "
                           f"(a {fmt.upper()} file has its own)")
        try:
            return parse_flange_pose(pose) if pose is not None else None
        except ValueError as e:
            raise ApiError(422, "bad_flange_pose", str(e)) from None

    def check_body(data: bytes, fmt: str) -> None:
        """An encoded body's format and truncation (before any work is queued)."""
        if fmt != "raw":
            try:
                check_encoded(data, fmt)
            except ImageError as e:
                raise ApiError(422, "image_unusable", str(e)) from None

    # -- measurements --------------------------------------------------------------------
    @app.post("/v1/measurements", response_model=MeasurementRecord, dependencies=auth,
              responses=_responses(400, 401, 409, 413, 415, 422, 500, 503, 504),
              openapi_extra=_OPENAPI_BODY, tags=["measurements"])
    async def post_measurement(request: Request, q: Annotated[MeasureQuery, Query()],
                               store: StoreDep, pool: PoolDep):
        """Measure the holder's pose in one image; the answer is stored before it is sent."""
        data, fmt, size, row, rid, holder = await measurement_input(request, q, store, pool)
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
            record, row_cols = await _measure(pool, data, fmt, size, holder, row, rid, sha,
                                              flange_text, t0)
            try:
                stored = await asyncio.to_thread(
                    store.insert, record, row_cols,
                    data if settings.image_cap_bytes > 0 else None, MEDIA_TYPES[fmt][1])
            except (sqlite3.Error, OSError) as e:
                raise ApiError(500, "store_failed", f"the measurement could not be recorded "
                               f"({type(e).__name__}: {e}); nothing was answered") from None
            m = request.app.state.metrics
            m.measurements.labels(str(record["ok"]).lower()).inc()
            m.measure_s.observe((record["timings_ms"]["decode_ms"]
                                 + record["timings_ms"]["measure_ms"]) / 1e3)
            return JSONResponse(stored)
        finally:
            if mine is not None:
                inflight.pop(rid, None)
                mine.set_result(None)

    async def _measure(pool, data, fmt, size, holder, row, rid, sha, flange_text, t0):
        try:
            fut = pool.submit(measure_job, data, fmt, size, holder, row,
                              deadline_s=settings.deadline_s)
        except QueueFullError as e:
            raise queue_full(e) from None
        except PoolClosedError as e:
            raise ApiError(503, "shutting_down", str(e), headers={"Retry-After": "5"}) from None
        try:
            res = await asyncio.wait_for(asyncio.wrap_future(fut), settings.deadline_s + 5.0)
        except (TimeoutError, DeadlineExceededError) as e:
            raise ApiError(504, "deadline_exceeded", str(e) or "no answer within "
                           f"{settings.deadline_s} s") from None
        except WorkerCrashedError as e:
            raise ApiError(500, "worker_crashed", str(e)) from None
        except PoolClosedError as e:
            raise ApiError(503, "shutting_down", str(e), headers={"Retry-After": "5"}) from None
        except JobError as e:
            if e.internal:
                raise ApiError(500, "internal_error", f"measurement failed: {e}") from None
            code = "image_unusable" if e.kind == "ImageError" else "bad_input"
            raise ApiError(422, code, str(e)) from None
        total_ms = (time.perf_counter() - t0) * 1e3
        w = res["worker"]
        meas, robot = _finite(res["measurement"]), _finite(res["robot"])
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

    @app.get("/v1/measurements/{measurement_id}", response_model=MeasurementRecord,
             dependencies=auth, responses=_responses(401, 404, 422), tags=["measurements"])
    async def get_measurement(measurement_id: MeasurementId, store: StoreDep):
        """One stored measurement, exactly as it was answered."""
        rec = await asyncio.to_thread(store.get, measurement_id)
        if rec is None:
            raise ApiError(404, "not_found", f"no measurement {measurement_id}")
        return JSONResponse(rec)

    @app.get("/v1/measurements", response_model=MeasurementList, dependencies=auth,
             responses=_responses(401, 422), tags=["measurements"])
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

    @app.get("/v1/measurements/{measurement_id}/image", dependencies=auth,
             responses={200: {"content": {t: {} for t, _ in MEDIA_TYPES.values()},
                              "description": "The image as received."},
                        **_responses(401, 404, 422)},
             response_class=Response, tags=["measurements"])
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

    @app.get("/v1/measurements/{measurement_id}/overlay.png", dependencies=auth,
             responses={200: {"content": {"image/png": {}}, "description": "Overlay picture."},
                        **_responses(401, 404, 422, 503, 504)},
             response_class=Response, tags=["measurements"])
    async def get_overlay(measurement_id: MeasurementId, store: StoreDep, pool: PoolDep):
        """What was detected and what the pose predicts, drawn on the stored image."""
        found = await asyncio.to_thread(store.image, measurement_id)
        if found is None:
            await _not_kept(store, measurement_id)
        path, fmt, size, holder = found
        try:
            fut = pool.submit(overlay_job, str(path), fmt, size, holder,
                              deadline_s=settings.deadline_s)
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

    # -- tracking sessions ---------------------------------------------------------------
    def get_tracks(request: Request) -> TrackSessions:
        return request.app.state.tracks

    TracksDep = Annotated[TrackSessions, Depends(get_tracks)]
    TrackId = Annotated[str, Path(pattern=ID_PATTERN, description="Tracking session id.")]

    def session_of(tracks: TrackSessions, track_id: str):
        s = tracks.get(track_id)
        if s is None:
            raise ApiError(404, "not_found", f"no tracking session {track_id} (closed, or idle "
                           f"for more than {settings.track_idle_s:g} s)")
        return s

    @app.post("/v1/tracks", response_model=TrackInfo, status_code=201, dependencies=auth,
              responses=_responses(401, 422, 429), tags=["tracking"])
    async def create_track(body: TrackCreate, tracks: TracksDep):
        """Open a tracking session for one approach: send its frames in order to
        ``/v1/tracks/{id}/frames``; the first is measured in full."""
        check_holder(body.holder)
        try:
            s = await asyncio.to_thread(tracks.create, body.holder, body.filter,
                                        body.anchor_lag)
        except TooManyTracksError as e:
            raise ApiError(429, "too_many_tracks", str(e), headers={
                "Retry-After": str(int(math.ceil(settings.track_idle_s)))}) from None
        return JSONResponse(s.info(settings.track_idle_s), status_code=201)

    @app.get("/v1/tracks/{track_id}", response_model=TrackInfo, dependencies=auth,
             responses=_responses(401, 404, 422), tags=["tracking"])
    async def get_track(track_id: TrackId, tracks: TracksDep):
        """A session: frames answered, the last frame's mode."""
        return JSONResponse(session_of(tracks, track_id).info(settings.track_idle_s))

    @app.delete("/v1/tracks/{track_id}", status_code=204, dependencies=auth,
                responses=_responses(401, 404, 422), response_class=Response,
                tags=["tracking"])
    async def delete_track(track_id: TrackId, tracks: TracksDep):
        """Close a session (its tracker and the tracker's re-anchor worker, if any)."""
        s = session_of(tracks, track_id)
        async with s.lock:    # after a frame being tracked
            await asyncio.to_thread(tracks.close, track_id)
        return Response(status_code=204)

    @app.post("/v1/tracks/{track_id}/frames", response_model=TrackFrameOut, dependencies=auth,
              responses=_responses(400, 401, 404, 413, 415, 422, 500),
              openapi_extra={"requestBody": {
                  **_OPENAPI_BODY["requestBody"],
                  "content": {k: v for k, v in _OPENAPI_BODY["requestBody"]["content"].items()
                              if k != "application/json"}}},
              tags=["tracking"])
    async def post_frame(request: Request, track_id: TrackId,
                         q: Annotated[TrackFrameQuery, Query()], tracks: TracksDep):
        """The next frame of the session: its pose from the previous ones (or a full
        measurement, with the reason). Not stored."""
        t0 = time.perf_counter()
        s = session_of(tracks, track_id)
        ctype = request.headers.get("content-type", "").split(";")[0].strip().lower()
        if ctype not in FORMATS:
            raise ApiError(415, "unsupported_media_type",
                           f"content type {ctype or '(none)'!r} not accepted for frames: send "
                           "image/png, image/tiff, image/jpeg or application/octet-stream "
                           "(raw 8-bit, with width and height)")
        fmt = FORMATS[ctype]
        row = image_params(fmt, q.width, q.height, q.flange_pose)
        data = await read_body(request)
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
                out = await asyncio.to_thread(track_frame, s, cell, img, row, q.t_s,
                                              q.frame_id)
            except CutterposeError as e:
                raise ApiError(422, "bad_input", f"{type(e).__name__}: {e}") from None
            finally:
                s.last_used = time.monotonic()
        t4 = time.perf_counter()
        out = _finite(out)
        out["track_id"] = s.id
        out["timings_ms"] = out.get("timings_ms", {}) | {
            "decode_ms": round((t2 - t1) * 1e3, 3), "wait_ms": round((t3 - t2) * 1e3, 3),
            "track_ms": round((t4 - t3) * 1e3, 3), "total_ms": round((t4 - t0) * 1e3, 3)}
        return JSONResponse(out)

    # -- service -------------------------------------------------------------------------
    @app.get("/health", response_model=Health, tags=["service"])
    async def health():
        """The process answers (liveness)."""
        return {"status": "alive"}

    @app.get("/ready", response_model=Ready, responses=_responses(503), tags=["service"])
    async def ready(pool: PoolDep):
        """Cell loaded and every worker up (readiness); 503 otherwise."""
        body = {"ready": pool.ready, "workers": pool.workers(), "queued": pool.queued,
                "cell": cell.describe()}
        return JSONResponse(body, status_code=200 if body["ready"] else 503)

    @app.get("/metrics", dependencies=auth, response_class=Response,
             responses={200: {"content": {CONTENT_TYPE_LATEST: {}},
                              "description": "Prometheus text format."}, **_responses(401)},
             tags=["service"])
    async def metrics(request: Request):
        """Requests, refusals by reason, latency histograms, queue depth, workers."""
        return Response(request.app.state.metrics.text(), media_type=CONTENT_TYPE_LATEST)

    return app
