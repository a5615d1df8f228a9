"""The TAK feed: CoT events pushed to a TAK server (or any CoT listener) off the request path.

Configured by ``PASSIVE_LOCATOR_TAK_URL``: ``tcp://host:port`` (a TAK server's streaming input, 8087 by
convention), ``udp://host:port`` (one datagram per event, e.g. multicast SA 239.2.3.1:6969) or
``tls://host:port`` (8089) with ``PASSIVE_LOCATOR_TAK_CA_FILE`` and a client certificate
``PASSIVE_LOCATOR_TAK_CERT_FILE`` / ``PASSIVE_LOCATOR_TAK_KEY_FILE``. Unset: no feed.

What is sent: every fix whose request carries ``cot`` options, and every session update. A route only
puts the event on a bounded queue (``PASSIVE_LOCATOR_TAK_QUEUE_SIZE``); one sender thread per app
connects, sends and reconnects with backoff. When the queue is full the event is dropped and counted
(``passive_locator_tak_queue_dropped_total``), so a slow or absent TAK server never slows the API.

Plain sockets on a thread rather than pytak: the feed only writes whole events to one stream, which the
standard library does in a few lines, and the routes that enqueue are both sync and async.
"""

from __future__ import annotations

import logging
import queue
import socket
import ssl
import threading
from urllib.parse import urlsplit

from pydantic import Field, field_validator
from pydantic_settings import BaseSettings, SettingsConfigDict

logger = logging.getLogger("passive_locator")


class TakSettings(BaseSettings):
    """The TAK feed's settings (environment prefix ``PASSIVE_LOCATOR_TAK_``)."""

    model_config = SettingsConfigDict(env_prefix="PASSIVE_LOCATOR_TAK_", extra="ignore")

    url: str | None = Field(None, description="tcp://host:port, udp://host:port or tls://host:port; unset = no feed")
    ca_file: str | None = Field(None, description="tls: CA bundle that signed the TAK server's certificate")
    cert_file: str | None = Field(None, description="tls: this service's client certificate (PEM)")
    key_file: str | None = Field(None, description="tls: its private key (PEM)")
    queue_size: int = Field(1000, ge=1, le=1_000_000, description="events waiting to be sent; more are dropped")

    @field_validator("url")
    @classmethod
    def _scheme(cls, value):
        if value:
            parts = urlsplit(value)
            if parts.scheme not in ("tcp", "udp", "tls") or not parts.hostname or not parts.port:
                raise ValueError("PASSIVE_LOCATOR_TAK_URL must be tcp://, udp:// or tls://host:port")
        return value or None


class TakFeed:
    """A bounded queue of CoT events and the thread that sends them."""

    def __init__(self, settings: TakSettings, metrics):
        self.settings, self.metrics = settings, metrics
        parts = urlsplit(settings.url)
        self.scheme, self.address = parts.scheme, (parts.hostname, parts.port)
        self.queue: queue.Queue[bytes | None] = queue.Queue(maxsize=settings.queue_size)
        self._thread = threading.Thread(target=self._run, name="tak-feed", daemon=True)
        self._started = threading.Lock()
        self._stopping = threading.Event()

    def push(self, event: str | None) -> bool:
        """Queue one event (never blocks); False when it was dropped."""
        if event is None:
            return True
        if not self._thread.is_alive():
            with self._started:
                if not self._thread.is_alive() and not self._stopping.is_set():
                    self._thread.start()
        try:
            self.queue.put_nowait(event.encode())
            self.metrics.tak_queued.set(self.queue.qsize())
            return True
        except queue.Full:
            self.metrics.tak_dropped.inc()
            return False

    def close(self, timeout_s: float = 2.0) -> None:
        self._stopping.set()
        if self._thread.is_alive():
            try:
                self.queue.put_nowait(None)
            except queue.Full:
                pass
            self._thread.join(timeout_s)

    def _connect(self):
        if self.scheme == "udp":
            sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
            sock.connect(self.address)
            return sock
        sock = socket.create_connection(self.address, timeout=10.0)
        if self.scheme == "tls":
            context = ssl.create_default_context(cafile=self.settings.ca_file)
            if self.settings.cert_file:
                context.load_cert_chain(self.settings.cert_file, self.settings.key_file)
            sock = context.wrap_socket(sock, server_hostname=self.address[0])
        return sock

    def _run(self) -> None:
        sock, backoff_s, pending = None, 0.5, None
        while not self._stopping.is_set():
            event = pending if pending is not None else self.queue.get()
            self.metrics.tak_queued.set(self.queue.qsize())
            if event is None:
                break
            pending = event
            try:
                if sock is None:
                    sock = self._connect()
                    backoff_s = 0.5
                    self.metrics.tak_connected.set(1)
                if self.scheme == "udp":
                    sock.send(event)
                else:
                    sock.sendall(event)
                self.metrics.tak_events.labels("sent").inc()
                pending = None
            except OSError as error:
                self.metrics.tak_events.labels("failed").inc()
                logger.warning("TAK feed %s://%s:%s: %s; retrying in %.1f s", self.scheme, *self.address, error,
                               backoff_s)
                if sock is not None:
                    sock.close()
                    sock = None
                self.metrics.tak_connected.set(0)
                self._stopping.wait(backoff_s)
                backoff_s = min(backoff_s * 2.0, 30.0)
        if sock is not None:
            sock.close()
        self.metrics.tak_connected.set(0)


def feed(app) -> TakFeed | None:
    """The app's TAK feed (None when no URL is configured), made on first use."""
    found = getattr(app.state, "tak_feed", False)
    if found is False:
        settings = getattr(app.state, "tak_settings", None) or TakSettings()
        found = TakFeed(settings, app.state.metrics) if settings.url else None
        app.state.tak_feed = found
    return found


def close(app, timeout_s: float = 2.0) -> None:
    """Stop the app's TAK sender thread, if one was made (at shutdown: queued events not yet sent are dropped)."""
    found = getattr(app.state, "tak_feed", None)
    if found:
        found.close(timeout_s)


def push(app, event: str | None) -> None:
    """Queue a CoT event for the app's TAK feed, if it has one."""
    target = feed(app)
    if target is not None:
        target.push(event)


def push_fix(app, body: dict, options) -> None:
    """A fix whose request carried ``cot`` options (``options``: its :class:`service.renderings.points.Renderings`)."""
    target = feed(app)
    if target is not None and getattr(options, "cot", None) is not None:
        from service.renderings.points import fix_cot

        target.push(body.get("cot") or fix_cot(body, options))


def push_batch(app, problems: list, results: list[dict]) -> None:
    """The solved fixes of a batch whose problems carried ``cot`` options."""
    target = feed(app)
    if target is None:
        return
    from service.renderings.points import fix_cot, problem_renderings

    for result in results:
        problem = problems[result["index"]]
        if result["ok"] and isinstance(problem, dict) and problem.get("cot") is not None:
            target.push(result["fix"].get("cot") or fix_cot(result["fix"], problem_renderings(problem)))


def push_session(app, state: dict, cot_options) -> None:
    """A session's new state, as its CoT track event."""
    target = feed(app)
    if target is not None:
        from service.renderings.points import session_cot

        target.push(session_cot(state, cot_options))
