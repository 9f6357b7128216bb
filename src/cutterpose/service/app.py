"""The HTTP API of ``cutterpose serve`` (FastAPI): measurements in, records out.

:func:`create_app` builds the application for a loaded cell: its lifespan starts the worker
pool and opens the store, its routes come from :mod:`.routes` (one router per group), the
shared state reaches them as dependencies (:mod:`.deps`), and every error is an
:class:`.models.ErrorBody` (:mod:`.http_errors`).

Convention:
    Units and frames as in :mod:`.models`.
"""

import asyncio
from contextlib import asynccontextmanager

from fastapi import FastAPI

from .config import Cell
from .deps import AuthGuard
from .http_errors import ApiError, install_error_handlers
from .jobs import init_worker
from .metrics import Metrics, MetricsMiddleware
from .routes import ROUTERS
from .store import Store
from .tracks import TrackSessions
from .workers import WorkerPool

__all__ = ["create_app", "ApiError"]


def create_app(cell: Cell, pool: WorkerPool | None = None) -> FastAPI:
    """The application for a loaded cell. The worker pool and the store start with the
    application's lifespan (``pool``: a ready-made pool, for tests)."""
    settings = cell.service

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
    app.state.cell = cell
    app.state.auth_guard = AuthGuard(settings.auth_max_failures, settings.auth_window_s)
    app.add_middleware(MetricsMiddleware,
                       metrics_getter=lambda: getattr(app.state, "metrics", None))
    install_error_handlers(app)
    for router in ROUTERS:
        app.include_router(router)
    return app
