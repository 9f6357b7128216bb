"""Prometheus metrics of the service (``GET /metrics``, text exposition format).

One registry per application (tests build several). Metric names follow Prometheus' naming
rules: base units (seconds, bytes), ``_total`` for counters.

Convention:
    ``route`` labels are the route templates (``/v1/measurements/{measurement_id}``), never raw
    paths, so that the label set stays bounded.
"""

from __future__ import annotations

import time

from prometheus_client import (
    CONTENT_TYPE_LATEST,
    CollectorRegistry,
    Counter,
    Gauge,
    Histogram,
    generate_latest,
)

__all__ = ["Metrics", "CONTENT_TYPE_LATEST", "MetricsMiddleware"]

_LATENCY_BUCKETS_S = (0.01, 0.025, 0.05, 0.1, 0.25, 0.5, 1.0, 2.5, 5.0, 10.0, 30.0, 60.0)


class Metrics:
    """The service's counters, histograms and gauges."""

    def __init__(self, pool=None, store=None):
        self.registry = r = CollectorRegistry()
        self.requests = Counter("cutterpose_http_requests", "HTTP requests answered",
                                ["method", "route", "status"], registry=r)
        self.latency = Histogram("cutterpose_http_request_duration_seconds",
                                 "Time from request to answer", ["route"],
                                 buckets=_LATENCY_BUCKETS_S, registry=r)
        self.refusals = Counter("cutterpose_refusals", "Requests refused, by reason "
                                "(unauthorized, too_large, queue_full, deadline, "
                                "worker_crashed, bad_input, unsupported_media_type, ...)",
                                ["reason"], registry=r)
        self.measure_s = Histogram("cutterpose_measure_duration_seconds",
                                   "Decoding and measurement time in a worker",
                                   buckets=_LATENCY_BUCKETS_S, registry=r)
        self.measurements = Counter("cutterpose_measurements", "Measurements stored",
                                    ["ok"], registry=r)
        if pool is not None:
            Gauge("cutterpose_queue_depth", "Requests waiting for a worker",
                  registry=r).set_function(lambda: pool.queued)
            Gauge("cutterpose_jobs_running", "Jobs running in workers",
                  registry=r).set_function(lambda: pool.running)
            Gauge("cutterpose_workers", "Worker processes configured",
                  registry=r).set_function(lambda: pool.n_workers)
            Gauge("cutterpose_workers_ready", "Worker processes alive and ready",
                  registry=r).set_function(
                lambda: sum(w["alive"] and w["ready"] for w in pool.workers()))
            Gauge("cutterpose_worker_restarts", "Worker processes replaced since start "
                  "(crashes and deadline kills)", registry=r).set_function(lambda: pool.restarts)
        if store is not None:
            Gauge("cutterpose_images_bytes", "Bytes of stored images",
                  registry=r).set_function(lambda: store.images_bytes)

    def refuse(self, reason: str) -> None:
        self.refusals.labels(reason).inc()

    def text(self) -> bytes:
        return generate_latest(self.registry)


class MetricsMiddleware:
    """ASGI middleware counting every HTTP answer by route template and status, with its
    latency (pure ASGI, so streaming bodies are not buffered)."""

    def __init__(self, app, metrics_getter):
        self.app = app
        self.metrics_getter = metrics_getter

    async def __call__(self, scope, receive, send):
        if scope["type"] != "http":
            return await self.app(scope, receive, send)
        t0 = time.perf_counter()
        status = {"code": 500}

        async def send_wrapper(message):
            if message["type"] == "http.response.start":
                status["code"] = message["status"]
            await send(message)

        try:
            await self.app(scope, receive, send_wrapper)
        finally:
            m = self.metrics_getter()
            if m is not None:
                route = getattr(scope.get("route"), "path", None) or "unmatched"
                m.requests.labels(scope["method"], route, str(status["code"])).inc()
                m.latency.labels(route).observe(time.perf_counter() - t0)
