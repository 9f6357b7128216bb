"""The service's error answers: :class:`ApiError` and the exception handlers that turn every
failure into a typed JSON body (:class:`.models.ErrorBody`), counted in the refusals metric.

Convention:
    ``error`` is a stable machine-readable code (``too_large``, ``queue_full``, ...),
    ``message`` one line for a person; ``detail`` lists every validation error when there are
    several.
"""

from __future__ import annotations

import logging
import math

from fastapi import FastAPI, Request
from fastapi.exceptions import RequestValidationError
from fastapi.responses import JSONResponse, Response
from starlette.exceptions import HTTPException as StarletteHTTPException

from .models import ErrorBody

LOGGER = logging.getLogger("cutterpose.service")

__all__ = ["ApiError", "ClientGoneError", "error_response", "responses",
           "install_error_handlers", "finite", "refuse"]

ERRORS = {400: "Malformed request", 401: "Missing or wrong bearer token",
          404: "Not found", 408: "The body did not arrive in time (connection closed)",
          409: "Request id reused for a different request",
          413: "Body larger than the limit", 415: "Unsupported content type",
          422: "Invalid parameters or unusable image",
          429: "Too many tracking sessions open, or too many wrong tokens from this address "
               "(retry after Retry-After seconds)",
          500: "Service fault",
          503: "Busy (retry after Retry-After seconds), not ready, or the data directory "
               "cannot be written now",
          504: "Deadline exceeded"}


def responses(*codes) -> dict:
    """The OpenAPI ``responses`` entry of a route's error codes (a route that needs the token
    may also answer 429 to an address that sent too many wrong ones)."""
    if 401 in codes and 429 not in codes:
        codes = (*codes, 429)
    return {c: {"model": ErrorBody, "description": ERRORS[c]} for c in sorted(codes)}


class ApiError(Exception):
    """An HTTP error with a typed body (:class:`.models.ErrorBody`)."""

    def __init__(self, status: int, error: str, message: str, headers: dict | None = None,
                 detail: list | None = None):
        super().__init__(message)
        self.status, self.error, self.message = status, error, message
        self.headers, self.detail = headers, detail


class ClientGoneError(Exception):
    """The client closed the connection before its request was in: logged as one INFO line
    (never an error with a traceback), nothing answered."""


def error_response(status: int, error: str, message: str, headers=None, detail=None):
    body = {"error": error, "message": message}
    if detail is not None:
        body["detail"] = detail
    return JSONResponse(body, status_code=status, headers=headers)


def finite(x):
    """JSON-safe copy: NaN / inf become null (the record is stored with allow_nan=False)."""
    if isinstance(x, float):
        return x if math.isfinite(x) else None
    if isinstance(x, dict):
        return {k: finite(v) for k, v in x.items()}
    if isinstance(x, (list, tuple)):
        return [finite(v) for v in x]
    return x


def refuse(app: FastAPI, reason: str) -> None:
    """Count a refusal by reason (once the application's metrics exist)."""
    m = getattr(app.state, "metrics", None)
    if m is not None:
        m.refuse(reason)


def install_error_handlers(app: FastAPI) -> None:
    """Every exception becomes a typed JSON answer (a fault: 500, its traceback in the log)."""

    @app.exception_handler(ClientGoneError)
    async def _client_gone(request: Request, e: ClientGoneError):
        refuse(request.app, "client_gone")
        LOGGER.info("%s", e)
        return Response(status_code=400)   # nobody reads it: the connection is gone

    @app.exception_handler(ApiError)
    async def _api_error(request: Request, e: ApiError):
        refuse(request.app, e.error)
        return error_response(e.status, e.error, e.message, e.headers, e.detail)

    @app.exception_handler(RequestValidationError)
    async def _validation_error(request: Request, e: RequestValidationError):
        refuse(request.app, "validation_error")
        errs = [{"loc": list(x.get("loc", ())), "msg": x.get("msg", ""),
                 "type": x.get("type", "")} for x in e.errors()]
        first = errs[0] if errs else {"loc": [], "msg": "invalid request"}
        where = ".".join(str(p) for p in first["loc"])
        return error_response(422, "validation_error", f"{where}: {first['msg']}",
                              detail=errs)

    @app.exception_handler(StarletteHTTPException)
    async def _http_error(request: Request, e: StarletteHTTPException):
        code = {404: "not_found", 405: "method_not_allowed"}.get(e.status_code, "http_error")
        return error_response(e.status_code, code, str(e.detail),
                              getattr(e, "headers", None))

    @app.exception_handler(Exception)
    async def _internal(request: Request, e: Exception):
        refuse(request.app, "internal_error")
        return error_response(500, "internal_error", "internal error (see the service log)")
