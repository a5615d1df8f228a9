"""Prometheus metrics of one app, with prometheus_client.

Each app has its own registry (tests build many apps in one process). With
several server processes (``serve --workers N``), the CLI points
``PROMETHEUS_MULTIPROC_DIR`` at a fresh directory before the workers start;
prometheus_client then keeps every value in files there, and ``/metrics``
(answered by any one worker) sums them over all workers, so nothing is split
silently across processes. The process metrics (``process_*``: resident
memory, CPU seconds, open files) describe one process, so they are given in
single-process mode only (one worker per pod or container is the deployed
shape).

Every labelled series whose label values are known in advance exists at 0
from the start (a rate or an alert over it works before the first event).

Metric names (all ``passive_locator_`` + ..., apart from ``process_*``):

===================================  =========  ====================================================
requests_total                       counter    requests by method, route template and status
request_seconds                      histogram  request latency by method and route template
requests_in_flight                   gauge      requests being answered now
fixes_total                          counter    fixes by method and outcome (``ok`` or the error code)
fix_seconds                          histogram  single fixes, submission to result, by method
batch_problems_total                 counter    problems received in batches
sessions_created_total               counter    sessions created
sessions_live                        gauge      unexpired sessions in the store (counted in the background)
session_updates_total                counter    posts that applied at least one epoch
session_epochs_applied_total         counter    epochs applied
session_epochs_duplicate_total       counter    epochs acknowledged as duplicates (not applied)
event_streams_open                   gauge      session event streams open now
session_report_posts_total           counter    network-session report posts that applied at least one report
session_reports_applied_total        counter    network-session reports applied
session_reports_duplicate_total      counter    network-session reports acknowledged as duplicates (not applied)
session_reports_late_total           counter    network-session reports older than the reorder window (not applied)
store_errors_total                   counter    session-store failures by operation
events_published_total               counter    session update events published to subscribers
tak_events_total                     counter    CoT events handed to the TAK feed, by outcome
tak_queue_dropped_total              counter    CoT events dropped because the TAK queue was full
evaluation_chunks_total              counter    chunks of evaluation trials run
evaluations_running                  gauge      evaluations holding a CPU-pool worker now
tak_connected                        gauge      1 while the TAK feed holds a connection (or UDP socket)
tak_queue_events                     gauge      CoT events waiting to be sent
build_info                           gauge      1, labelled with the version and Python
process_*                            various    prometheus_client's process collector (Linux)
===================================  =========  ====================================================

The ``method`` of ``fixes_total`` and ``fix_seconds`` is the estimator that
ran (``auto`` resolved to the method it stood for), whatever the outcome; a
request refused before any method ran (invalid input) is counted under the
method it asked for, ``invalid`` when that is no method.
"""

from __future__ import annotations

import asyncio
import collections
import importlib.metadata
import logging
import os
import platform
import time

from prometheus_client import (CollectorRegistry, Counter, Gauge, Histogram, ProcessCollector,
                               disable_created_metrics, generate_latest)
from prometheus_client import multiprocess

from core.errors import LocalizationError
from core.estimators import REGISTRY as METHODS

logger = logging.getLogger("passive_locator")

PREFIX = "passive_locator_"
CONTENT_TYPE = "text/plain; version=0.0.4; charset=utf-8"
_BUCKETS_S = (0.001, 0.0025, 0.005, 0.01, 0.025, 0.05, 0.1, 0.25, 0.5, 1.0, 2.5, 5.0, 10.0, 30.0)
_METHOD_LABELS = frozenset(["auto", *METHODS])
#: Store operations counted in ``store_errors_total`` (the GuardedStore names a call by its function).
_STORE_OPERATIONS = ("create", "get", "page", "update", "delete", "check", "publish", "count_live")
#: Seconds between two background counts of the live sessions (a scrape starts one when the last is older).
LIVE_SESSIONS_EVERY_S = 15.0


def _error_codes() -> list[str]:
    """Every problem code a fix can end with: the core's failures, and the service's own."""
    codes, todo = set(), [LocalizationError]
    while todo:
        cls = todo.pop()
        codes.add(cls.code)
        todo.extend(cls.__subclasses__())
    return sorted(codes | {"invalid_input", "over_limit", "internal_error"})

