"""What only real server processes show: durability across SIGKILL, and concurrent posts across replicas."""

from __future__ import annotations

import threading

import httpx
import pytest

from .helpers import (Server, api_epochs, assert_close_bodies, batches, create_body, paper_track, post_batch,
                      post_from_clients, reference_run)

BATCH = 10


@pytest.fixture(scope="module")
def epochs() -> list[dict]:
    return api_epochs(paper_track(seed=2024, epochs=200))


@pytest.fixture(scope="module")
def reference(epochs) -> dict:
    return reference_run(epochs, BATCH)



def test_acknowledged_epochs_survive_sigkill(tmp_path, epochs, reference):
    store = f"sqlite:///{tmp_path}/s.db"
    with httpx.Client(timeout=30.0) as client:
        with Server(store, tmp_path / "uvicorn.log") as server:
            session_id = client.post(f"{server.url}/v1/sessions", json=create_body()).json()["id"]
            for batch in batches(epochs[:100], BATCH):
                acknowledged = post_batch(client, server.url, session_id, "measurements", batch)
            server.kill()
        assert acknowledged["updates"] == 100
        with Server(store, tmp_path / "uvicorn.log") as server:
            restored = client.get(f"{server.url}/v1/sessions/{session_id}").json()
            assert restored["updates"] == 100 and restored["version"] == acknowledged["version"]
            assert {k: v for k, v in restored.items()} == {k: v for k, v in acknowledged.items()
                                                           if k not in ("applied", "duplicates")}
            for batch in batches(epochs[100:], BATCH):
                post_batch(client, server.url, session_id, "measurements", batch)
            final = client.get(f"{server.url}/v1/sessions/{session_id}").json()
    assert final["updates"] == 200
    assert_close_bodies(final, reference, rtol=1e-9)


def test_a_kill_in_the_middle_of_traffic_loses_nothing_acknowledged(tmp_path, epochs, reference):
    """SIGKILL while a client posts as fast as it can; it resumes from its last acknowledged seq."""
    store = f"sqlite:///{tmp_path}/s.db"
    acknowledged_seq = []
    with httpx.Client(timeout=30.0) as client:
        server = Server(store, tmp_path / "uvicorn.log").start()
        session_id = client.post(f"{server.url}/v1/sessions", json=create_body()).json()["id"]
        killed = threading.Event()

        def stream():
            with httpx.Client(timeout=30.0) as own:
                for batch in batches(epochs, 2):
                    try:
                        body = post_batch(own, server.url, session_id, "measurements", batch)
                    except httpx.HTTPError:
                        return  # the kill: this post's fate is unknown
                    acknowledged_seq.append(body["last_seq"])
                    if len(acknowledged_seq) == 25:
                        killed.set()

        poster = threading.Thread(target=stream)
        poster.start()
        assert killed.wait(timeout=60)
        server.kill()
        poster.join(timeout=60)
        assert 25 <= len(acknowledged_seq) < 100
        with Server(store, tmp_path / "uvicorn.log") as server:
            restored = client.get(f"{server.url}/v1/sessions/{session_id}").json()
            assert restored["last_seq"] >= acknowledged_seq[-1]
            assert restored["updates"] == restored["last_seq"]
            resume = acknowledged_seq[-1]  # what the client knows; anything after may or may not have landed
            for batch in batches(epochs[resume:], BATCH):
                post_batch(client, server.url, session_id, "measurements", batch)
            final = client.get(f"{server.url}/v1/sessions/{session_id}").json()
    assert final["updates"] == 200
    assert_close_bodies(final, reference, rtol=1e-9)


@pytest.mark.parametrize("kind, processes", [
    ("sqlite", 1),
    ("sqlite", 2),
    pytest.param("redis", 2, marks=pytest.mark.redis),
])
def test_concurrent_clients_apply_every_epoch_exactly_once(request, tmp_path, epochs, reference, kind, processes):
    store = f"sqlite:///{tmp_path}/s.db" if kind == "sqlite" else request.getfixturevalue("redis_url")
    servers = [Server(store, tmp_path / f"uvicorn-{i}.log") for i in range(processes)]
    try:
        for server in servers:
            server.start()
        with httpx.Client(timeout=30.0) as client:
            session_id = client.post(f"{servers[0].url}/v1/sessions", json=create_body()).json()["id"]
        stream = batches(epochs, BATCH)
        results, failures = post_from_clients(servers, session_id, "measurements", stream, join_timeout_s=120)
        assert failures == []
        assert len(results) == 4 * len(stream)
        assert sum(r["applied"] for r in results) == len(epochs)
        assert sum(r["duplicates"] for r in results) == 3 * len(epochs)
        with httpx.Client(timeout=30.0) as client:
            final = client.get(f"{servers[-1].url}/v1/sessions/{session_id}").json()
    finally:
        for server in servers:
            server.kill()
    assert (final["updates"], final["last_seq"], final["version"]) == (len(epochs), len(epochs), 1 + len(stream))
    assert_close_bodies(final, reference, rtol=0.0)
