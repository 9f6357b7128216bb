"""Reading and checking an image request (measurements and tracked frames): the body, streamed
in under the size limit; its content type; the raw size and flange pose parameters; the holder
name; the encoded image's format and truncation. Every check raises :class:`.http_errors.ApiError`
before any work is queued.

Convention:
    Sizes ``(width, height)`` in pixels; formats as in :mod:`.jobs`.
"""

from __future__ import annotations

import asyncio
import logging
import time

from fastapi import Request
from starlette.requests import ClientDisconnect

from ..errors import ImageError
from .config import Cell, ServiceSettings
from .http_errors import ApiError, ClientGoneError
from .jobs import check_encoded
from .models import MeasureJSON, parse_flange_pose
from .workers import QueueFullError

__all__ = ["OPENAPI_BODY", "content_type", "read_body", "queue_full", "shutting_down",
           "check_holder", "image_params", "check_body"]

LOGGER = logging.getLogger("cutterpose.service")

OPENAPI_BODY = {
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


def content_type(request: Request) -> str:
    """The request's media type, lower case, without parameters (``""`` when absent)."""
    return request.headers.get("content-type", "").split(";")[0].strip().lower()


async def read_body(request: Request, settings: ServiceSettings) -> bytes:
    """The whole body, refused with 413 as soon as it passes ``max_body_bytes`` (so a 200 MB
    body is never held), with 400 when empty, and with 408 (connection closed) when no byte
    comes for ``body_idle_timeout_s`` or the whole body is not in after ``upload_timeout_s``.
    A client that goes away mid-body raises :class:`.http_errors.ClientGoneError`."""
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
    chunks = request.stream().__aiter__()
    end = time.monotonic() + settings.upload_timeout_s
    while True:
        left = end - time.monotonic()
        wait = min(settings.body_idle_timeout_s, left)
        try:
            chunk = await asyncio.wait_for(chunks.__anext__(), max(wait, 0.0))
        except StopAsyncIteration:
            break
        except TimeoutError:
            why = (f"no body byte for {settings.body_idle_timeout_s:g} s "
                   "(service.body_idle_timeout_s)" if wait < left else
                   f"the body was not in after {settings.upload_timeout_s:g} s "
                   "(service.upload_timeout_s)")
            LOGGER.info("%s: %s %s: %s after %d bytes; answered 408", _peer(request),
                        request.method, request.url.path, why, len(buf))
            raise ApiError(408, "request_timeout", f"{why}; received {len(buf)} bytes",
                           headers={"Connection": "close"}) from None
        except ClientDisconnect:
            of = f" of {cl}" if cl else ""
            raise ClientGoneError(f"{_peer(request)}: {request.method} {request.url.path}: the "
                             f"client went away during the upload ({len(buf)}{of} bytes "
                             "received)") from None
        buf += chunk  # checked while it streams in
        if len(buf) > limit:
            raise too_large
    if not buf:
        raise ApiError(400, "empty_body", "empty body: send the image")
    return bytes(buf)


def _peer(request: Request) -> str:
    c = request.client
    return f"{c.host}:{c.port}" if c else "client"


def queue_full(e: QueueFullError) -> ApiError:
    return ApiError(503, "queue_full", f"busy: {e}; retry after {e.retry_after_s:.0f} s",
                    headers={"Retry-After": str(int(e.retry_after_s))})


def shutting_down(e: Exception) -> ApiError:
    return ApiError(503, "shutting_down", str(e), headers={"Retry-After": "5"})


def check_holder(cell: Cell, holder: str | None) -> None:
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

