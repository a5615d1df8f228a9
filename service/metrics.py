"""Prometheus metrics of one app, with prometheus_client.

Each app has its own registry (tests build many apps in one process). With
several server processes (``serve --workers N``), the CLI points
``PROMETHEUS_MULTIPROC_DIR`` at a fresh directory before the workers start;
prometheus_client then keeps every value in files there, and ``/metrics``
(answered by any one worker) sums them over all workers, so nothing is split
silently across processes.

Metric names (all ``passive_locator_`` + ...):

===================================  =========  ====================================================
requests_total                       counter    requests by method, route template and status
request_seconds                      histogram  request latency by method and route template
requests_in_flight                   gauge      requests being answered now
fixes_total                          counter    fixes by method and outcome (``ok`` or the error code)
batch_problems_total                 counter    problems received in batches
sessions_created_total               counter    sessions created
session_updates_total                counter    posts that applied at least one epoch
session_epochs_applied_total         counter    epochs applied
session_epochs_duplicate_total       counter    epochs acknowledged as duplicates (not applied)
session_report_posts_total           counter    network-session report posts that applied at least one report
session_reports_applied_total        counter    network-session reports applied
session_reports_duplicate_total      counter    network-session reports acknowledged as duplicates (not applied)
session_reports_late_total           counter    network-session reports older than the reorder window (not applied)
store_errors_total                   counter    session-store failures by operation
events_published_total               counter    session update events published to subscribers
tak_events_total                     counter    CoT events handed to the TAK feed, by outcome
tak_queue_dropped_total              counter    CoT events dropped because the TAK queue was full
build_info                           gauge      1, labelled with the version and Python
===================================  =========  ====================================================
"""

from __future__ import annotations

import collections
import importlib.metadata
import os
import platform

from prometheus_client import CollectorRegistry, Counter, Gauge, Histogram, disable_created_metrics, generate_latest
from prometheus_client import multiprocess

from core.estimators import REGISTRY as METHODS
from service.wire import requested_method

PREFIX = "passive_locator_"
CONTENT_TYPE = "text/plain; version=0.0.4; charset=utf-8"
_BUCKETS_S = (0.001, 0.0025, 0.005, 0.01, 0.025, 0.05, 0.1, 0.25, 0.5, 1.0, 2.5, 5.0, 10.0, 30.0)
_METHOD_LABELS = frozenset(["auto", *METHODS])

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
        self.fixes = counter("fixes", "Fixes requested, by method and outcome (ok, or the problem code)",
                             ("method", "outcome"))
        self.store_errors = counter("store_errors", "Session-store operations that failed, by operation",
                                    ("operation",))
        self.tak_events = counter("tak_events", "CoT events for the TAK feed, by outcome (sent, failed)",
                                  ("outcome",))
        self.tak_dropped = counter("tak_queue_dropped", "CoT events dropped because the TAK send queue was full")
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

    def fix(self, method, outcome: str, count: int = 1) -> None:
        """``count`` fixes (``outcome`` ``ok`` or a problem code); an unknown method name is counted as ``invalid``."""
        self.fixes.labels(method if method in _METHOD_LABELS else "invalid", outcome).inc(count)

    def batch_fixes(self, problems: list, results: list[dict]) -> None:
        """The fixes of a batch response: each slot's method and outcome (one increment per label pair)."""
        tally: collections.Counter = collections.Counter()
        for problem, result in zip(problems, results):
            if result["ok"]:
                tally[result["fix"]["method"], "ok"] += 1
            else:
                method = requested_method(problem)
                tally[method if isinstance(method, str) else None, result["error"]["code"]] += 1
        for (method, outcome), count in tally.items():
            self.fix(method, outcome, count)

    def render(self) -> bytes:
        """The text exposition (summed over workers in multiprocess mode)."""
        if self.multiprocess:
            registry = CollectorRegistry()
            multiprocess.MultiProcessCollector(registry)
            return generate_latest(registry)
        return generate_latest(self.registry)


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
