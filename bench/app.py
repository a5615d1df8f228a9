"""The benchmark's own app: the product app plus ``POST /bench/echo``.

The echo route is the yardstick for the single-fix row: the same framework,
middleware, body size, JSON parsing and orjson response as ``/v1/fixes``,
with no work. It exists only in this instance, never in the product API.
"""

from __future__ import annotations

from typing import Any

from fastapi import FastAPI

from service.app import create_app
from service.responses import JsonResponse
from service.settings import Settings


def create_bench_app(settings: Settings | None = None) -> FastAPI:
    """``create_app(settings)`` with ``POST /bench/echo`` added (a plain ``def``, like the fix route)."""
    app = create_app(settings)

    @app.post("/bench/echo", include_in_schema=False)
    def echo(body: dict[str, Any]) -> JsonResponse:
        return JsonResponse(body)

    return app


def app_from_environment() -> FastAPI:
    """Factory for ``uvicorn --factory bench.app:app_from_environment`` (settings from the environment)."""
    return create_bench_app()
