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
writes of other sessions wait past the 0.5 s busy timeout. Writers are
serialised across processes sharing the file (waiting up to
``busy_timeout_s``); readers are not blocked (WAL).

Group commit: within one process, writes that arrive while a transaction
is being written queue (in arrival order, rather than in SQLite's own
backoff sleeps, under which a writer among eight busy threads could lose
the race past the busy timeout while the file was never held that long),
and the first of them, once the transaction ends, writes every one queued
in one transaction: one fsync for all of them. Each write keeps its own
outcome (a savepoint each: one that fails, a taken id say, is rolled back
alone), and is acknowledged to its caller only after that ``COMMIT`` and
the file check below; when the ``COMMIT`` fails, every write of the group
fails with it and none was applied.
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
import copy
import math
import os
import pathlib
import sqlite3
import threading
import time
from contextlib import contextmanager
from typing import Any, Callable, Iterator, NamedTuple, TypeVar

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

T = TypeVar("T")


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
        self._turns = _Turns()
        #: The database file and its WAL (None where the filesystem kept SQLite out of WAL mode) as opened; None
        #: until the schema's write has made them, and in memory.
        self._identity: tuple[FileIdentity, FileIdentity | None] | None = None
        self._shared: sqlite3.Connection | None = self._connect() if self.memory else None
        self._commit(lambda db: [db.execute(statement) for statement in _SCHEMA.split(";") if statement.strip()])
        with self._db() as db:
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

    def _insert(self, record: SessionRecord) -> None:
        text, now = record.to_json(), self.now()

        def insert(db: sqlite3.Connection) -> None:
            db.execute("DELETE FROM sessions WHERE expires_at <= ?", (now,))
            db.execute("INSERT INTO sessions (id, owner, version, expires_at, record) VALUES (?, ?, ?, ?, ?)",
                       (record.id, record.owner, record.version, record.expires_at, text))

        self._commit(insert)

    def _version(self, session_id: str) -> int | None:
        with self._db() as db:
            row = db.execute("SELECT version FROM sessions WHERE id = ?", (session_id,)).fetchone()
        return None if row is None else row[0]

    def _load(self, session_id: str) -> SessionRecord | None:
        with self._db() as db:
            row = db.execute("SELECT record FROM sessions WHERE id = ?", (session_id,)).fetchone()
        return None if row is None else SessionRecord.from_json(row[0])

    def page(self, owner: str, limit: int, after: str | None = None) -> tuple[list[SessionRecord], bool]:
        with self._db() as db:
            rows = db.execute(
                "SELECT record FROM sessions WHERE owner = ? AND id > ? AND expires_at > ? ORDER BY id LIMIT ?",
                (owner, after or "", self.now(), limit + 1)).fetchall()
        records = [SessionRecord.from_json(row[0]) for row in rows]
        return records[:limit], len(records) > limit

    def _swap(self, session_id: str, version: int, new: SessionRecord) -> bool:
        text = new.to_json()

        def swap(db: sqlite3.Connection) -> bool:
            written = db.execute(
                "UPDATE sessions SET version = ?, expires_at = ?, record = ? WHERE id = ? AND version = ?",
                (new.version, new.expires_at, text, session_id, version))
            return written.rowcount == 1

        return self._commit(swap)

    def _remove(self, owner: str, session_id: str) -> bool:
        now = self.now()

        def remove(db: sqlite3.Connection) -> bool:
            row = db.execute("SELECT record FROM sessions WHERE id = ?", (session_id,)).fetchone()
            if self._live(row, owner, now) is None:
                return False
            db.execute("DELETE FROM sessions WHERE id = ?", (session_id,))
            return True

        return self._commit(remove)

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
        checked_at = self.now()
        self._commit(lambda db: db.execute("INSERT OR REPLACE INTO readiness (id, checked_at) VALUES (1, ?)",
                                           (checked_at,)))
        with self._db() as db:
            now = time.monotonic()
            if now - self._integrity_checked_at >= self.integrity_interval_s:
                verdict = [row[0] for row in db.execute("PRAGMA quick_check").fetchall()]
                if verdict != ["ok"]:
                    raise sqlite3.DatabaseError(f"integrity check failed: {'; '.join(verdict[:3])}")
                self._integrity_checked_at = now

    @contextmanager
    def _write(self, db: sqlite3.Connection) -> Iterator[None]:
        """``BEGIN IMMEDIATE`` ... ``COMMIT`` of the caller's statements alone, rolled back on any exception,
        in its turn among this process's writers (the schema's write, and tests that hold the lock).

        The write lock is taken before the first read, so a read-modify-write
        cannot interleave with another writer's (no lost update, no upgrade
        deadlock). Waiting longer than the busy timeout, for this process's
        writers or for another process's lock, is a 503.
        """
        turn = _Write(None)
        self._turns.enter(turn, self.busy_timeout_s)
        try:
            self._begin(db)
            try:
                yield
                db.execute("COMMIT")
            except BaseException:
                if db.in_transaction:
                    db.execute("ROLLBACK")
                raise
            self._verify_in_place()  # after COMMIT: a removal while it ran is seen before anyone is answered
        finally:
            self._turns.leave(())

    def _commit(self, work: Callable[[sqlite3.Connection], T]) -> T:
        """``work(db)`` in a transaction shared with the other writes of this process queued meanwhile; its
        result once that transaction is committed (and the file checked), or its error.

        Raises
        ------
        StoreBusy
            When this write waited longer than the busy timeout for its turn, or for another process's lock.
        sqlite3.Error
            What ``work`` raised (its savepoint rolled back, the others' writes kept), or what the
            ``BEGIN``, ``COMMIT`` or the file check raised (nothing of the group applied or acknowledged).
        """
        mine = _Write(work)
        if not self._turns.enter(mine, self.busy_timeout_s):
            return mine.outcome()  # written in another's group
        group = [mine]
        try:
            group += self._turns.take()
            with self._db() as db:
                self._write_group(db, group)
        finally:
            self._turns.leave(group[1:])
        return mine.outcome()

    def _begin(self, db: sqlite3.Connection) -> None:
        try:
            db.execute("BEGIN IMMEDIATE")
        except sqlite3.OperationalError as error:
            if "locked" in str(error) or "busy" in str(error):
                raise _busy() from error
            raise

    def _write_group(self, db: sqlite3.Connection, group: list["_Write"]) -> None:
        """Every write of ``group`` in one transaction, each behind its own savepoint. A write's outcome is
        set only once the transaction's fate is known: on any failure of the transaction itself, each write
        gets that error (copied: each caller raises its own)."""
        outcomes: list[tuple[Any, Exception | None]] = []
        try:
            self._begin(db)
            try:
                for write in group:
                    db.execute("SAVEPOINT one_write")
                    try:
                        outcomes.append((write.work(db), None))
                    except Exception as error:  # this write's own failure: the others go on
                        db.execute("ROLLBACK TO one_write")
                        outcomes.append((None, error))
                    db.execute("RELEASE one_write")
                db.execute("COMMIT")
            except BaseException:
                if db.in_transaction:
                    db.execute("ROLLBACK")
                raise
            self._verify_in_place()  # after COMMIT: a removal while it ran is seen before anyone is answered
        except Exception as error:
            outcomes = [(None, error if k == 0 else _copied(error)) for k in range(len(group))]
        for write, (result, error) in zip(group, outcomes):
            write.result, write.error, write.settled = result, error, True

    def close(self) -> None:
        with self._registry_lock:
            connections, self._connections = self._connections, []
        for db in connections:
            db.close()


