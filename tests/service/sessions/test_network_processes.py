"""Network sessions across real server processes: acknowledged reports survive SIGKILL and a restart continues
exactly; concurrent posts (across replicas) apply every report once; a store fault is a 503 that applies
nothing."""

from __future__ import annotations

import sqlite3

import httpx
import numpy as np
import pytest
from fastapi.testclient import TestClient

from core.simulation.network import SCENES, simulate_network
from service.app import create_app
from service.sessions.scene_requests import api_report, create_body
from service.settings import Settings

from .helpers import Server, batches, post_batch, post_from_clients

BATCH = 10
SCENE = SCENES["df_network"](duration_s=60.0)


@pytest.fixture(scope="module")
def reports() -> list[dict]:
    return [api_report(p) for p in simulate_network(SCENE, np.random.default_rng(77)).posted]


@pytest.fixture(scope="module")
def reference(reports) -> dict:
    """The final state of posting the reports in batches, in one process, no kill, no concurrency."""
    with TestClient(create_app(Settings(store="sqlite:///:memory:"))) as client:
        session_id = client.post("/v1/sessions", json=create_body(SCENE)).json()["id"]
        for batch in batches(reports, BATCH):
            assert client.post(f"/v1/sessions/{session_id}/reports", json={"reports": batch}).status_code == 200
        return client.get(f"/v1/sessions/{session_id}").json()


def _filter_view(body: dict) -> dict:
    return {k: body[k] for k in ("last_seq", "last_time_s", "updates", "tracks", "stations", "ended_tracks")}


def test_acknowledged_reports_survive_sigkill_and_the_restart_continues_exactly(tmp_path, reports, reference):
    store = f"sqlite:///{tmp_path}/s.db"
    half = len(reports) // 2 // BATCH * BATCH
    with httpx.Client(timeout=30.0) as client:
        with Server(store, tmp_path / "uvicorn.log") as server:
            session_id = client.post(f"{server.url}/v1/sessions", json=create_body(SCENE)).json()["id"]
            for batch in batches(reports[:half], BATCH):
                acknowledged = post_batch(client, server.url, session_id, "reports", batch)
            server.kill()
        with Server(store, tmp_path / "uvicorn.log") as server:
            restored = client.get(f"{server.url}/v1/sessions/{session_id}").json()
            assert restored == {k: v for k, v in acknowledged.items() if k not in ("applied", "duplicates", "late")}
            for batch in batches(reports[half:], BATCH):
                post_batch(client, server.url, session_id, "reports", batch)
            final = client.get(f"{server.url}/v1/sessions/{session_id}").json()
    assert _filter_view(final) == _filter_view(reference)


@pytest.mark.parametrize("kind, processes", [("sqlite", 2), pytest.param("redis", 2, marks=pytest.mark.redis)])
def test_concurrent_clients_apply_every_report_exactly_once(request, tmp_path, reports, reference, kind, processes):
    store = f"sqlite:///{tmp_path}/s.db" if kind == "sqlite" else request.getfixturevalue("redis_url")
    servers = [Server(store, tmp_path / f"uvicorn-{i}.log") for i in range(processes)]
    try:
        for server in servers:
            server.start()
        with httpx.Client(timeout=30.0) as client:
            session_id = client.post(f"{servers[0].url}/v1/sessions", json=create_body(SCENE)).json()["id"]
        stream = batches(reports, BATCH)
        results, failures = post_from_clients(servers, session_id, "reports", stream, join_timeout_s=180)
        assert failures == []
        assert sum(r["applied"] for r in results) == len(reports)
        assert sum(r["duplicates"] for r in results) == 3 * len(reports)
        with httpx.Client(timeout=30.0) as client:
            final = client.get(f"{servers[-1].url}/v1/sessions/{session_id}").json()
    finally:
        for server in servers:
            server.kill()
    assert final["version"] == 1 + len(stream)
    assert _filter_view(final) == _filter_view(reference)


def test_a_store_fault_is_a_503_and_applies_nothing(tmp_path, reports, monkeypatch):
    with TestClient(create_app(Settings(store=f"sqlite:///{tmp_path}/s.db"))) as client:
        session_id = client.post("/v1/sessions", json=create_body(SCENE)).json()["id"]
        backend = client.app.state.store.backend()

        def broken(*args, **kwargs):
            raise sqlite3.OperationalError("disk I/O error")

        monkeypatch.setattr(backend, "_swap", broken)
        response = client.post(f"/v1/sessions/{session_id}/reports", json={"reports": reports[:BATCH]})
        assert response.status_code == 503, response.text
        assert response.headers["content-type"] == "application/problem+json"
        assert int(response.headers["retry-after"]) >= 1
        monkeypatch.undo()
        state = client.get(f"/v1/sessions/{session_id}").json()
        assert (state["version"], state["updates"], state["tracks"]) == (1, 0, [])
        retried = client.post(f"/v1/sessions/{session_id}/reports", json={"reports": reports[:BATCH]})
        assert retried.status_code == 200 and retried.json()["applied"] == BATCH
