"""Pure-ASGI middleware: request ids, the body limit, rate limiting and metrics.

Pure ASGI rather than ``BaseHTTPMiddleware``: no extra task per request and
the body can be counted while it streams.
"""

from __future__ import annotations

import itertools
import logging
import time
import uuid

import orjson

from service.metrics import Metrics
from service.problems import MEDIA_TYPE, problem_body

logger = logging.getLogger("passive_locator")


async def _send_problem(send, status: int, code: str, detail: str, request_id: str, headers=()) -> None:
    body = orjson.dumps(problem_body(status, code, detail, request_id=request_id))
    await send({"type": "http.response.start", "status": status,
                "headers": [(b"content-type", MEDIA_TYPE.encode()), (b"content-length", str(len(body)).encode()),
                            (b"x-request-id", request_id.encode()), *headers]})
    await send({"type": "http.response.body", "body": body})


class _BodyTooLarge(Exception):
    pass


class ServiceMiddleware:
    """Request id (echoed or made), body limit (413), rate limit (429), metrics, and the 500 of last resort."""

    def __init__(self, app, max_body_bytes: int, metrics: Metrics, rate_limiter=None):
        self._id_prefix = uuid.uuid4().hex[:16]
        self._id_counter = itertools.count(1)
        self.app = app
        self.max_body_bytes = max_body_bytes
        self.metrics = metrics
        self.rate_limiter = rate_limiter

    async def __call__(self, scope, receive, send):
        if scope["type"] != "http":
            await self.app(scope, receive, send)
            return
        headers = dict(scope.get("headers") or [])
        request_id = headers.get(b"x-request-id", b"").decode("latin-1")[:128] or self._next_request_id()
        scope.setdefault("state", {})["request_id"] = request_id
        started = time.perf_counter()
        status_holder = {"status": 500, "started": False}

        async def send_with_id(message):
            if message["type"] == "http.response.start":
                status_holder["status"], status_holder["started"] = message["status"], True
                message = {**message, "headers": [*message.get("headers", []), (b"x-request-id", request_id.encode())]}
            await send(message)

        try:
            declared = headers.get(b"content-length")
            if declared is not None and declared.isdigit() and int(declared) > self.max_body_bytes:
                await self._too_large(send_with_id, request_id)
                return
            if self.rate_limiter is not None:
                client = headers.get(b"authorization") or (scope.get("client") or ("?",))[0].encode()
                retry_after = self.rate_limiter.take(client)
                if retry_after:
                    status_holder["started"] = True
                    status_holder["status"] = 429
                    await _send_problem(send, 429, "rate_limited", "over the configured rate limit", request_id,
                                        [(b"retry-after", str(max(1, round(retry_after))).encode())])
                    return
            received = 0

            async def counting_receive():
                nonlocal received
                message = await receive()
                if message["type"] == "http.request":
                    received += len(message.get("body", b""))
                    if received > self.max_body_bytes:
                        raise _BodyTooLarge
                return message

            await self.app(scope, counting_receive, send_with_id)
        except _BodyTooLarge:
            if not status_holder["started"]:
                await self._too_large(send_with_id, request_id)
        except Exception:
            logger.exception("unhandled error (request id %s)", request_id)
            if not status_holder["started"]:
                await _send_problem(send, 500, "internal_error", f"internal error; quote request id {request_id}",
                                    request_id)
            status_holder["status"] = 500
        finally:
            route = scope.get("route")
            path = getattr(route, "path", None) or "unmatched"
            self.metrics.observe(scope.get("method", "?"), path, status_holder["status"],
                                 time.perf_counter() - started)

    def _next_request_id(self) -> str:
        """Unique per process start and request; one urandom call per process, not per request."""
        return f"{self._id_prefix}{next(self._id_counter):016x}"

    async def _too_large(self, send, request_id):
        body = orjson.dumps(problem_body(413, "body_too_large",
                                         f"request body exceeds {self.max_body_bytes} bytes", request_id=request_id))
        await send({"type": "http.response.start", "status": 413,
                    "headers": [(b"content-type", MEDIA_TYPE.encode()), (b"content-length", str(len(body)).encode()),
                                (b"connection", b"close")]})
        await send({"type": "http.response.body", "body": body})


class TokenBucket:
    """Per-client token buckets: ``rate`` tokens per second up to ``burst``."""

    def __init__(self, rate_per_s: float, burst: int, clock=time.monotonic):
        self.rate, self.burst, self.clock = rate_per_s, burst, clock
        self.buckets: dict[bytes, tuple[float, float]] = {}

    def take(self, client: bytes) -> float:
        """Take one token; returns 0 when allowed, else the seconds until one is free."""
        now = self.clock()
        tokens, last = self.buckets.get(client, (float(self.burst), now))
        tokens = min(float(self.burst), tokens + (now - last) * self.rate)
        if tokens >= 1.0:
            self.buckets[client] = (tokens - 1.0, now)
            return 0.0
        self.buckets[client] = (tokens, now)
        return (1.0 - tokens) / self.rate
