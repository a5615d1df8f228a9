"""What a store's process keeps between calls: the record cache (validated by version against the backend, so
another process's write is seen), the decoded states of network sessions (equal to a fresh decode of what was
stored), and SQLite's group commit (one transaction for the writes queued together, each with its own outcome,
and none applied when the transaction fails)."""

from __future__ import annotations

import sqlite3
import threading
from contextlib import contextmanager

import numpy as np
import pytest
from fastapi.testclient import TestClient

from core.simulation.network import SCENES, simulate_network
from core.tracking.network import NetworkState
from service.app import create_app
from service.sessions import network as network_sessions
from service.sessions.records import decoded_states
from service.settings import Settings
from service.stores import open_store
from service.stores.sqlite import SqliteStore

from .network_scenes import api_report, create_body
from .test_stores import bump, make_record


def test_a_write_through_another_instance_is_seen_by_a_read_and_an_update(store_url, clock):
    """Two instances of one store (two processes or replicas): each caches what it read, and a write of the
    other is what it reads and changes next, never its cached record."""
    first, second = open_store(store_url, clock=clock), open_store(store_url, clock=clock)
    first.create(make_record("0001", now=clock()))
    assert first.get("alice", "0001").state["n"] == 0  # cached by the first
    second.update("alice", "0001", bump)
    seen = first.get("alice", "0001")
    assert (seen.version, seen.state["n"]) == (2, 1)
    assert first.update("alice", "0001", bump).state["n"] == 2  # changed from the other's write
    assert (second.get("alice", "0001").version, second.get("alice", "0001").state["n"]) == (3, 2)
    second.delete("alice", "0001")
    assert first.get("alice", "0001") is None
    for s in (first, second):
        s.close()


def test_an_update_decided_on_a_record_another_instance_moved_on_from_is_decided_again(store_url, clock):
    """An update starts from the cached record without reading the backend: a change that refuses it (as a
    stale If-Match would) or writes nothing is decided again on the latest record, not answered from the
    cache; a session the other instance deleted is gone."""
    first, second = open_store(store_url, clock=clock), open_store(store_url, clock=clock)
    first.create(make_record("0001", now=clock()))
    second.update("alice", "0001", bump)  # the first's cache still holds version 1
    seen = []

    def only_at_version_2(record):
        seen.append(record.version)
        if record.version != 2:
            raise ValueError(f"precondition: at version {record.version}")
        return bump(record)

    assert first.update("alice", "0001", only_at_version_2).version == 3
    assert seen == [1, 2]
    second.update("alice", "0001", bump)
    unchanged = first.update("alice", "0001", lambda record: None)
    assert (unchanged.version, unchanged.state["n"]) == (4, 3)
    with pytest.raises(ValueError):  # on the current record, the change's own refusal stands
        first.update("alice", "0001", only_at_version_2)
    second.delete("alice", "0001")
    assert first.update("alice", "0001", bump) is None
    for s in (first, second):
        s.close()


def test_a_cached_record_is_not_served_to_another_owner_nor_after_it_expired(store, clock):
    store.create(make_record("0001", now=clock(), ttl_s=10.0))
    assert store.get("alice", "0001") is not None
    assert store.get("bob", "0001") is None
    clock.advance(11.0)
    assert store.get("alice", "0001") is None


class _WatchedConnection:
    """A connection whose ``COMMIT`` statements are counted, and fail while ``failing`` is set (as on a full
    disk)."""

    def __init__(self, db: sqlite3.Connection, failing: threading.Event):
        self.db, self.failing, self.commits = db, failing, 0

    def execute(self, sql: str, *args):
        if sql == "COMMIT":
            self.commits += 1
            if self.failing.is_set():
                raise sqlite3.OperationalError("database or disk is full")
        return self.db.execute(sql, *args)

    def __getattr__(self, name):
        return getattr(self.db, name)


def _grouped(tmp_path, count: int, failing: threading.Event | None = None):
    """``count`` sessions updated by ``count`` threads that queue while the test holds the write turn, so that
    they are written together once it lets go (their COMMIT failing while ``failing`` is set); the store, the
    wrapped connections and each thread's error."""
    failing = failing or threading.Event()
    store = SqliteStore(str(tmp_path / "s.db"), busy_timeout_s=20.0)
    for k in range(count):
        store.create(make_record(f"{k:04d}", now=store.now(), ttl_s=1e6))
    wrapped: dict[int, _WatchedConnection] = {}
    opened = store._db

    @contextmanager
    def watched_db():
        with opened() as db:
            yield wrapped.setdefault(id(db), _WatchedConnection(db, failing))

    store._db = watched_db
    errors: dict[int, BaseException | None] = {}

    def work(k):
        try:
            store.update("alice", f"{k:04d}", bump)
            errors[k] = None
        except BaseException as error:  # each thread's outcome is asserted below
            errors[k] = error

    threads = [threading.Thread(target=work, args=(k,)) for k in range(count)]
    with opened() as db, store._write(db):
        for t in threads:
            t.start()
        while len(store._turns._queue) < count:  # every thread's write waits for the turn the test holds
            threading.Event().wait(0.01)
    for t in threads:
        t.join(30)
    return store, wrapped, errors


