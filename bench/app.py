"""The benchmark's own app: the product app plus ``POST /bench/echo``.

The echo route is the yardstick for the single-fix row: the fix route's shape
with a solve that costs nothing. Like ``POST /v1/fixes`` it is an ``async``
route behind the same middleware that reads the body with orjson, checks the
owner, hands the parsed body to a one-thread executor and waits for it there
(as the coalescer's drain does), then answers with orjson; the worker only
returns the body. It exists only in this instance, never in the product API.
"""

from __future__ import annotations

import asyncio
from concurrent.futures import ThreadPoolExecutor

from fastapi import FastAPI, Request

from service.app import create_app
from service.deps import get_owner, parse_json
from service.responses import JsonResponse
from service.settings import Settings


def create_bench_app(settings: Settings | None = None) -> FastAPI:
    """``create_app(settings)`` with ``POST /bench/echo`` added."""
    app = create_app(settings)
    worker = ThreadPoolExecutor(1, thread_name_prefix="echo")

    @app.post("/bench/echo", include_in_schema=False)
    async def echo(http: Request) -> JsonResponse:
        body = parse_json(await http.body())
        get_owner(http)
        return JsonResponse(await asyncio.get_running_loop().run_in_executor(worker, lambda: body))

    return app


def app_from_environment() -> FastAPI:
    """Factory for ``uvicorn --factory bench.app:app_from_environment`` (settings from the environment)."""
    return create_bench_app()
