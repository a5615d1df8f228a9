"""The session-store interface and the record every backend keeps.

A store persists :class:`SessionRecord` values and knows nothing about
filters: the session service (``service/sessions/observer.py``) decides what a record
becomes. What a store guarantees is that :meth:`SessionStore.update` is a
read-modify-write applied one at a time per session, across threads and
across processes (and, for Redis, across replicas), so two concurrent posts
to one session never lose each other's epochs. Every backend does it the
same way: read, change outside any lock, then write only if the session is
still at the version read (compare-and-set), else read and change again.
A slow change (a post of 10,000 epochs) thus holds no lock that writes to
other sessions wait for.

Every store keeps the records this process read or wrote last
(:class:`RecordCache`): a version names one record for the session's life,
whichever process or replica wrote it, since every write is a
compare-and-set that bumps it; so a read asks the backend for the version
alone, and fetches and decodes the whole record only when the cached one is
not at that version; and an update changes the cached record without even
that read, its compare-and-set being the check.
"""

from __future__ import annotations

import collections
import random
import threading
import time
from abc import ABC, abstractmethod
from dataclasses import dataclass, fields, replace
from typing import Any, Callable

import orjson

Clock = Callable[[], float]


class StoreError(Exception):
    """A session store could not do what was asked, for now: the client should retry.

    The store says what went wrong and when to retry; the app maps it to an
    HTTP answer in one place (:func:`service.web.problems.install`).

    Parameters
    ----------
    detail : str
        For the client: what failed and that a retry may succeed.
    retry_after_s : float
        Seconds after which a retry may succeed.
    """

    #: The problem code the client sees.
    code = "store_error"

    def __init__(self, detail: str, retry_after_s: float = 1.0):
        super().__init__(detail)
        self.detail, self.retry_after_s = detail, retry_after_s


class StoreUnavailable(StoreError):
    """The backend failed, did not answer in time, or its breaker is open."""

    code = "store_unavailable"


class StoreBusy(StoreError):
    """The backend is up but could not serialise this write in time: its write lock stayed taken, or a
    session's compare-and-set lost to other writers every time."""

    code = "store_busy"


@dataclass(frozen=True)
class SessionRecord:
    """One session as stored.

    Attributes
    ----------
    id : str
        Opaque, URL-safe; ids sort in creation order (a millisecond time prefix).
    owner : str
        Digest of the API key that created the session (``anonymous`` without keys).
    config : dict
        The session's creation parameters as given at the API (JSON-able).
    state : dict
        The filter state as its ``to_dict()`` gave it (JSON-able, exact round trip).
    version : int
        1 at creation, +1 on every write; the ``ETag``.
    last_seq : int or None
        Highest measurement ``seq`` applied (None before the first).
    last_time_s : float or None
        ``time_s`` of that measurement.
    updates : int
        Measurement epochs applied.
    created_at, updated_at, expires_at : float
        Unix seconds (from the store's clock). A session is gone once
        ``expires_at <= now``.
    ttl_s : float
        Idle lifetime: every write sets ``expires_at = now + ttl_s``.
    """

    id: str
    owner: str
    config: dict[str, Any]
    state: dict[str, Any]
    version: int
    last_seq: int | None
    last_time_s: float | None
    updates: int
    created_at: float
    updated_at: float
    expires_at: float
    ttl_s: float

    def to_json(self) -> bytes:
        """Exact JSON (shortest round-trip floats); numpy scalars a core ``to_dict`` may leave are accepted."""
        # The fields themselves, not asdict's deep copy: a network session's state holds thousands of numbers,
        # and copying them cost more than the filter step and the write together.
        return orjson.dumps({f.name: getattr(self, f.name) for f in fields(self)}, option=orjson.OPT_SERIALIZE_NUMPY)

    @classmethod
    def from_json(cls, data: bytes | str) -> "SessionRecord":
        return cls(**orjson.loads(data))

    def expired(self, now: float) -> bool:
        return self.expires_at <= now


class RecordCache:
    """The last records of this process's reads and writes, one per session id, validated by version.

    Records are values: whoever gets one from a store must not change it
    (:func:`dataclasses.replace` makes the next one), since the same object
    is handed to every later reader of that version.

    Parameters
    ----------
    size : int
        Sessions kept (least recently used dropped first); 0 keeps none.
    """

    def __init__(self, size: int = 128):
        self.size = size
        self._records: collections.OrderedDict[str, SessionRecord] = collections.OrderedDict()
        self._lock = threading.Lock()

    def get(self, session_id: str, version: int) -> SessionRecord | None:
        """The cached record of the session when it is at ``version``, else None."""
        with self._lock:
            record = self._records.get(session_id)
            if record is None or record.version != version:
                return None
            self._records.move_to_end(session_id)
            return record

    def latest(self, session_id: str) -> SessionRecord | None:
        """The cached record of the session, whatever version the backend is at now."""
        with self._lock:
            return self._records.get(session_id)

    def put(self, record: SessionRecord) -> None:
        """Keep ``record`` (a version as stored: read, or written and committed), unless an older one."""
        if self.size <= 0:
            return
        with self._lock:
            known = self._records.get(record.id)
            if known is not None and known.version > record.version:
                return
            self._records[record.id] = record
            self._records.move_to_end(record.id)
            while len(self._records) > self.size:
                self._records.popitem(last=False)

    def drop(self, session_id: str) -> None:
        with self._lock:
            self._records.pop(session_id, None)


#: ``change(record) -> new record | None``: what :meth:`SessionStore.update` applies.
Change = Callable[[SessionRecord], "SessionRecord | None"]


