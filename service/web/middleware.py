"""Pure-ASGI middleware: request ids, the header fields (400), rate limiting (429), who is asking (401),
content type (415), the body limit (413), metrics, one log line per request, the 503 of a request cut off
at shutdown, and the 500 of last resort.

Pure ASGI rather than ``BaseHTTPMiddleware``: no extra task per request, and
the body is read here, counted while it streams (a chunked body over the
limit is a 413 like a declared one), and handed to the app in one piece.

In that order, so that nothing of a request is read or parsed for a caller that is not let in: the header
fields the service reads are parsed once, strictly (:mod:`service.web.headers`), the caller's one identity is
worked out from them (:mod:`service.web.auth`: the limiter's bucket, the 401 and the routes' owner all come
from it), and only then is the body read.
"""

from __future__ import annotations

import asyncio
import itertools
import logging
import time
import uuid
from collections import OrderedDict

import orjson
from starlette.routing import Match

from service.ops.logs import request_id_var
from service.ops.metrics import Metrics
from service.web import auth
from service.web.headers import HeaderError, RequestHeaders
from service.web.problems import MEDIA_TYPE, ApiError, problem_body

logger = logging.getLogger("passive_locator")

#: Probes are never rate-limited (an orchestrator's health check must not fail under load).
PROBE_PATHS = frozenset(("/healthz", "/readyz", "/metrics"))
#: What :meth:`ServiceMiddleware._read_body` returns for a body whose connection ended before it did.
_GONE = object()
#: Methods whose body must be JSON (the only one any route takes a body with; others get 405 from the router).
_BODY_METHODS = frozenset(("POST",))
#: Route-match answers :meth:`ServiceMiddleware._route_matches` keeps (by method and path), and the longest
#: path kept: a session's path is under 100 characters, and the bound keeps what unknown paths can fill small.
_ROUTE_ANSWERS_KEPT = 4096
_ROUTE_PATH_KEPT = 256


def is_json_media_type(media: bytes | None) -> bool:
    """``application/json`` or any ``application/<x>+json`` (a parsed media type, without parameters)."""
    return media is not None and (media == b"application/json"
                                  or (media.startswith(b"application/") and media.endswith(b"+json")))


async def _send_problem(send, status: int, code: str, detail: str, request_id: str, headers=()) -> None:
    body = orjson.dumps(problem_body(status, code, detail, request_id=request_id))
    await send({"type": "http.response.start", "status": status,
                "headers": [(b"content-type", MEDIA_TYPE.encode()), (b"content-length", str(len(body)).encode()),
                            *headers]})
    await send({"type": "http.response.body", "body": body})


async def _send_error(send, error: ApiError, request_id: str) -> None:
    await _send_problem(send, error.status, error.code, error.detail, request_id,
                        [(name.lower().encode(), value.encode()) for name, value in error.headers.items()])


