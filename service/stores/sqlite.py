"""SQLite session store: the embedded default (``sqlite:///./var/sessions.db``).

Durability: WAL journal with ``synchronous=FULL``, so a commit returns only
after its WAL frames are fsync'd. ``NORMAL`` with WAL would already survive
a killed process (the frames are in the OS page cache when COMMIT returns);
``FULL`` also survives an OS crash or power cut, and an acknowledged
measurement must never come back unapplied, since the client will not resend
a ``seq`` it saw acknowledged. The price is one fsync per write.

Concurrency: :meth:`SqliteStore.update` is the base class's compare-and-set:
the change runs outside any lock, and the write is an ``UPDATE ... WHERE
version = ?`` inside ``BEGIN IMMEDIATE`` (the database's write lock, held
for that statement and its fsync only). With load-change-save all inside
the lock, a post of 10,000 epochs (0.6 s of filter steps) would make the
writes of other sessions wait past the 0.5 s busy timeout (measured: 1,082
of 1,161 posts of six streaming clients answered 503). Writers are serialised
across processes sharing the file (waiting up to ``busy_timeout_s``);
readers are not blocked (WAL). Within one process the writers first queue
on a lock of the store's: SQLite's own wait is a sleep with growing backoff,
under which a writer among eight busy threads could lose the race for 0.5 s
and answer 503 while the file was never contended for that long (measured:
42 of about 3,500 posts at 8 clients).
Each thread has its own connection; ``:memory:`` (one database per
connection) uses a single connection behind a lock instead.

Durability at the configured path: an open connection keeps reading and
writing its file after the file is unlinked (its directory removed, the file
deleted or replaced), so SQLite would go on committing to an inode that no
path names any more, and everything acknowledged since would be gone at the
next start. So the store records the identity (device and inode) of the
database and its WAL when it opens, and every write, every new connection
and the readiness check compare the files the path names now with them
(:meth:`SqliteStore._verify_in_place`, two ``stat`` calls): a mismatch is a
:class:`StoreMoved` error (503), checked after ``COMMIT`` and before the write
is acknowledged, and it stays so until a restart opens whatever the path then
names.
"""

from __future__ import annotations

import collections
import math
import os
import pathlib
import sqlite3
import threading
import time
from contextlib import contextmanager
from typing import Iterator, NamedTuple

from service.stores.base import Clock, SessionRecord, SessionStore, StoreBusy

_SCHEMA = """
CREATE TABLE IF NOT EXISTS sessions (
    id TEXT PRIMARY KEY,
    owner TEXT NOT NULL,
    version INTEGER NOT NULL,
    expires_at REAL NOT NULL,
    record BLOB NOT NULL
) WITHOUT ROWID;
CREATE INDEX IF NOT EXISTS sessions_by_owner ON sessions (owner, id);
CREATE INDEX IF NOT EXISTS sessions_by_expiry ON sessions (expires_at);
CREATE TABLE IF NOT EXISTS readiness (id INTEGER PRIMARY KEY, checked_at REAL NOT NULL);
"""


class StoreMoved(sqlite3.OperationalError):
    """The configured path no longer names the database file this store has open: nothing written now would
    be found there after a restart."""


class FileIdentity(NamedTuple):
    """What names one file whatever its path: ``st_dev`` and ``st_ino``."""

    device: int
    inode: int

    @classmethod
    def of(cls, path: str) -> "FileIdentity":
        """The identity of the file at ``path`` (``FileNotFoundError`` when there is none)."""
        found = os.stat(path)
        return cls(found.st_dev, found.st_ino)


