"""Liveness, readiness and metrics."""

from __future__ import annotations

from fastapi import APIRouter, Request
from fastapi.responses import PlainTextResponse

from service import schemas
from service.problems import ApiError

router = APIRouter(tags=["operations"])


@router.get("/healthz", operation_id="operations-healthz", summary="Liveness", response_model=schemas.Health)
def healthz() -> dict:
    return {"status": "ok"}


@router.get("/readyz", operation_id="operations-readyz", summary="Readiness: the session store is reachable",
            response_model=schemas.Readiness)
def readyz(request: Request) -> dict:
    store = request.app.state.store
    try:
        store.ping()
    except Exception as error:  # any store failure means not ready, whatever the backend raises
        raise ApiError(503, "store_unavailable", f"session store unreachable: {type(error).__name__}") from error
    return {"status": "ready", "store": store.kind}


@router.get("/metrics", operation_id="operations-metrics", summary="Prometheus metrics",
            response_class=PlainTextResponse)
def metrics(request: Request) -> PlainTextResponse:
    return PlainTextResponse(request.app.state.metrics.render(), media_type="text/plain; version=0.0.4")
