"""GET /metrics: parsed with prometheus_client's own parser, in one process and summed over workers."""

from __future__ import annotations

import asyncio
import importlib.metadata
import re
import sqlite3
import subprocess
import sys
import time

import httpx
import pytest
from fastapi.testclient import TestClient
from prometheus_client.parser import text_string_to_metric_families

from service.app import create_app
from service.ops import metrics
from service.settings import Settings
from tests.service.conftest import STATIONS_300KM, TARGET, bearing_request
from tests.service.sessions.helpers import REPO, free_port


def families(text: str) -> dict:
    return {family.name: family for family in text_string_to_metric_families(text)}


def sample(text: str, name: str, **labels) -> float | None:
    """The value of the sample ``name`` whose labels include ``labels`` (None when there is none)."""
    for family in text_string_to_metric_families(text):
        for s in family.samples:
            if s.name == name and all(s.labels.get(k) == v for k, v in labels.items()):
                return s.value
    return None


def test_every_metric_has_help_and_the_documented_names(client):
    text = client.get("/metrics").text
    found = families(text)
    assert all(family.documentation for family in found.values()), [n for n, f in found.items() if not f.documentation]
    expected = {"requests", "request_seconds", "requests_in_flight", "fixes", "fix_seconds", "batch_problems",
                "sessions_created", "sessions_live", "session_updates", "session_epochs_applied",
                "session_epochs_duplicate", "event_streams_open", "store_errors", "events_published", "tak_events",
                "tak_queue_dropped", "tak_connected", "tak_queue_events", "build_info"}
    assert {f"passive_locator_{name}" for name in expected} <= set(found)
    documented = set(re.findall(r"^(\w+) +(?:counter|gauge|histogram) ", metrics.__doc__, re.M))
    assert {name.removeprefix("passive_locator_") for name in found if name.startswith("passive_locator_")} \
        == {name.removesuffix("_total") for name in documented}
    assert sample(text, "passive_locator_build_info", version=importlib.metadata.version("passive-locator")) == 1
    assert sample(text, "passive_locator_requests_in_flight") == 1  # this request


@pytest.mark.skipif(not sys.platform.startswith("linux"), reason="prometheus_client reads /proc")
def test_process_metrics_describe_this_process(client):
    text = client.get("/metrics").text
    assert {"process_resident_memory_bytes", "process_cpu_seconds", "process_open_fds", "process_max_fds",
            "process_start_time_seconds"} <= set(families(text))
    assert sample(text, "process_resident_memory_bytes") > 10e6  # numpy, scipy and numba are loaded
    assert sample(text, "process_open_fds") >= 3


def test_counters_exist_at_zero_before_their_first_event(client):
    text = client.get("/metrics").text
    for method in ("auto", "ml", "eove", "invalid"):
        for outcome in ("ok", "invalid_input", "unobservable", "not_converged", "internal_error"):
            assert sample(text, "passive_locator_fixes_total", method=method, outcome=outcome) == 0, (method, outcome)
    assert sample(text, "passive_locator_fix_seconds_count", method="ml") == 0
    for operation in ("create", "get", "update", "check"):
        assert sample(text, "passive_locator_store_errors_total", operation=operation) == 0
    for outcome in ("sent", "failed"):
        assert sample(text, "passive_locator_tak_events_total", outcome=outcome) == 0
    for name in ("sessions_created_total", "batch_problems_total", "tak_queue_dropped_total", "event_streams_open",
                 "sessions_live", "tak_connected"):
        assert sample(text, f"passive_locator_{name}") == 0, name


def _parallel_bearings(**extra) -> dict:
    """Two bearings that never meet: ``auto`` reads it, runs ML, and ML finds it unobservable."""
    stations = [{"id": "a", "position": {"east_m": 0.0, "north_m": 0.0, "up_m": 0.0}},
                {"id": "b", "position": {"east_m": 1000.0, "north_m": 0.0, "up_m": 0.0}}]
    return {"frame": "local", "stations": stations, "constraints": {"altitude_m": 0.0}, **extra,
            "measurements": [{"type": "bearing", "station_id": s, "azimuth_deg": 0.0, "sigma_azimuth_deg": 1.0}
                             for s in ("a", "b")]}


def test_a_failed_auto_fix_counts_under_the_method_that_ran(client):
    answer = client.post("/v1/fixes", json=_parallel_bearings())
    assert answer.status_code == 422
    code = answer.json()["code"]
    assert client.post("/v1/fixes", json=bearing_request(STATIONS_300KM, TARGET)).status_code == 200
    batch = {"problems": [_parallel_bearings(), _parallel_bearings(method="ml"),
                          bearing_request(STATIONS_300KM, TARGET)]}
    assert [r["ok"] for r in client.post("/v1/fixes/batch", json=batch).json()["results"]] == [False, False, True]
    text = client.get("/metrics").text
    fixes = {(s.labels["method"], s.labels["outcome"]): s.value
             for s in families(text)["passive_locator_fixes"].samples if s.name == "passive_locator_fixes_total"}
    assert fixes[("ml", code)] == 3 and fixes[("ml", "ok")] == 2
    assert fixes[("auto", code)] == 0  # auto stood for ml: nothing is counted under the name that did not run
    assert {k for k, v in fixes.items() if v} == {("ml", code), ("ml", "ok")}
    # the latency histogram: the two single fixes (a batch's time is its request's), under the method that ran
    assert sample(text, "passive_locator_fix_seconds_count", method="ml") == 2
    assert sample(text, "passive_locator_fix_seconds_bucket", method="ml", le="+Inf") == 2
    assert sample(text, "passive_locator_fix_seconds_count", method="eove") == 0


