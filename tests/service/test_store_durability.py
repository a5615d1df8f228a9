"""A write the SQLite store cannot make durable at its configured path is a 503, never an acknowledgement.

An open SQLite connection goes on committing to its file after the file is unlinked, so without a check a
removed directory, a deleted or a replaced file would keep answering 201/200 (and ``/readyz`` 200) while every
write went to an inode that no path names; the next start would find none of them.
"""

from __future__ import annotations

import os
import pathlib
import shutil
import sqlite3
import time

import pytest
from fastapi.testclient import TestClient

from service.app import create_app
from service.settings import Settings
from service.stores.sqlite import SqliteStore, StoreMoved
from tests.service.sessions.helpers import api_epochs, create_body, paper_track


def _remove_directory(path: pathlib.Path) -> None:
    shutil.rmtree(path.parent)


def _remove_files(path: pathlib.Path) -> None:
    for suffix in ("", "-wal", "-shm"):
        os.unlink(f"{path}{suffix}")


def _remove_the_wal(path: pathlib.Path) -> None:
    os.unlink(f"{path}-wal")


def _replace_the_file(path: pathlib.Path) -> None:
    stranger = path.with_name("stranger.db")
    sqlite3.connect(stranger).execute("CREATE TABLE t (x)").connection.close()
    os.replace(stranger, path)


def _remove_and_recreate_the_directory(path: pathlib.Path) -> None:
    shutil.rmtree(path.parent)
    path.parent.mkdir()


FAULTS = [_remove_directory, _remove_files, _remove_the_wal, _replace_the_file, _remove_and_recreate_the_directory]


def _client(path: pathlib.Path) -> TestClient:
    client = TestClient(create_app(Settings(store=f"sqlite:///{path}", store_breaker_failures=1000)))
    client.__enter__()
    return client


def _assert_503(response) -> None:
    assert response.status_code == 503, response.text
    assert response.headers["content-type"].startswith("application/problem+json")
    assert int(response.headers["retry-after"]) >= 1


@pytest.mark.parametrize("fault", FAULTS, ids=lambda fault: fault.__name__.strip("_"))
def test_nothing_is_acknowledged_once_the_path_no_longer_names_the_database(tmp_path, fault):
    path = tmp_path / "var" / "sessions.db"
    client = _client(path)
    epochs = api_epochs(paper_track(seed=3, epochs=8))
    try:
        before = client.post("/v1/sessions", json=create_body())
        assert before.status_code == 201
        session = before.json()["id"]
        assert client.post(f"/v1/sessions/{session}/measurements",
                           json={"measurements": epochs[:2]}).status_code == 200
        assert client.get("/readyz").status_code == 200
        fault(path)
        acknowledged = []
        for attempt in range(4):  # more than one: each store thread's connection and a new one alike
            created = client.post("/v1/sessions", json=create_body())
            if created.status_code == 201:
                acknowledged.append(created.json()["id"])
            else:
                _assert_503(created)
            posted = client.post(f"/v1/sessions/{session}/measurements",
                                 json={"measurements": epochs[2 + attempt:3 + attempt]})
            _assert_503(posted)
        _assert_503(client.get("/readyz"))
        assert acknowledged == []
    finally:
        client.__exit__(None, None, None)


def test_acknowledged_writes_are_there_after_a_restart_when_nothing_moved(tmp_path):
    """The check refuses nothing on a healthy store (the other half of the contract)."""
    path = tmp_path / "sessions.db"
    client = _client(path)
    try:
        ids = [client.post("/v1/sessions", json=create_body()).json()["id"] for _ in range(5)]
    finally:
        client.__exit__(None, None, None)
    client = _client(path)
    try:
        assert [client.get(f"/v1/sessions/{i}").status_code for i in ids] == [200] * 5
    finally:
        client.__exit__(None, None, None)


def test_a_new_connection_does_not_create_an_empty_database_where_the_file_was(tmp_path):
    path = tmp_path / "sessions.db"
    store = SqliteStore(str(path))
    try:
        _remove_files(path)
        with pytest.raises(sqlite3.OperationalError):
            store._connect()
        assert not path.exists()
        with pytest.raises(StoreMoved):
            store.check()
    finally:
        store.close()


def test_the_check_costs_microseconds_beside_the_write():
    """Not a timing assert: prints the per-write cost of the path check for the report (``-s``)."""
    import tempfile

    with tempfile.TemporaryDirectory() as directory:
        store = SqliteStore(os.path.join(directory, "s.db"))
        try:
            started = time.perf_counter()
            for _ in range(10_000):
                store._verify_in_place()
            per_check_us = (time.perf_counter() - started) / 10_000 * 1e6
            with store._db() as db:
                started = time.perf_counter()
                for _ in range(50):
                    with store._write(db):
                        db.execute("INSERT OR REPLACE INTO readiness (id, checked_at) VALUES (1, 0)")
                per_write_us = (time.perf_counter() - started) / 50 * 1e6
        finally:
            store.close()
    print(f"path check {per_check_us:.1f} us per write; a committed write {per_write_us:.0f} us")
    assert per_check_us > 0 and per_write_us > 0


def test_a_database_that_sqlite_keeps_out_of_wal_mode_is_checked_by_its_file_alone(tmp_path, monkeypatch):
    """Where the filesystem refuses WAL (no shared memory), SQLite stays in its rollback journal: no -wal file
    to compare, and the store must still open and still see the file replaced."""
    path = tmp_path / "sessions.db"
    real_connect = sqlite3.connect

    class NoWal(sqlite3.Connection):
        def execute(self, sql, *args):
            if sql == "PRAGMA journal_mode=WAL":
                sql = "PRAGMA journal_mode=DELETE"
            return super().execute(sql, *args)

    monkeypatch.setattr(sqlite3, "connect", lambda *a, **k: real_connect(*a, factory=NoWal, **k))
    store = SqliteStore(str(path))
    try:
        assert not os.path.exists(f"{path}-wal")
        store.check()
        _replace_the_file(path)
        with pytest.raises(sqlite3.OperationalError):  # StoreMoved, or SQLite's own "database moved"
            store.check()
    finally:
        store.close()
