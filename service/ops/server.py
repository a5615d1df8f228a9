"""The HTTP server's own limits: how long a request may take to arrive, and how many connections are held.

uvicorn closes a kept-alive connection that stays idle, but nothing bounds a request that is arriving:
headers sent a byte at a time, or a declared body that never comes, held their connection (and its file
descriptor and buffers) for ever, and nothing bounded how many such connections one process holds. So the
service runs uvicorn's httptools protocol with, per connection:

- a header deadline (``header_timeout_s``): a request's line and headers must be complete this long after
  the connection opens or the idle connection receives its first byte, and may not exceed
  :data:`MAX_HEADER_BYTES`;
- a body deadline (``body_timeout_s``): the whole body must be in this long after the headers;

either missed is a 408 problem+json and the connection closed (the route waiting for the body sees the
client gone). And per process, a bound on open connections (``max_connections``): one more than that makes
room by closing the connection that has waited longest for a client that has not finished its request (or
an idle kept-alive one), with a 503 ``too_many_connections``; only when every connection is busy with a
request being served is the new one refused so. A flood of slow connections thus costs at most
``max_connections`` descriptors, each for at most a deadline, and cannot lock out a new client (an
orchestrator's ``/healthz``) for longer than it takes to connect.

The limits are read from the environment (:class:`service.settings.Settings`) once per process, so every
worker that uvicorn starts applies them.
"""

from __future__ import annotations

import asyncio
import functools
from typing import NamedTuple

import orjson
from uvicorn.protocols.http.httptools_impl import HttpToolsProtocol

from service.web.problems import MEDIA_TYPE, problem_body

#: Largest request line plus headers (bytes): beyond it a 431, whatever the deadline.
MAX_HEADER_BYTES = 64 * 1024

_REASONS = {400: b"Bad Request", 408: b"Request Timeout", 431: b"Request Header Fields Too Large", 503: b"Service Unavailable"}


class Limits(NamedTuple):
    header_timeout_s: float
    body_timeout_s: float
    max_connections: int


@functools.cache
def limits() -> Limits:
    """This process's limits, from the environment (read once)."""
    from service.settings import Settings

    settings = Settings()
    return Limits(settings.header_timeout_s, settings.body_timeout_s, settings.max_connections)


def _problem(status: int, code: str, detail: str, retry_after: bool = False) -> bytes:
    """A whole HTTP/1.1 problem+json response that closes the connection (written without a request cycle)."""
    body = orjson.dumps(problem_body(status, code, detail))
    head = [b"HTTP/1.1 %d %s" % (status, _REASONS[status]), b"content-type: " + MEDIA_TYPE.encode(),
            b"content-length: %d" % len(body), b"connection: close"]
    if retry_after:
        head.append(b"retry-after: 1")
    return b"\r\n".join(head) + b"\r\n\r\n" + body


class BoundedHttpToolsProtocol(HttpToolsProtocol):
    """uvicorn's httptools protocol with the header and body deadlines and the connection bound above."""

    def __init__(self, *args, **kwargs):
        super().__init__(*args, **kwargs)
        self._limits = limits()
        self._phase: str | None = None  # "headers" or "body" while a request is arriving
        self._timer: asyncio.TimerHandle | None = None
        self._header_bytes = 0
        #: Loop time since which this connection has waited for its client (eviction takes the oldest).
        self._waiting_since = 0.0

    # the request's arrival
    def connection_made(self, transport) -> None:
        super().connection_made(transport)
        if len(self.connections) > self._limits.max_connections and not self._make_room():
            self._close_with(_problem(503, "too_many_connections", "the server holds as many connections as it "
                                      "may; retry", retry_after=True))
            return
        self._wait("headers")

    def data_received(self, data: bytes) -> None:
        if self._phase is None and (self.cycle is None or self.cycle.response_complete):
            self._wait("headers")  # the first bytes of a request on a kept-alive connection
        counting = self._phase == "headers"
        super().data_received(data)
        if counting and self._phase == "headers":  # still in the headers after this read
            self._header_bytes += len(data)
            if self._header_bytes > MAX_HEADER_BYTES:
                self._close_with(_problem(431, "headers_too_large",
                                          f"the request line and headers exceed {MAX_HEADER_BYTES} bytes"))

    def send_400_response(self, msg: str) -> None:
        """A request the parser refuses: problem+json like every other error (uvicorn's is plain text)."""
        self._close_with(_problem(400, "malformed_request", f"not an HTTP/1.1 request: {msg}"))

    def on_headers_complete(self) -> None:
        super().on_headers_complete()
        self._wait("body")  # on_message_complete ends it at once for a request without a body

    def on_message_complete(self) -> None:
        super().on_message_complete()
        self._stop_waiting()

    def on_response_complete(self) -> None:
        super().on_response_complete()
        self._waiting_since = self.loop.time()

    def connection_lost(self, exc) -> None:
        self._stop_waiting()
        super().connection_lost(exc)

    # deadlines
    def _wait(self, phase: str) -> None:
        self._stop_waiting()
        self._phase, self._header_bytes = phase, 0
        self._waiting_since = self.loop.time()
        seconds = self._limits.header_timeout_s if phase == "headers" else self._limits.body_timeout_s
        self._timer = self.loop.call_later(seconds, self._timed_out)

    def _stop_waiting(self) -> None:
        if self._timer is not None:
            self._timer.cancel()
        self._timer, self._phase = None, None

    def _timed_out(self) -> None:
        phase, seconds = self._phase, (self._limits.header_timeout_s if self._phase == "headers"
                                       else self._limits.body_timeout_s)
        self._timer = None
        self._close_with(_problem(408, "request_timeout", f"the request's {phase} did not arrive within "
                                  f"{seconds:g} s ({phase[:-1] if phase == 'headers' else phase}_timeout_s)"))

    def _close_with(self, response: bytes) -> None:
        """Answer ``response`` unless a response has begun, tell a waiting route the client is gone, close."""
        self._stop_waiting()
        if self.transport.is_closing():
            return
        cycle = self.cycle
        if cycle is None or not cycle.response_started or cycle.response_complete:
            self.transport.write(response)
        if cycle is not None and not cycle.response_complete:
            cycle.disconnected = True
            cycle.message_event.set()
        self.transport.close()

    # the bound
    def _make_room(self) -> bool:
        """Close the connection that has waited longest for its client (arriving or idle); False when every
        other connection is serving a request."""
        waiting = [c for c in self.connections if c is not self and isinstance(c, BoundedHttpToolsProtocol)
                   and not c.transport.is_closing() and c._waiting_for_client()]
        if not waiting:
            return False
        oldest = min(waiting, key=lambda c: c._waiting_since)
        oldest._close_with(_problem(503, "too_many_connections", "closed to make room for another connection "
                                    "(this one had not sent a whole request); retry", retry_after=True))
        return True

    def _waiting_for_client(self) -> bool:
        """Whether the connection waits for its client: a request arriving, or idle between requests."""
        return self._phase is not None or self.cycle is None or self.cycle.response_complete
