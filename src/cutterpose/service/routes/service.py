"""The service's own routes: liveness (``/health``), readiness (``/ready``) and Prometheus
metrics (``/metrics``)."""

from __future__ import annotations

from fastapi import APIRouter
from fastapi.responses import JSONResponse, Response

from ..deps import AUTH, CellDep, MetricsDep, PoolDep
from ..http_errors import responses
from ..metrics import CONTENT_TYPE_LATEST
from ..models import Health, Ready

__all__ = ["router"]

router = APIRouter(tags=["service"])


@router.get("/health", response_model=Health)
async def health():
    """The process answers (liveness)."""
    return {"status": "alive"}


@router.get("/ready", response_model=Ready, responses=responses(503))
async def ready(pool: PoolDep, cell: CellDep):
    """Cell loaded and every worker up (readiness); 503 otherwise."""
    body = {"ready": pool.ready, "workers": pool.workers(), "queued": pool.queued,
            "cell": cell.describe()}
    return JSONResponse(body, status_code=200 if body["ready"] else 503)


@router.get("/metrics", dependencies=AUTH, response_class=Response,
            responses={200: {"content": {CONTENT_TYPE_LATEST: {}},
                             "description": "Prometheus text format."}, **responses(401)})
async def metrics(m: MetricsDep):
    """Requests, refusals by reason, latency histograms, queue depth, workers."""
    return Response(m.text(), media_type=CONTENT_TYPE_LATEST)
