"""Redis session store, for several replicas sharing sessions.

URL: ``redis://host:port/db`` (also ``rediss://`` and ``unix://``), with an
optional ``key_prefix`` query parameter (default ``passive-locator:``) so
that several deployments, or test runs, can share one database.

Layout: one hash per session, ``<prefix>session:<id>`` with fields ``v``
(version), ``r`` (the record as JSON); a sorted set per owner,
``<prefix>owner:<owner>``, of its session ids (score 0, ordered by id) for
paging. The session hash carries a Redis TTL equal to the session's idle
lifetime, so abandoned sessions are reclaimed by Redis itself; owner-set
members whose hash is gone are dropped lazily while listing.

Concurrency: :meth:`RedisStore.update` is optimistic. It reads the record,
computes the new one, and writes it with a Lua compare-and-set that succeeds
only if the stored version is still the one read (the script runs
atomically in Redis). On a conflict it reads again and recomputes, with a
jittered exponential backoff; every successful write therefore derives from
the latest record, and no update is lost whichever replica makes it.
"""

from __future__ import annotations

import math
from urllib.parse import parse_qsl, urlencode, urlsplit, urlunsplit

import redis
from redis.backoff import NoBackoff
from redis.retry import Retry

from service.stores.base import Clock, SessionRecord, SessionStore, StoreBusy

DEFAULT_PREFIX = "passive-locator:"

_CREATE = """
if redis.call('EXISTS', KEYS[1]) == 1 then return 0 end
redis.call('HSET', KEYS[1], 'v', ARGV[1], 'r', ARGV[2])
redis.call('PEXPIRE', KEYS[1], ARGV[3])
redis.call('ZADD', KEYS[2], 0, ARGV[4])
return 1
"""

# Write the record only if the stored version is still the one the caller read.
_COMPARE_AND_SET = """
if redis.call('HGET', KEYS[1], 'v') ~= ARGV[1] then return 0 end
redis.call('HSET', KEYS[1], 'v', ARGV[2], 'r', ARGV[3])
redis.call('PEXPIRE', KEYS[1], ARGV[4])
return 1
"""

_DELETE = """
if redis.call('HGET', KEYS[1], 'v') ~= ARGV[1] then return 0 end
redis.call('DEL', KEYS[1])
redis.call('ZREM', KEYS[2], ARGV[2])
return 1
"""


def split_url(url: str) -> tuple[str, str]:
    """A store URL's Redis client URL and its key prefix (our own ``key_prefix`` query parameter, removed)."""
    parts = urlsplit(url)
    query = parse_qsl(parts.query, keep_blank_values=True)
    prefix = next((value for name, value in query if name == "key_prefix"), DEFAULT_PREFIX)
    rest = urlencode([(name, value) for name, value in query if name != "key_prefix"])
    return urlunsplit(parts._replace(query=rest)), prefix


class RedisStore(SessionStore):
    """Sessions in Redis.

    Parameters
    ----------
    client : redis.Redis
    prefix : str
        Prepended to every key.
    clock : callable, optional
        Unix seconds; default :func:`time.time`. Expiry is decided by this
        clock (the record's ``expires_at``); Redis's own TTL only reclaims memory.
    max_attempts : int
        Compare-and-set attempts of one update before answering 503.
    """

    kind = "redis"

    def __init__(self, client: redis.Redis, prefix: str = DEFAULT_PREFIX, clock: Clock | None = None,
                 max_attempts: int = 100):
        super().__init__(clock)
        self.client = client
        self.prefix = prefix
        self.max_attempts = max_attempts
        self._create = client.register_script(_CREATE)
        self._compare_and_set = client.register_script(_COMPARE_AND_SET)
        self._delete = client.register_script(_DELETE)

    @classmethod
    def from_url(cls, url: str, clock: Clock | None = None, timeout_s: float = 1.0) -> "RedisStore":
        """Open a client (lazily: nothing connects yet).

        ``timeout_s`` bounds a connect and each read: a dead or stopped Redis costs a call at most that
        (no retries here: the caller's breaker decides what to do next).
        """
        client_url, prefix = split_url(url)
        client = redis.Redis.from_url(client_url, socket_timeout=timeout_s,
                                      socket_connect_timeout=timeout_s, health_check_interval=30,
                                      retry=Retry(NoBackoff(), 0))
        return cls(client, prefix, clock)

    def _session_key(self, session_id: str) -> str:
        return f"{self.prefix}session:{session_id}"

    def _owner_key(self, owner: str) -> str:
        return f"{self.prefix}owner:{owner}"

    def _ttl_ms(self, record: SessionRecord) -> int:
        return max(1, math.ceil((record.expires_at - self.now()) * 1000.0))

    def _insert(self, record: SessionRecord) -> None:
        created = self._create(keys=[self._session_key(record.id), self._owner_key(record.owner)],
                               args=[record.version, record.to_json(), self._ttl_ms(record), record.id])
        if not created:
            raise ValueError(f"session {record.id!r} exists")

    def _version(self, session_id: str) -> int | None:
        found = self.client.hget(self._session_key(session_id), "v")
        return None if found is None else int(found)

    def _load(self, session_id: str) -> SessionRecord | None:
        raw = self.client.hget(self._session_key(session_id), "r")
        return None if raw is None else SessionRecord.from_json(raw)

    def page(self, owner: str, limit: int, after: str | None = None) -> tuple[list[SessionRecord], bool]:
        owner_key = self._owner_key(owner)
        start = f"({after}" if after else "-"
        chunk = max(limit + 1, 16)
        now = self.now()
        found: list[SessionRecord] = []
        while True:
            ids = [i.decode() for i in self.client.zrangebylex(owner_key, start, "+", start=0, num=chunk)]
            if not ids:
                return found, False
            pipe = self.client.pipeline(transaction=False)
            for session_id in ids:
                pipe.hget(self._session_key(session_id), "r")
            gone = []
            for session_id, raw in zip(ids, pipe.execute()):
                if raw is None:
                    gone.append(session_id)
                    continue
                record = SessionRecord.from_json(raw)
                if record.expired(now):
                    continue
                if len(found) == limit:
                    return found, True
                found.append(record)
            if gone:
                self.client.zrem(owner_key, *gone)
            start = f"({ids[-1]}"

    def _swap(self, session_id: str, version: int, new: SessionRecord) -> bool:
        return bool(self._compare_and_set(keys=[self._session_key(session_id)],
                                          args=[version, new.version, new.to_json(), self._ttl_ms(new)]))

    def _remove(self, owner: str, session_id: str) -> bool:
        keys = [self._session_key(session_id), self._owner_key(owner)]
        for _ in range(self.max_attempts):
            record = self.get(owner, session_id)
            if record is None:
                return False
            if self._delete(keys=keys, args=[record.version, session_id]):
                return True
        raise StoreBusy(f"session {session_id} is being updated by many clients at once; retry")

    def ping(self) -> None:
        self.client.ping()

    def count_live(self) -> int:
        # Redis's own TTL drops a session shortly after the record's expiry: close enough for a gauge.
        return sum(1 for _ in self.client.scan_iter(match=f"{self.prefix}session:*", count=1000))

    def check(self) -> None:
        """A write that expires by itself: proves the server takes writes (not read-only, not out of memory)."""
        self.client.set(f"{self.prefix}readyz", str(self.now()), px=10_000)

    def close(self) -> None:
        self.client.close()