class _Write:
    """One write waiting for its transaction: ``work(db)`` (None: a caller's own :meth:`SqliteStore._write`),
    then its result or error."""

    __slots__ = ("work", "result", "error", "settled", "written", "wake")

    def __init__(self, work: Callable[[sqlite3.Connection], Any] | None):
        self.work, self.result, self.error = work, None, None
        #: Whether its transaction's fate set ``result`` or ``error``; whether a writer's turn ended with it.
        self.settled = self.written = False
        self.wake = threading.Event()

    def outcome(self):
        if not self.settled:  # the writer that took it was interrupted before the transaction's end
            raise sqlite3.OperationalError("the write was interrupted before its commit; it was not applied")
        if self.error is not None:
            raise self.error
        return self.result


class _Turns:
    """The writers of one process: one writes at a time, the others wait in arrival order.

    A release hands the turn to the longest waiter, so a writer's wait is
    bounded by the writers ahead of it, whatever the thread scheduling; and
    the writer whose turn it is takes every grouped write waiting
    (:meth:`take`) into its transaction, so those are done when it releases
    and wait no longer.
    """

    def __init__(self) -> None:
        self._mutex = threading.Lock()
        self._held = False
        self._queue: collections.deque[_Write] = collections.deque()

    def enter(self, write: _Write, timeout: float) -> bool:
        """Wait for ``write``'s turn: True when it is (the caller writes, then calls :meth:`leave`), False when
        another writer wrote it in its group meanwhile.

        Raises
        ------
        StoreBusy
            When ``timeout`` seconds passed and no writer has taken it.
        """
        with self._mutex:
            if not self._held:
                self._held = True
                return True
            self._queue.append(write)
        if not write.wake.wait(timeout):
            with self._mutex:
                if write in self._queue:
                    self._queue.remove(write)
                    raise _busy()
            write.wake.wait()  # in a group being written, or handed the turn as the wait timed out
        return not write.written

    def take(self) -> list[_Write]:
        """The grouped writes waiting (in order), out of the queue: the caller writes them in its transaction."""
        with self._mutex:
            taken = [w for w in self._queue if w.work is not None]
            if taken:
                self._queue = collections.deque(w for w in self._queue if w.work is None)
        return taken

    def leave(self, written) -> None:
        """End the caller's turn: the writes it took are done (their callers wake with their outcome), and the
        longest waiter, if any, has the next turn."""
        for write in written:
            write.written = True
            write.wake.set()
        with self._mutex:
            if self._queue:
                self._queue.popleft().wake.set()
            else:
                self._held = False


def _copied(error: Exception) -> Exception:
    """A copy of ``error`` for another thread to raise (one instance raised in several threads would share
    and grow one traceback), chained to it."""
    try:
        twin = copy.copy(error)
    except Exception:  # an exception that cannot be copied: raise the one instance
        return error
    twin.__cause__ = error
    return twin


def _busy() -> StoreBusy:
    return StoreBusy("the session store is busy; retry")
