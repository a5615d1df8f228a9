"""Fixtures shared by the session tests: stores (SQLite and Redis), a settable clock, free ports."""

from __future__ import annotations

import os
import uuid

import pytest
import redis

DEFAULT_REDIS_URL = "redis://127.0.0.1:6379/15"


class FakeClock:
    """Unix seconds that move only when told to."""

    def __init__(self, now: float = 1.7e9):
        self.now = now

    def __call__(self) -> float:
        return self.now

    def advance(self, seconds: float) -> None:
        self.now += seconds


@pytest.fixture
def clock() -> FakeClock:
    return FakeClock()


def redis_base_url() -> str:
    return os.environ.get("PASSIVE_LOCATOR_TEST_REDIS_URL", DEFAULT_REDIS_URL)


@pytest.fixture
def redis_url():
    """A Redis URL with a key prefix of this test's own; its keys are deleted afterwards.

    Skips when no Redis answers, unless PASSIVE_LOCATOR_REQUIRE_REDIS=1 (CI), where it fails.
    """
    base = redis_base_url()
    client = redis.Redis.from_url(base, socket_connect_timeout=2.0)
    try:
        client.ping()
    except redis.RedisError as error:
        client.close()
        message = f"no Redis at {base}: {error}"
        if os.environ.get("PASSIVE_LOCATOR_REQUIRE_REDIS") == "1":
            pytest.fail(message)
        pytest.skip(message)
    prefix = f"pl-test-{uuid.uuid4().hex}:"
    separator = "&" if "?" in base else "?"
    yield f"{base}{separator}key_prefix={prefix}"
    for key in client.scan_iter(match=f"{prefix}*", count=1000):
        client.delete(key)
    client.close()


@pytest.fixture(params=["sqlite", pytest.param("redis", marks=pytest.mark.redis)])
def store_url(request, tmp_path):
    """A fresh store URL of each kind."""
    if request.param == "sqlite":
        return f"sqlite:///{tmp_path}/sessions.db"
    return request.getfixturevalue("redis_url")


@pytest.fixture
def store(store_url, clock):
    from service.stores import open_store

    opened = open_store(store_url, clock=clock)
    yield opened
    opened.close()
