"""GET /metrics: Prometheus exposition of the server's metrics (every worker process's)."""

from __future__ import annotations

from fastapi import APIRouter, Response
from prometheus_client import CONTENT_TYPE_LATEST

from app.http.deps import MetricsDep

router = APIRouter(tags=["health"])


@router.get("/metrics", response_class=Response)
def metrics(m: MetricsDep) -> Response:
    """Request counts and latency per route, detections calibrated, fit jobs, active versions."""
    return Response(m.exposition(), media_type=CONTENT_TYPE_LATEST)
