"""FastAPI dependencies of the service's routes: the shared state the application's lifespan
sets up (cell, settings, store, worker pool, tracking sessions, metrics) and the bearer-token
check.

Convention:
    The state lives on ``app.state`` (one application per cell; tests build several), so a
    dependency reads it from the request and a router holds no global.
"""

from __future__ import annotations

import hmac
from typing import Annotated

from fastapi import Depends, Path, Request
from fastapi.security import HTTPAuthorizationCredentials, HTTPBearer

from .config import Cell, ServiceSettings
from .http_errors import ApiError
from .metrics import Metrics
from .store import Store
from .tracks import TrackSessions
from .workers import WorkerPool

__all__ = ["CellDep", "SettingsDep", "StoreDep", "PoolDep", "TracksDep", "MetricsDep",
           "AUTH", "ID_PATTERN", "MeasurementId", "TrackId", "require_token"]

ID_PATTERN = r"^[0-9a-f]{32}$"

bearer = HTTPBearer(auto_error=False, description="The cell's token (CUTTERPOSE_TOKEN or "
                    "service.token_file of the cell file).")


def get_cell(request: Request) -> Cell:
    return request.app.state.cell


def get_settings(request: Request) -> ServiceSettings:
    return request.app.state.cell.service


def get_store(request: Request) -> Store:
    return request.app.state.store


def get_pool(request: Request) -> WorkerPool:
    return request.app.state.pool


def get_tracks(request: Request) -> TrackSessions:
    return request.app.state.tracks


def get_metrics(request: Request) -> Metrics:
    return request.app.state.metrics


def require_token(request: Request,
                  cred: Annotated[HTTPAuthorizationCredentials | None, Depends(bearer)]) -> None:
    """401 unless the request carries the cell's bearer token."""
    token = request.app.state.cell.token.encode()
    # constant-time: the comparison's duration does not tell how much of a guess was right
    if cred is None or not hmac.compare_digest(cred.credentials.encode(), token):
        raise ApiError(401, "unauthorized", "missing or wrong bearer token (header "
                       "'Authorization: Bearer <token>')",
                       headers={"WWW-Authenticate": "Bearer"})


CellDep = Annotated[Cell, Depends(get_cell)]
SettingsDep = Annotated[ServiceSettings, Depends(get_settings)]
StoreDep = Annotated[Store, Depends(get_store)]
PoolDep = Annotated[WorkerPool, Depends(get_pool)]
TracksDep = Annotated[TrackSessions, Depends(get_tracks)]
MetricsDep = Annotated[Metrics, Depends(get_metrics)]
#: the routes' ``dependencies=`` for the bearer token
AUTH = [Depends(require_token)]
MeasurementId = Annotated[str, Path(pattern=ID_PATTERN, description="Measurement id.")]
TrackId = Annotated[str, Path(pattern=ID_PATTERN, description="Tracking session id.")]