def test_writes_queued_together_are_committed_in_one_transaction_each_with_its_outcome(tmp_path):
    store, wrapped, errors = _grouped(tmp_path, 6)
    assert errors == dict.fromkeys(range(6))
    assert [store.get("alice", f"{k:04d}").state["n"] for k in range(6)] == [1] * 6
    assert sum(c.commits for c in wrapped.values()) == 1  # one leader wrote the six in one transaction
    fresh = SqliteStore(str(tmp_path / "s.db"))
    assert [fresh.get("alice", f"{k:04d}").version for k in range(6)] == [2] * 6
    for s in (store, fresh):
        s.close()


def test_a_failed_commit_fails_every_write_of_its_group_and_applies_none(tmp_path):
    count, failing = 6, threading.Event()
    failing.set()
    store, _, errors = _grouped(tmp_path, count, failing)
    assert sorted(type(e).__name__ for e in errors.values()) == ["OperationalError"] * count
    assert len({id(e) for e in errors.values()}) == count  # each thread raised its own
    failing.clear()
    fresh = SqliteStore(str(tmp_path / "s.db"))
    assert [(fresh.get("alice", f"{k:04d}").version, fresh.get("alice", f"{k:04d}").state["n"])
            for k in range(count)] == [(1, 0)] * count
    assert store.update("alice", "0000", bump).state["n"] == 1  # the store writes again once the fault is gone
    for s in (store, fresh):
        s.close()


def test_a_write_that_fails_alone_is_rolled_back_alone(tmp_path):
    """A create of a taken id queued with updates of other sessions: it fails, they are written."""
    store = SqliteStore(str(tmp_path / "s.db"), busy_timeout_s=20.0)
    for k in range(3):
        store.create(make_record(f"{k:04d}", now=store.now(), ttl_s=1e6))
    outcomes: dict[str, object] = {}

    def update(k):
        outcomes[f"update {k}"] = store.update("alice", f"{k:04d}", bump).state["n"]

    def create_taken():
        try:
            store.create(make_record("0001", now=store.now(), ttl_s=1e6))
            outcomes["create"] = "created"
        except sqlite3.IntegrityError as error:
            outcomes["create"] = type(error).__name__

    threads = [threading.Thread(target=update, args=(0,)), threading.Thread(target=create_taken),
               threading.Thread(target=update, args=(2,))]
    with store._db() as db, store._write(db):
        for t in threads:
            t.start()
        while len(store._turns._queue) < len(threads):
            threading.Event().wait(0.01)
    for t in threads:
        t.join(30)
    assert outcomes == {"update 0": 1, "create": "IntegrityError", "update 2": 1}
    assert store.get("alice", "0001").version == 1
    store.close()


SCENE = SCENES["df_network"](duration_s=40.0)


def test_the_state_a_post_leaves_in_memory_equals_the_one_decoded_after_a_restart(tmp_path):
    """The decoded state a post keeps for the next one is the state a restarted process reads from the
    store: the cache changes where a post starts from, never what it computes."""
    url = f"sqlite:///{tmp_path}/s.db"
    reports = [api_report(p) for p in simulate_network(SCENE, np.random.default_rng(5)).posted]
    with TestClient(create_app(Settings(store=url))) as client:
        session_id = client.post("/v1/sessions", json=create_body(SCENE)).json()["id"]
        for start in range(0, len(reports), 7):
            response = client.post(f"/v1/sessions/{session_id}/reports", json={"reports": reports[start:start + 7]})
            assert response.status_code == 200, response.text
        record = client.app.state.store.backend().get("anonymous", session_id)
        in_memory = decoded_states.get(record, network_sessions.core_state)
        body = client.get(f"/v1/sessions/{session_id}").json()
    restarted = open_store(url)
    stored = restarted.get("anonymous", session_id)
    assert stored.version == record.version
    from_store = NetworkState.from_dict(stored.state["core"])
    assert from_store == in_memory
    assert len(in_memory.tracks) >= 1
    assert network_sessions.state_body(stored, state=from_store)["tracks"] == body["tracks"]
    restarted.close()


def test_a_network_post_after_another_process_wrote_starts_from_that_write(tmp_path):
    """Two apps on one SQLite file (two processes' worth of caches): posts alternate between them, and the
    session ends where one app posting everything ends."""
    url = f"sqlite:///{tmp_path}/s.db"
    reports = [api_report(p) for p in simulate_network(SCENE, np.random.default_rng(6)).posted]
    with TestClient(create_app(Settings(store="sqlite:///:memory:"))) as alone:
        alone_id = alone.post("/v1/sessions", json=create_body(SCENE)).json()["id"]
        for start in range(0, len(reports), 5):
            assert alone.post(f"/v1/sessions/{alone_id}/reports",
                              json={"reports": reports[start:start + 5]}).status_code == 200
        expected = alone.get(f"/v1/sessions/{alone_id}").json()
    with TestClient(create_app(Settings(store=url))) as a, TestClient(create_app(Settings(store=url))) as b:
        session_id = a.post("/v1/sessions", json=create_body(SCENE)).json()["id"]
        for k, start in enumerate(range(0, len(reports), 5)):
            client = a if k % 2 == 0 else b
            response = client.post(f"/v1/sessions/{session_id}/reports", json={"reports": reports[start:start + 5]})
            assert response.status_code == 200, response.text
            assert response.json()["version"] == k + 2
        for client in (a, b):
            got = client.get(f"/v1/sessions/{session_id}").json()
            assert got["tracks"] == expected["tracks"] and got["updates"] == expected["updates"]
