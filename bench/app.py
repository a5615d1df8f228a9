"""The benchmark's own app: the product app plus ``POST /bench/echo``.

The echo route is the yardstick for the single-fix row: the fix route's shape
with a solve that costs nothing. Like ``POST /v1/fixes`` it is an ``async``
route behind the same middleware that decodes the body as the fix route does
(:func:`service.fixes.decode.decode_fix`, else orjson), checks the owner, hands the
body to a one-thread executor and waits for it there (as the coalescer's
drain does), then answers with the body's JSON; the worker only returns the
body. ``POST /bench/echo_inline`` does the same without the hop to the
worker, so the two tell what the hop alone costs. Both exist only in this
instance, never in the product API (whose routes run no CPU work on the loop).
"""

from __future__ import annotations

import asyncio
from concurrent.futures import ThreadPoolExecutor

import msgspec
from fastapi import FastAPI, Request
from starlette.responses import Response

from service.app import create_app
from service.fixes.decode import decode_fix
from service.settings import Settings
from service.web.deps import get_owner, parse_json


def create_bench_app(settings: Settings | None = None) -> FastAPI:
    """``create_app(settings)`` with ``POST /bench/echo`` and ``POST /bench/echo_inline`` added."""
    app = create_app(settings)
    worker = ThreadPoolExecutor(1, thread_name_prefix="echo")

    @app.post("/bench/echo", include_in_schema=False)
    async def echo(http: Request) -> Response:
        raw = await http.body()
        body = decode_fix(raw) or parse_json(raw)
        get_owner(http)
        body = await asyncio.get_running_loop().run_in_executor(worker, lambda: body)
        return Response(msgspec.json.encode(body), media_type="application/json")

    @app.post("/bench/echo_inline", include_in_schema=False)
    async def echo_inline(http: Request) -> Response:
        raw = await http.body()
        body = decode_fix(raw) or parse_json(raw)
        get_owner(http)
        return Response(msgspec.json.encode(body), media_type="application/json")

    return app


def app_from_environment() -> FastAPI:
    """Factory for ``uvicorn --factory bench.app:app_from_environment`` (settings from the environment)."""
    return create_bench_app()
