"""FastAPI dependencies of the service's routes: the shared state the application's lifespan
sets up (cell, settings, store, worker pool, tracking sessions, metrics) and the bearer-token
check.

Convention:
    The state lives on ``app.state`` (one application per cell; tests build several), so a
    dependency reads it from the request and a router holds no global.
"""

from __future__ import annotations

import hmac
import math
import threading
import time
from collections import OrderedDict, deque
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
           "AUTH", "ID_PATTERN", "MeasurementId", "TrackId", "require_token", "AuthGuard"]

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


class AuthGuard:
    """Wrong bearer tokens counted per client address: after ``max_failures`` within
    ``window_s`` every request of that address that needs the token gets 429 until the
    window has cleared, the right token included (else a right guess would still show).

    A guess costs the guesser ``window_s / max_failures`` seconds on average (3 s at the
    defaults): a 32-character token stays out of reach. Behind a proxy every client has the
    proxy's address; keep the token secret rather than lowering the limit there."""

    def __init__(self, max_failures: int, window_s: float, max_addresses: int = 10_000):
        self.max_failures, self.window_s = int(max_failures), float(window_s)
        self.max_addresses = max_addresses
        self._fails: OrderedDict[str, deque] = OrderedDict()
        self._lock = threading.Lock()

    def retry_after_s(self, address: str, now: float | None = None) -> float:
        """Seconds until ``address`` may try again (0: it may now)."""
        now = time.monotonic() if now is None else now
        with self._lock:
            q = self._fails.get(address)
            if q is None:
                return 0.0
            while q and q[0] <= now - self.window_s:
                q.popleft()
            if len(q) < self.max_failures:
                return 0.0
            return q[len(q) - self.max_failures] + self.window_s - now

    def failed(self, address: str, now: float | None = None) -> None:
        now = time.monotonic() if now is None else now
        with self._lock:
            q = self._fails.pop(address, None) or deque(maxlen=self.max_failures)
            q.append(now)
            self._fails[address] = q          # most recent last
            while len(self._fails) > self.max_addresses:
                self._fails.popitem(last=False)


def require_token(request: Request,
                  cred: Annotated[HTTPAuthorizationCredentials | None, Depends(bearer)]) -> None:
    """401 unless the request carries the cell's bearer token; 429 for an address that sent
    too many wrong ones (:class:`AuthGuard`)."""
    token = request.app.state.cell.token.encode()
    guard: AuthGuard = request.app.state.auth_guard
    address = request.client.host if request.client else ""
    wait_s = guard.retry_after_s(address)
    if wait_s > 0:
        raise ApiError(429, "too_many_auth_failures", f"{guard.max_failures} wrong bearer "
                       f"tokens from {address} within {guard.window_s:g} s; retry after "
                       f"{math.ceil(wait_s)} s", headers={"Retry-After": str(math.ceil(wait_s))})
    # constant-time: the comparison's duration does not tell how much of a guess was right
    if cred is None or not hmac.compare_digest(cred.credentials.encode(), token):
        if cred is not None:       # a missing header is a misconfigured client, not a guess
            guard.failed(address)
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