class SqliteStore(SessionStore):
    """Sessions in one SQLite file.

    Parameters
    ----------
    path : str
        Database file (its directory is created), or ``:memory:``.
    clock : callable, optional
        Unix seconds; default :func:`time.time`.
    busy_timeout_s : float
        How long a writer waits for another's lock before giving up (503).
    """

    kind = "sqlite"

    def __init__(self, path: str, clock: Clock | None = None, busy_timeout_s: float = 30.0,
                 integrity_interval_s: float = 60.0):
        super().__init__(clock)
        self.integrity_interval_s = integrity_interval_s
        self._integrity_checked_at = -math.inf
        self.path = path
        self.memory = path == ":memory:"
        if not self.memory:
            os.makedirs(os.path.dirname(os.path.abspath(path)), exist_ok=True)
        self.busy_timeout_s = busy_timeout_s
        self._local = threading.local()
        self._connections: list[sqlite3.Connection] = []
        self._registry_lock = threading.Lock()
        self._memory_lock = threading.RLock()
        self._writer = _Turns()
        #: The database file and its WAL (None where the filesystem kept SQLite out of WAL mode) as opened; None
        #: until the schema's write has made them, and in memory.
        self._identity: tuple[FileIdentity, FileIdentity | None] | None = None
        self._shared: sqlite3.Connection | None = self._connect() if self.memory else None
        with self._db() as db:
            with self._write(db):
                for statement in _SCHEMA.split(";"):
                    if statement.strip():
                        db.execute(statement)
            wal = db.execute("PRAGMA journal_mode").fetchone()[0] == "wal"
        if not self.memory:
            self._identity = (FileIdentity.of(self.path), FileIdentity.of(self.path + "-wal") if wal else None)

    @classmethod
    def from_url(cls, url: str, clock: Clock | None = None, timeout_s: float = 30.0,
                 integrity_interval_s: float = 60.0) -> "SqliteStore":
        """``sqlite:///relative/or/absolute/path`` (``sqlite:////abs`` also works), ``sqlite:///:memory:``.

        ``timeout_s`` is the busy timeout: how long a writer waits for another's lock (then 503).
        """
        return cls(url.removeprefix("sqlite://").removeprefix("/") or ":memory:", clock, timeout_s,
                   integrity_interval_s)

    def _connect(self) -> sqlite3.Connection:
        """A new connection; only the store's first may create the file (a later one finding it gone would
        otherwise start an empty database there)."""
        target, uri = self.path, False
        if self._identity is not None:
            target, uri = pathlib.Path(self.path).absolute().as_uri() + "?mode=rw", True
        db = sqlite3.connect(target, timeout=self.busy_timeout_s, isolation_level=None, check_same_thread=False,
                             uri=uri)
        try:
            if not self.memory:
                db.execute("PRAGMA journal_mode=WAL")
            db.execute("PRAGMA synchronous=FULL")
            self._verify_in_place()  # a connection opened after the file was replaced would open the stranger
        except BaseException:
            db.close()
            raise
        with self._registry_lock:
            self._connections.append(db)
        return db

    def _verify_in_place(self) -> None:
        """Raise :class:`StoreMoved` unless the configured path still names the database (and WAL) opened.

        Two ``stat`` calls: microseconds, beside the fsync of the commit they guard.
        """
        if self._identity is None:
            return
        database, wal = self._identity
        try:
            now = (FileIdentity.of(self.path), None if wal is None else FileIdentity.of(self.path + "-wal"))
        except FileNotFoundError:
            now = None
        if now != (database, wal):
            raise StoreMoved(f"{self.path} (or its -wal) was removed or replaced under the running service: a "
                             "write now would not be there after a restart; restart to use what the path names")

    @contextmanager
    def _db(self) -> Iterator[sqlite3.Connection]:
        if self._shared is not None:
            with self._memory_lock:
                yield self._shared
            return
        db = getattr(self._local, "db", None)
        if db is None:
            db = self._local.db = self._connect()
        yield db

    def _live(self, row, owner: str, now: float) -> SessionRecord | None:
        if row is None:
            return None
        record = SessionRecord.from_json(row[0])
        if record.owner != owner or record.expired(now):
            return None
        return record

    def create(self, record: SessionRecord) -> None:
        with self._db() as db, self._write(db):
            db.execute("DELETE FROM sessions WHERE expires_at <= ?", (self.now(),))
            db.execute("INSERT INTO sessions (id, owner, version, expires_at, record) VALUES (?, ?, ?, ?, ?)",
                       (record.id, record.owner, record.version, record.expires_at, record.to_json()))

    def get(self, owner: str, session_id: str) -> SessionRecord | None:
        with self._db() as db:
            row = db.execute("SELECT record FROM sessions WHERE id = ?", (session_id,)).fetchone()
        return self._live(row, owner, self.now())

    def page(self, owner: str, limit: int, after: str | None = None) -> tuple[list[SessionRecord], bool]:
        with self._db() as db:
            rows = db.execute(
                "SELECT record FROM sessions WHERE owner = ? AND id > ? AND expires_at > ? ORDER BY id LIMIT ?",
                (owner, after or "", self.now(), limit + 1)).fetchall()
        records = [SessionRecord.from_json(row[0]) for row in rows]
        return records[:limit], len(records) > limit

    def _swap(self, session_id: str, version: int, new: SessionRecord) -> bool:
        text = new.to_json()
        with self._db() as db, self._write(db):
            written = db.execute(
                "UPDATE sessions SET version = ?, expires_at = ?, record = ? WHERE id = ? AND version = ?",
                (new.version, new.expires_at, text, session_id, version))
            return written.rowcount == 1

    def delete(self, owner: str, session_id: str) -> bool:
        with self._db() as db, self._write(db):
            row = db.execute("SELECT record FROM sessions WHERE id = ?", (session_id,)).fetchone()
            if self._live(row, owner, self.now()) is None:
                return False
            db.execute("DELETE FROM sessions WHERE id = ?", (session_id,))
            return True

    def ping(self) -> None:
        with self._db() as db:
            db.execute("SELECT 1").fetchone()

    def count_live(self) -> int:
        with self._db() as db:
            return db.execute("SELECT count(*) FROM sessions WHERE expires_at > ?", (self.now(),)).fetchone()[0]

    def check(self) -> None:
        """A committed write (a full disk or read-only file fails it) to the file the path still names (a
        removed or replaced file fails it), and ``PRAGMA quick_check`` at most every ``integrity_interval_s``
        (a corrupt page fails it).

        Raises
        ------
        sqlite3.DatabaseError
            When the write fails, the path names another file (:class:`StoreMoved`) or the check finds damage.
        """
        with self._db() as db:
            with self._write(db):
                db.execute("INSERT OR REPLACE INTO readiness (id, checked_at) VALUES (1, ?)", (self.now(),))
            now = time.monotonic()
            if now - self._integrity_checked_at >= self.integrity_interval_s:
                verdict = [row[0] for row in db.execute("PRAGMA quick_check").fetchall()]
                if verdict != ["ok"]:
                    raise sqlite3.DatabaseError(f"integrity check failed: {'; '.join(verdict[:3])}")
                self._integrity_checked_at = now

    @contextmanager
    def _write(self, db: sqlite3.Connection) -> Iterator[None]:
        """``BEGIN IMMEDIATE`` ... ``COMMIT``, rolled back on any exception, one writer of this process at a time.

        The write lock is taken before the first read, so a read-modify-write
        cannot interleave with another writer's (no lost update, no upgrade
        deadlock). Waiting longer than the busy timeout, for this process's
        writers or for another process's lock, is a 503.
        """
        if not self._writer.acquire(timeout=self.busy_timeout_s):
            raise _busy()
        try:
            try:
                db.execute("BEGIN IMMEDIATE")
            except sqlite3.OperationalError as error:
                if "locked" in str(error) or "busy" in str(error):
                    raise _busy() from error
                raise
            try:
                yield
            except BaseException:
                db.execute("ROLLBACK")
                raise
            db.execute("COMMIT")
            self._verify_in_place()  # after COMMIT: a removal while it ran is seen before anyone is answered
        finally:
            self._writer.release()

    def close(self) -> None:
        with self._registry_lock:
            connections, self._connections = self._connections, []
        for db in connections:
            db.close()


class _Turns:
    """A lock that serves its waiters in arrival order: a release hands it to the longest waiter.

    A writer's wait is then bounded by the writers ahead of it, whatever the
    thread scheduling. A plain ``threading.Lock`` (no order) also ended the
    503s of 8 session clients, with a longer tail: p99 42 and 67 ms against
    34 and 35 ms, two runs each at one epoch per post.
    """

    def __init__(self) -> None:
        self._mutex = threading.Lock()
        self._held = False
        self._queue: collections.deque[threading.Event] = collections.deque()

    def acquire(self, timeout: float) -> bool:
        with self._mutex:
            if not self._held:
                self._held = True
                return True
            turn = threading.Event()
            self._queue.append(turn)
        if turn.wait(timeout):
            return True
        with self._mutex:
            if turn.is_set():  # handed over as the wait timed out
                return True
            self._queue.remove(turn)
            return False

    def release(self) -> None:
        with self._mutex:
            if self._queue:
                self._queue.popleft().set()
            else:
                self._held = False


def _busy() -> StoreBusy:
    return StoreBusy("the session store is busy; retry")
