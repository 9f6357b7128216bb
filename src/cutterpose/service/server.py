"""Running the service under uvicorn with limits on what a slow or hostile client can hold.

uvicorn closes an idle keep-alive connection (``timeout_keep_alive``) and refuses a request
head larger than ``h11_max_incomplete_event_size`` (400), but a connection that sends a partial
request head and then nothing is kept open for ever. :class:`GuardedH11Protocol` adds what it
lacks:

- a header deadline (``service.header_timeout_s``): a connection whose request head is not
  complete that long after it opened (or after its previous answer) is closed;
- a connection cap (``service.max_connections``): connections beyond it are closed at once,
  so idle sockets cannot use up the process's file descriptors.

The body's own deadlines (idle and whole upload: 408) are the application's
(:func:`.bodies.read_body`). Each closing is logged as one INFO line on the ``cutterpose``
logger.

Convention:
    Times in seconds; sizes in bytes.
"""

from __future__ import annotations

import logging

import h11
from uvicorn.protocols.http.h11_impl import H11Protocol

from .config import Cell, ServiceSettings
from .store import Store

__all__ = ["GuardedH11Protocol", "uvicorn_config", "run", "check_store", "LOGGER"]

LOGGER = logging.getLogger("cutterpose.service")


class GuardedH11Protocol(H11Protocol):
    """uvicorn's h11 protocol with a request-head deadline and a connection cap (module doc);
    the limits are class attributes, set by :func:`guarded_protocol`."""

    header_timeout_s: float = 10.0
    max_connections: int = 1000

    def connection_made(self, transport) -> None:
        super().connection_made(transport)
        self._head_timer = None
        if len(self.connections) > self.max_connections:
            LOGGER.info("%s: connection closed at once: %d connections open, the limit is %d "
                        "(service.max_connections)", _peer(self.client), len(self.connections),
                        self.max_connections)
            self.transport.close()
            return
        self._arm()

    def data_received(self, data: bytes) -> None:
        super().data_received(data)
        if self.conn.their_state is not h11.IDLE:    # the request head is complete
            self._disarm()

    def on_response_complete(self) -> None:
        super().on_response_complete()
        if not self.transport.is_closing():
            self._arm()                               # the next request's head

    def connection_lost(self, exc) -> None:
        self._disarm()
        super().connection_lost(exc)

    def _arm(self) -> None:
        self._disarm()
        self._head_timer = self.loop.call_later(self.header_timeout_s, self._head_timeout)

    def _disarm(self) -> None:
        timer = getattr(self, "_head_timer", None)
        if timer is not None:
            timer.cancel()
            self._head_timer = None

    def _head_timeout(self) -> None:
        self._head_timer = None
        if self.transport.is_closing() or self.conn.their_state is not h11.IDLE:
            return
        LOGGER.info("%s: connection closed: no complete request head within %g s "
                    "(service.header_timeout_s)", _peer(self.client), self.header_timeout_s)
        self.transport.close()


def _peer(client) -> str:
    return f"{client[0]}:{client[1]}" if client else "client"


def guarded_protocol(settings: ServiceSettings) -> type[GuardedH11Protocol]:
    """:class:`GuardedH11Protocol` with the cell's limits."""
    return type("CellH11Protocol", (GuardedH11Protocol,),
                {"header_timeout_s": settings.header_timeout_s,
                 "max_connections": settings.max_connections})


def log_config(log_level: str) -> dict:
    """uvicorn's logging configuration plus the ``cutterpose`` logger on its handler."""
    from uvicorn.config import LOGGING_CONFIG

    cfg = {k: (dict(v) if isinstance(v, dict) else v) for k, v in LOGGING_CONFIG.items()}
    cfg["loggers"] = dict(cfg["loggers"]) | {
        "cutterpose": {"handlers": ["default"], "level": log_level.upper(),
                       "propagate": False}}
    return cfg


def uvicorn_config(cell: Cell, app, host: str = "127.0.0.1", port: int = 8000,
                   log_level: str = "info", **ssl):
    """The ``uvicorn.Config`` of ``cutterpose serve``: the cell's timeouts and limits."""
    import uvicorn

    s = cell.service
    return uvicorn.Config(
        app, host=host, port=port, log_level=log_level, log_config=log_config(log_level),
        http=guarded_protocol(s), timeout_keep_alive=max(1, round(s.keep_alive_s)),
        h11_max_incomplete_event_size=s.max_header_bytes, timeout_graceful_shutdown=10,
        **ssl)


def check_store(settings: ServiceSettings) -> None:
    """Open the record once before serving, so that a locked, corrupt or unwritable database
    stops the start with its reason (:class:`~.store.StoreError`)."""
    Store(settings.data_dir, settings.image_cap_bytes).close()


def run(cell: Cell, host: str = "127.0.0.1", port: int = 8000, log_level: str = "info",
        **ssl) -> None:
    """Serve ``cell`` until interrupted (``cutterpose serve``).

    Raises
    ------
    StoreError
        The data directory's database cannot be opened (before anything is served).
    """
    import uvicorn

    from .app import create_app

    check_store(cell.service)
    uvicorn.Server(uvicorn_config(cell, create_app(cell), host, port, log_level,
                                  **ssl)).run()