class SessionStore(ABC):
    """Durable storage of session records.

    Every method that takes an ``owner`` treats a session of another owner
    exactly like a missing one, and so is an expired session.

    Attributes
    ----------
    kind : str
        ``"sqlite"`` or ``"redis"``, reported by ``/readyz``.
    clock : callable returning float
        Unix seconds; injectable so that tests can expire sessions without sleeping.
    cache : RecordCache
        The records of this store's last reads and writes (``cached_records`` sessions).
    """

    kind: str

    def __init__(self, clock: Clock | None = None, cached_records: int = 128):
        self.clock: Clock = clock or time.time
        self.cache = RecordCache(cached_records)

    def now(self) -> float:
        return self.clock()

    def create(self, record: SessionRecord) -> None:
        """Store a new record (its id must be new)."""
        self._insert(record)
        self.cache.put(record)

    def get(self, owner: str, session_id: str) -> SessionRecord | None:
        """The owner's live session, or None."""
        record = self._current(session_id)
        if record is None or record.owner != owner or record.expired(self.now()):
            return None
        return record

    def _current(self, session_id: str) -> SessionRecord | None:
        """The session's stored record, whoever owns it and live or not: the cached one while the backend is
        still at its version, else the backend's (cached from now on)."""
        version = self._version(session_id)
        if version is None:
            self.cache.drop(session_id)
            return None
        record = self.cache.get(session_id, version)
        if record is None:
            record = self._load(session_id)
            if record is not None:
                self.cache.put(record)
        return record

    @abstractmethod
    def _insert(self, record: SessionRecord) -> None:
        """Write a new record (ValueError or the backend's integrity error when its id exists)."""

    @abstractmethod
    def _version(self, session_id: str) -> int | None:
        """The stored version of the session (None when there is none): one small read."""

    @abstractmethod
    def _load(self, session_id: str) -> SessionRecord | None:
        """The stored record of the session, whoever owns it and live or not."""

    @abstractmethod
    def page(self, owner: str, limit: int, after: str | None = None) -> tuple[list[SessionRecord], bool]:
        """The owner's live sessions with ids above ``after``, in id order.

        Returns
        -------
        records : list of SessionRecord
            At most ``limit``.
        more : bool
            Whether live sessions follow the last one returned.
        """

    #: Compare-and-set attempts of one update before it answers 503 ``store_busy``.
    max_attempts: int = 100

    def update(self, owner: str, session_id: str, change: Change,
               read: SessionRecord | None = None) -> SessionRecord | None:
        """Read-modify-write one session atomically.

        ``change`` gets the current record and returns the new one, or None
        to write nothing; whatever it raises propagates and nothing is
        written. The store sets the new record's ``version`` to the old one
        plus 1. ``change`` runs outside any lock and is called again on the
        fresh record when another write came first, so it must depend only
        on its argument.

        The first attempt changes the record as this process last read or
        wrote it (or ``read``), without reading the backend: the write's
        compare-and-set finds out when another process has moved the session
        on since. A change that raises or writes nothing is not written, so
        then one version read decides: the error or the record stands when
        the record was current, else the change is made again on the latest.

        Parameters
        ----------
        read : SessionRecord, optional
            The owner's session as the caller read it: the first attempt
            changes it, unless it has expired since.

        Returns
        -------
        SessionRecord or None
            The record as stored after the call (unchanged when ``change``
            returned None); None when the session does not exist for this owner.
        """
        for attempt in range(self.max_attempts):
            record = None
            if attempt == 0:
                record = read if read is not None else self.cache.latest(session_id)
                if record is not None and (record.owner != owner or not record.expires_at > self.now()):
                    record = None
            unverified = record is not None
            if record is None:
                record = self.get(owner, session_id)
                if record is None:
                    return None
            try:
                new = change(record)
            except Exception:
                if unverified and self._version(session_id) != record.version:
                    continue  # decided on a record another process has moved on from: decide on the latest
                raise
            if new is None:
                if unverified and self._version(session_id) != record.version:
                    continue
                return record
            new = next_version(record, new)
            if self._swap(session_id, record.version, new):
                self.cache.put(new)
                return new
            time.sleep(random.uniform(0.0, min(0.05, 0.0005 * 2**attempt)))
        raise StoreBusy(f"session {session_id} is being updated by many clients at once; retry")

    @abstractmethod
    def _swap(self, session_id: str, version: int, new: SessionRecord) -> bool:
        """Write ``new`` if the session is still at ``version``; whether it was written."""

    def delete(self, owner: str, session_id: str) -> bool:
        """Remove the owner's session; False when there was none."""
        removed = self._remove(owner, session_id)
        self.cache.drop(session_id)
        return removed

    @abstractmethod
    def _remove(self, owner: str, session_id: str) -> bool:
        """Remove the owner's live session from the backend; False when there was none."""

    @abstractmethod
    def ping(self) -> None:
        """Raise if the backend is unreachable."""

    def check(self) -> None:
        """Raise unless the backend is reachable and takes writes (readiness); default: :meth:`ping`."""
        self.ping()

    @abstractmethod
    def count_live(self) -> int:
        """How many unexpired sessions the store holds, of every owner (a gauge of the metrics)."""

    @abstractmethod
    def close(self) -> None:
        """Release connections."""


def next_version(old: SessionRecord, new: SessionRecord) -> SessionRecord:
    """``new`` with the version that follows ``old``'s (what every backend writes)."""
    return replace(new, id=old.id, owner=old.owner, version=old.version + 1)