class ServiceMiddleware:
    """Request id (echoed or made), 400 (header fields), 429, 401, 415, 413, metrics, access log, and the 500
    of last resort."""

    def __init__(self, app, max_body_bytes: int, metrics: Metrics, rate_limiter=None,
                 key_digests: frozenset[bytes] = frozenset(), routes=()):
        self.routes = routes
        self._route_answers: OrderedDict[tuple, bool] = OrderedDict()
        self._id_prefix = uuid.uuid4().hex[:16]
        self._id_counter = itertools.count(1)
        self.app = app
        self.max_body_bytes = max_body_bytes
        self.metrics = metrics
        self.rate_limiter = rate_limiter
        self.key_digests = key_digests

    async def __call__(self, scope, receive, send):
        if scope["type"] != "http":
            await self.app(scope, receive, send)
            return
        state = scope.setdefault("state", {})
        try:
            headers = RequestHeaders.parse(scope.get("headers") or [])
            header_error = None
        except HeaderError as error:
            headers, header_error = RequestHeaders(), error
        request_id = headers.request_id or self._next_request_id()
        state["request_id"] = request_id
        state["headers"] = headers
        identity = auth.identify(headers.authorization, self.key_digests,
                                 str((scope.get("client") or ("?",))[0]))
        state["identity"] = identity
        token = request_id_var.set(request_id)
        started = time.perf_counter()
        status_holder = {"status": 500, "started": False}

        async def send_with_id(message):
            if message["type"] == "http.response.start":
                status_holder["status"], status_holder["started"] = message["status"], True
                message = {**message, "headers": [*message.get("headers", []), (b"x-request-id", request_id.encode())]}
            await send(message)

        try:
            path, method = scope.get("path", ""), scope.get("method", "GET")
            if header_error is not None and self._route_matches(scope):  # else the router's 404 or 405
                refusal = (auth.unauthorized(None, header_error.detail) if header_error.status == 401
                           else ApiError(400, "invalid_header", header_error.detail))
                await _send_error(send_with_id, refusal, request_id)
                return
            if self.rate_limiter is not None and path not in PROBE_PATHS:
                retry_after = self.rate_limiter.take(identity.limiter_key)
                if retry_after:
                    await _send_problem(send_with_id, 429, "rate_limited", "over the configured rate limit",
                                        request_id, [(b"retry-after", str(max(1, round(retry_after))).encode())])
                    return
            if self.key_digests and identity.owner is None and auth.protects(path) and self._route_matches(scope):
                await _send_error(send_with_id, auth.unauthorized(identity), request_id)  # before any body is read
                return
            if method in _BODY_METHODS and self._route_matches(scope):
                if not is_json_media_type(headers.content_type):
                    await _send_problem(send_with_id, 415, "unsupported_media_type",
                                        "the body must be JSON: Content-Type: application/json", request_id,
                                        [(b"accept-post", b"application/json")])
                    return
                body = await self._read_body(headers.content_length, receive)
                if body is None:
                    await self._too_large(send_with_id, request_id)
                    return
                if body is _GONE:  # the client went away (or the server's body deadline closed it)
                    status_holder["status"] = 499
                    return
                receive = _replay(body, receive)
            await self.app(scope, receive, send_with_id)
        except asyncio.CancelledError:
            # Only the server cancels a request's task: at shutdown, once its graceful timeout is over. The
            # client is told to come back (to another replica) rather than left with the server's plain 500.
            if status_holder["started"]:
                raise
            logger.warning("request cancelled at shutdown: answered 503 shutting_down")
            await _send_problem(send_with_id, 503, "shutting_down", "the server is shutting down; retry",
                                request_id, [(b"retry-after", b"1"), (b"connection", b"close")])
        except Exception:
            logger.exception("unhandled error")
            if not status_holder["started"]:
                await _send_problem(send_with_id, 500, "internal_error",
                                    f"internal error; quote request id {request_id}", request_id)
            status_holder["status"] = 500
        finally:
            route = scope.get("route")
            template = getattr(route, "path", None) or "unmatched"
            seconds = time.perf_counter() - started
            self.metrics.observe(scope.get("method", "?"), template, status_holder["status"], seconds)
            logger.info("request", extra={"method": scope.get("method"), "path": template,
                                          "status": status_holder["status"], "duration_ms": round(seconds * 1e3, 2)})
            request_id_var.reset(token)

    def _route_matches(self, scope) -> bool:
        """Whether a route serves this method at this path (else the router answers 404 or 405, reading
        nothing of the request).

        The answer depends on the method and path only (the routes are fixed once the app is built), and a
        client posts to the same session's path again and again, so the last :data:`_ROUTE_ANSWERS_KEPT`
        answers are kept rather than matched against every route per request."""
        key = (scope.get("method"), scope.get("root_path", ""), scope.get("path", ""))
        answers = self._route_answers
        found = answers.get(key)
        if found is not None:
            answers.move_to_end(key)
            return found
        found = any(route.matches(scope)[0] == Match.FULL for route in self.routes)
        if len(key[1]) + len(key[2]) <= _ROUTE_PATH_KEPT:
            answers[key] = found
            if len(answers) > _ROUTE_ANSWERS_KEPT:
                answers.popitem(last=False)
        return found

    async def _read_body(self, declared: int | None, receive):
        """The whole body; None once it is over the limit (``declared`` by Content-Length, or as it streams);
        :data:`_GONE` when the connection ended before the body did (nothing is left to answer)."""
        if declared is not None and declared > self.max_body_bytes:
            return None
        chunks, received = [], 0
        while True:
            message = await receive()
            if message["type"] != "http.request":
                return _GONE
            chunk = message.get("body", b"")
            received += len(chunk)
            if received > self.max_body_bytes:
                return None
            chunks.append(chunk)
            if not message.get("more_body", False):
                break
        return b"".join(chunks)

    def _next_request_id(self) -> str:
        """Unique per process start and request; one urandom call per process, not per request."""
        return f"{self._id_prefix}{next(self._id_counter):016x}"

    async def _too_large(self, send, request_id):
        await _send_problem(send, 413, "body_too_large", f"request body exceeds {self.max_body_bytes} bytes",
                            request_id, [(b"connection", b"close")])


def _replay(body: bytes, receive):
    """A ``receive`` that gives the buffered body once, then waits on the real one (for the disconnect)."""
    sent = False

    async def replay():
        nonlocal sent
        if not sent:
            sent = True
            return {"type": "http.request", "body": body, "more_body": False}
        return await receive()

    return replay


class TokenBucket:
    """Per-client token buckets: ``rate`` tokens per second up to ``burst``, at most ``max_clients`` kept.

    The least recently seen client is dropped first when the table is full
    (it comes back with a full bucket: the worst an attacker who floods the
    table with clients gains is one burst per client it can really be).
    """

    def __init__(self, rate_per_s: float, burst: int, max_clients: int = 10_000, clock=time.monotonic):
        self.rate, self.burst, self.max_clients, self.clock = rate_per_s, burst, max_clients, clock
        self.buckets: OrderedDict[bytes, tuple[float, float]] = OrderedDict()

    def take(self, client: bytes) -> float:
        """Take one token; returns 0 when allowed, else the seconds until one is free."""
        now = self.clock()
        tokens, last = self.buckets.pop(client, (float(self.burst), now))
        tokens = min(float(self.burst), tokens + (now - last) * self.rate)
        allowed = tokens >= 1.0
        self.buckets[client] = (tokens - 1.0 if allowed else tokens, now)
        while len(self.buckets) > self.max_clients:
            self.buckets.popitem(last=False)
        return 0.0 if allowed else (1.0 - tokens) / self.rate
