"""The live-session count behind the ``passive_locator_sessions_live`` gauge, on every backend."""

from __future__ import annotations

from tests.service.sessions.test_stores import make_record


def test_every_owners_sessions_are_counted_until_deleted(store):
    assert store.count_live() == 0
    store.create(make_record("0001", now=store.now()))
    store.create(make_record("0002", owner="bob", now=store.now()))
    assert store.count_live() == 2
    assert store.delete("alice", "0001")
    assert store.count_live() == 1


def test_an_expired_session_is_not_counted(tmp_path, clock):
    from service.stores import open_store

    store = open_store(f"sqlite:///{tmp_path}/s.db", clock=clock)
    try:
        store.create(make_record("0001", now=store.now(), ttl_s=10.0))
        store.create(make_record("0002", now=store.now(), ttl_s=100.0))
        assert store.count_live() == 2
        clock.advance(50.0)
        assert store.count_live() == 1
    finally:
        store.close()