disable_created_metrics()  # the *_created series would double the exposition for nothing a dashboard uses


def multiprocess_dir() -> str | None:
    """The shared directory of multiprocess mode, when the server runs several workers."""
    return os.environ.get("PROMETHEUS_MULTIPROC_DIR") or None


class Metrics:
    """The service's metrics; :meth:`render` gives the Prometheus text exposition."""

    def __init__(self):
        self.registry = CollectorRegistry(auto_describe=True)
        self.multiprocess = multiprocess_dir() is not None
        r = self.registry

        def counter(name, documentation, labels=()):
            return Counter(PREFIX + name, documentation, labels, registry=r)

        self.requests = counter("requests", "HTTP requests answered, by method, route template and status",
                                ("method", "path", "status"))
        self.latency = Histogram(PREFIX + "request_seconds", "Time to answer a request, by method and route template",
                                 ("method", "path"), buckets=_BUCKETS_S, registry=r)
        self.in_flight = Gauge(PREFIX + "requests_in_flight", "HTTP requests being answered now",
                               registry=r, multiprocess_mode="livesum")
        self.fixes = counter("fixes", "Fixes requested, by the method that ran (auto resolved; the requested "
                                      "one when refused before solving) and outcome (ok, or the problem code)",
                             ("method", "outcome"))
        self.fix_latency = Histogram(PREFIX + "fix_seconds", "Single fixes (POST /v1/fixes), from submission to "
                                                             "result (queue and solve), by the method that ran",
                                     ("method",), buckets=_BUCKETS_S, registry=r)
        self.store_errors = counter("store_errors", "Session-store operations that failed, by operation",
                                    ("operation",))
        self.tak_events = counter("tak_events", "CoT events for the TAK feed, by outcome (sent, failed)",
                                  ("outcome",))
        self.tak_dropped = counter("tak_queue_dropped", "CoT events dropped because the TAK send queue was full")
        self.tak_connected = Gauge(PREFIX + "tak_connected", "1 while the TAK feed holds a connection (UDP: a "
                                                             "socket), else 0", registry=r, multiprocess_mode="max")
        self.tak_queued = Gauge(PREFIX + "tak_queue_events", "CoT events waiting to be sent to TAK", registry=r,
                                multiprocess_mode="livesum")
        self.event_streams = Gauge(PREFIX + "event_streams_open", "Session event streams (server-sent events) "
                                                                  "open now", registry=r, multiprocess_mode="livesum")
        self.sessions_live = Gauge(PREFIX + "sessions_live", "Unexpired sessions in the store, as last counted "
                                                             "(in the background, at most every "
                                                             f"{LIVE_SESSIONS_EVERY_S:g} s, started by a scrape)",
                                   registry=r, multiprocess_mode="mostrecent")
        self.evaluation_chunks = counter("evaluation_chunks", "Chunks of evaluation trials run (an evaluation "
                                                              "checks between chunks whether to stop)")
        self.evaluations_running = Gauge(PREFIX + "evaluations_running", "Evaluations holding a CPU-pool worker "
                                                                         "now", registry=r,
                                         multiprocess_mode="livesum")
        self._counting: asyncio.Task | None = None
        self._counted_at = -float("inf")
        for method in sorted(_METHOD_LABELS | {"invalid"}):
            for outcome in ["ok", *_error_codes()]:
                self.fixes.labels(method, outcome)
        for method in sorted(METHODS):
            self.fix_latency.labels(method)
        for operation in _STORE_OPERATIONS:
            self.store_errors.labels(operation)
        for outcome in ("sent", "failed"):
            self.tak_events.labels(outcome)
        if not self.multiprocess:
            ProcessCollector(registry=r)
        self._counters = {
            "batch_problems_total": counter("batch_problems", "Problems received in fix batches"),
            "sessions_created_total": counter("sessions_created", "Sessions created"),
            "session_updates_total": counter("session_updates", "Measurement posts that applied at least one epoch"),
            "session_epochs_applied_total": counter("session_epochs_applied", "Session epochs applied"),
            "session_epochs_duplicate_total": counter("session_epochs_duplicate",
                                                      "Session epochs acknowledged as duplicates, not applied"),
            "session_report_posts_total": counter("session_report_posts",
                                                  "Network-session report posts that applied at least one report"),
            "session_reports_applied_total": counter("session_reports_applied", "Network-session reports applied"),
            "session_reports_duplicate_total": counter("session_reports_duplicate", "Network-session reports "
                                                       "acknowledged as duplicates, not applied"),
            "session_reports_late_total": counter("session_reports_late", "Network-session reports older than the "
                                                  "reorder window: counted, not applied"),
            "events_published_total": counter("events_published", "Session update events published"),
        }
        build = Gauge(PREFIX + "build_info", "Always 1: the running version and Python", ("version", "python"),
                      registry=r, multiprocess_mode="max")
        build.labels(_version(), platform.python_version()).set(1)

    def observe(self, method: str, path: str, status: int, seconds: float) -> None:
        """One answered request."""
        self.requests.labels(method, path, str(status)).inc()
        self.latency.labels(method, path).observe(seconds)

    def count(self, name: str, amount: float = 1.0) -> None:
        """Add to one of the unlabelled counters, by its exposed name (e.g. ``sessions_created_total``)."""
        if amount:
            self._counters[name].inc(amount)

    def fixes_done(self, methods: list, results: list[dict], seconds: list[float] | None = None) -> None:
        """Count fix results under the method each ran with, and observe their latency when given.

        Parameters
        ----------
        methods : list of str, length N
            The method of each result (``service.fixes.pipeline.fix_results``' ``methods_run``); a name that is
            no method is counted as ``invalid``.
        results : list of dict, length N
            ``{"ok": True, ...}`` or ``{"ok": False, "error": problem body}``.
        seconds : list of float, length N, optional
            Each single fix's time from submission to result.
        """
        tally: collections.Counter = collections.Counter()
        for method, result in zip(methods, results):
            tally[_label(method), "ok" if result["ok"] else result["error"]["code"]] += 1
        for (method, outcome), count in tally.items():
            self.fixes.labels(method, outcome).inc(count)
        if seconds is not None:
            for method, elapsed in zip(methods, seconds):
                self.fix_latency.labels(_label(method)).observe(elapsed)

    def refresh_live_sessions(self, store) -> None:
        """Start counting the store's live sessions on its threads, unless a count is running or recent.

        A scrape never waits for the store (``/metrics`` answers on the event loop): it shows the last count.
        """
        now = time.monotonic()
        if (self._counting is not None and not self._counting.done()) or now - self._counted_at < LIVE_SESSIONS_EVERY_S:
            return
        self._counted_at = now

        def count_live(backend) -> int:
            return backend.count_live()

        async def count() -> None:
            try:
                self.sessions_live.set(await store.run(count_live))
            except Exception as error:  # a store that is down keeps the last count (and counts a store error)
                logger.debug("live sessions not counted: %s", error)

        self._counting = asyncio.get_running_loop().create_task(count())

    def render(self) -> bytes:
        """The text exposition (summed over workers in multiprocess mode)."""
        if self.multiprocess:
            registry = CollectorRegistry()
            multiprocess.MultiProcessCollector(registry)
            return generate_latest(registry)
        return generate_latest(self.registry)


def _label(method) -> str:
    return method if type(method) is str and method in _METHOD_LABELS else "invalid"


def _version() -> str:
    try:
        return importlib.metadata.version("passive-locator")
    except importlib.metadata.PackageNotFoundError:
        return "unknown"


class InFlight:
    """ASGI middleware: the requests-in-flight gauge (outermost, so it counts every HTTP request)."""

    def __init__(self, app, metrics: Metrics):
        self.app, self.metrics = app, metrics

    async def __call__(self, scope, receive, send):
        if scope["type"] != "http":
            await self.app(scope, receive, send)
            return
        gauge = self.metrics.in_flight
        gauge.inc()
        try:
            await self.app(scope, receive, send)
        finally:
            gauge.dec()
