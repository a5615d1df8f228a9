"""GET /metrics: parsed with prometheus_client's own parser, in one process and summed over workers."""

from __future__ import annotations

import importlib.metadata
import sqlite3
import subprocess
import sys
import time

import httpx
import pytest
from prometheus_client.parser import text_string_to_metric_families

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
    expected = {"requests", "request_seconds", "requests_in_flight", "fixes", "batch_problems", "sessions_created",
                "session_updates", "session_epochs_applied", "session_epochs_duplicate", "store_errors",
                "events_published", "tak_events", "tak_queue_dropped", "build_info"}
    assert {f"passive_locator_{name}" for name in expected} <= set(found)
    assert sample(text, "passive_locator_build_info", version=importlib.metadata.version("passive-locator")) == 1
    assert sample(text, "passive_locator_requests_in_flight") == 1  # this request


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
        deadline = time.monotonic() + 60
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
