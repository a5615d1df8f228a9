"""Liveness, readiness and metrics: on the event loop, so no thread pool (busy or stuck) can delay them."""

from __future__ import annotations

from fastapi import APIRouter, Request
from fastapi.responses import PlainTextResponse

from service import schemas
from service.schemas import Problem

router = APIRouter(tags=["operations"])


@router.get("/healthz", operation_id="operations-healthz", summary="Liveness", response_model=schemas.Health)
async def healthz() -> dict:
    return {"status": "ok"}


@router.get("/readyz", operation_id="operations-readyz",
            summary="Readiness: the session store answers, takes a write, and (SQLite) passes its integrity check",
            response_model=schemas.Readiness,
            responses={503: {"model": Problem, "description": "the store is unreachable, read-only, full or damaged",
                             "headers": {"Retry-After": {"description": "seconds", "schema": {"type": "string"}}}}})
async def readyz(request: Request) -> dict:
    store = request.app.state.store
    await store.check()
    return {"status": "ready", "store": store.kind}


@router.get("/metrics", operation_id="operations-metrics", summary="Prometheus metrics",
            response_class=PlainTextResponse)
async def metrics(request: Request) -> PlainTextResponse:
    request.app.state.metrics.refresh_live_sessions(request.app.state.store)
    return PlainTextResponse(request.app.state.metrics.render(), media_type="text/plain; version=0.0.4")