def test_open_event_streams_are_a_gauge():
    from service.ops.metrics import Metrics
    from service.sessions.events import LocalBus

    found = Metrics()

    async def run():
        bus = LocalBus(found)
        first, second = bus.subscribe("s1"), bus.subscribe("s2")
        opened = found.event_streams._value.get()
        await first.aclose()
        await first.aclose()  # closing twice counts once
        after_one = found.event_streams._value.get()
        await second.aclose()
        return opened, after_one, found.event_streams._value.get()

    assert asyncio.run(run()) == (2, 1, 0)


def test_live_sessions_are_counted_in_the_background(client):
    from tests.service.sessions.helpers import create_body

    for _ in range(2):
        assert client.post("/v1/sessions", json=create_body(frame="wgs84")).status_code == 201
    deadline = time.monotonic() + 30
    while sample(client.get("/metrics").text, "passive_locator_sessions_live") != 2:
        assert time.monotonic() < deadline, "the live sessions were never counted"
        time.sleep(0.05)


def test_the_tak_link_is_a_gauge(monkeypatch, tmp_path):
    from tests.service.sessions.test_events_and_tak import Listener

    listener = Listener()
    monkeypatch.setenv("PASSIVE_LOCATOR_TAK_URL", f"tcp://127.0.0.1:{listener.port}")
    try:
        with TestClient(create_app(Settings(store=f"sqlite:///{tmp_path}/s.db"))) as client:
            assert sample(client.get("/metrics").text, "passive_locator_tak_connected") == 0
            fix = bearing_request(STATIONS_300KM, TARGET, cot={"uid": "tak-1"})
            assert client.post("/v1/fixes", json=fix).status_code == 200
            listener.events(1)
            deadline = time.monotonic() + 10
            while sample(client.get("/metrics").text, "passive_locator_tak_events_total", outcome="sent") != 1:
                assert time.monotonic() < deadline
                time.sleep(0.02)
            text = client.get("/metrics").text
            assert sample(text, "passive_locator_tak_connected") == 1
            assert sample(text, "passive_locator_tak_queue_events") == 0
    finally:
        listener.close()


def test_requests_latency_and_fixes_by_method_and_outcome(client):
    good = bearing_request(STATIONS_300KM, TARGET)
    unknown_station = bearing_request(STATIONS_300KM, TARGET)
    unknown_station["measurements"][0]["station_id"] = "rx-9"
    assert client.post("/v1/fixes", json=good).status_code == 200
    assert client.post("/v1/fixes", json=dict(good, method="eove")).status_code == 200
    assert client.post("/v1/fixes", json=unknown_station).status_code == 422
    batch = {"problems": [good, unknown_station, dict(good, method="not-a-method")]}
    assert client.post("/v1/fixes/batch", json=batch).status_code == 200
    text = client.get("/metrics").text
    assert sample(text, "passive_locator_requests_total", method="POST", path="/v1/fixes", status="200") == 2
    assert sample(text, "passive_locator_requests_total", method="POST", path="/v1/fixes", status="422") == 1
    assert sample(text, "passive_locator_request_seconds_count", method="POST", path="/v1/fixes") == 3
    assert sample(text, "passive_locator_fixes_total", method="ml", outcome="ok") == 2
    assert sample(text, "passive_locator_fixes_total", method="eove", outcome="ok") == 1
    code = client.post("/v1/fixes", json=unknown_station).json()["code"]
    text = client.get("/metrics").text
    assert sample(text, "passive_locator_fixes_total", method="auto", outcome=code) == 3
    assert sample(text, "passive_locator_fixes_total", method="invalid", outcome="invalid_input") == 1
    assert sample(text, "passive_locator_batch_problems_total") == 3


def test_store_errors_are_counted(client, monkeypatch):
    backend = client.app.state.store.backend()

    def broken(*args, **kwargs):
        raise sqlite3.OperationalError("disk I/O error")

    monkeypatch.setattr(backend, "get", broken)
    client.get("/v1/sessions/" + "0" * 32)
    assert sample(client.get("/metrics").text, "passive_locator_store_errors_total", operation="get") == 1


@pytest.mark.slow  # two server processes importing numpy and scipy: 5-20 s on a shared 2-core machine
def test_workers_share_their_metrics(tmp_path):
    """With --workers 2 the counts are summed over both processes, whichever one answers /metrics."""
    port = free_port()
    env = {"PASSIVE_LOCATOR_STORE": f"sqlite:///{tmp_path}/s.db", "PATH": "/usr/bin:/bin"}
    server = subprocess.Popen([sys.executable, "-m", "service.cli", "serve", "--port", str(port), "--workers", "2",
                               "--log-level", "warning"], cwd=REPO, env=env, stdout=subprocess.DEVNULL,
                              stderr=subprocess.DEVNULL)
    base = f"http://127.0.0.1:{port}"
    try:
        deadline = time.monotonic() + 180  # a bound on a hang, not a speed
        while time.monotonic() < deadline:
            try:
                if httpx.get(f"{base}/healthz", timeout=1).status_code == 200:
                    break
            except httpx.HTTPError:
                time.sleep(0.1)
        requests = 40
        for _ in range(requests):  # a new connection each time, so both workers answer some
            assert httpx.get(f"{base}/readyz", timeout=5).status_code == 200
        text = httpx.get(f"{base}/metrics", timeout=5).text
        assert sample(text, "passive_locator_requests_total", path="/readyz", status="200") == requests
    finally:
        server.terminate()
        server.wait(timeout=20)
