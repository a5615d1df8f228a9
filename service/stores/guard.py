"""The store as the routes see it: its calls on their own bounded threads, with a deadline and a circuit breaker.

A broken or hung store must cost a request a 503 within seconds, never a 500
and never the threads that serve everything else. So every store call runs
on a small executor of its own (not the framework's thread pool, which
``/healthz`` and the CPU-bound routes never share with it anyway, since
``/healthz`` runs on the event loop); the route awaits it for at most
``call_timeout_s``; any backend failure (``redis.RedisError``,
``sqlite3.Error``, ``OSError``) becomes ``503 store_unavailable`` with
``Retry-After``; and after ``failure_threshold`` failures in a row the
breaker opens: for ``cooldown_s`` calls fail at once without touching the
store (a hung store is not given more threads to hang), then one call at a
time is let through, and the first success closes it again. The backend
itself is opened lazily and reopened after a failed open, so a store that
was down at start or comes back later is used without a restart.
"""

from __future__ import annotations

import asyncio
import logging
import sqlite3
import threading
import time
from concurrent.futures import ThreadPoolExecutor
from typing import Any, Callable, TypeVar

from service.stores.base import SessionStore, StoreError, StoreUnavailable

logger = logging.getLogger("passive_locator")

T = TypeVar("T")


def _backend_errors() -> tuple[type[BaseException], ...]:
    errors: list[type[BaseException]] = [sqlite3.Error, OSError, TimeoutError]
    try:
        import redis

        errors.append(redis.RedisError)
    except ImportError:  # pragma: no cover - redis is a dependency
        pass
    return tuple(errors)


BACKEND_ERRORS = _backend_errors()


def unavailable(detail: str, retry_after_s: float) -> StoreUnavailable:
    return StoreUnavailable(detail, retry_after_s)


class CircuitBreaker:
    """Closed -> open after ``threshold`` failures in a row; open for ``cooldown_s``; then half-open
    (one trial call at a time) until a success closes it or a failure opens it again."""

    def __init__(self, threshold: int, cooldown_s: float, clock: Callable[[], float] = time.monotonic):
        self.threshold, self.cooldown_s, self.clock = threshold, cooldown_s, clock
        self._lock = threading.Lock()
        self._failures = 0
        self._open_until = 0.0
        self._trial = False

    def admit(self) -> float:
        """0 when a call may go ahead, else the seconds until one may."""
        with self._lock:
            if self._failures < self.threshold:
                return 0.0
            remaining = self._open_until - self.clock()
            if remaining > 0.0:
                return remaining
            if self._trial:
                return self.cooldown_s
            self._trial = True
            return 0.0

    def cooling(self) -> float:
        """Seconds left of an open breaker's cooldown (0 when closed or half-open); takes no trial."""
        with self._lock:
            if self._failures < self.threshold:
                return 0.0
            return max(0.0, self._open_until - self.clock())

    def success(self) -> None:
        with self._lock:
            self._failures, self._trial = 0, False

    def failure(self) -> None:
        with self._lock:
            self._failures += 1
            self._trial = False
            if self._failures >= self.threshold:
                self._open_until = self.clock() + self.cooldown_s

    @property
    def is_open(self) -> bool:
        with self._lock:
            return self._failures >= self.threshold


class GuardedStore:
    """A :class:`SessionStore` opened lazily, called off the event loop with a deadline, behind a breaker.

    Parameters
    ----------
    open_backend : callable(clock) -> SessionStore
        Opens the backend; called again after a failed open or a closed store.
    kind : str
        ``"sqlite"`` or ``"redis"`` (known before the backend opens).
    workers : int
        Threads for store calls: at most this many calls touch the store at once.
    call_timeout_s : float
        A call not finished by then answers 503 (its thread finishes on the
        backend's own, shorter, socket or busy timeout).
    failure_threshold, cooldown_s
        The breaker's settings.
    """

    def __init__(self, open_backend: Callable[[Callable[[], float]], SessionStore], kind: str, workers: int = 8,
                 call_timeout_s: float = 2.5, failure_threshold: int = 3, cooldown_s: float = 1.0):
        self._open_backend = open_backend
        self.kind = kind
        self.clock: Callable[[], float] = time.time
        self.call_timeout_s = call_timeout_s
        self.breaker = CircuitBreaker(failure_threshold, cooldown_s)
        self._executor = ThreadPoolExecutor(workers, thread_name_prefix="store")
        self._backend: SessionStore | None = None
        self._open_lock = threading.Lock()
        #: Called with the operation's name on every store failure (the app counts them in its metrics).
        self.on_failure: Callable[[str], None] = lambda operation: None

    def now(self) -> float:
        """The store's clock (the backend's ``now``): Unix seconds."""
        return self.clock()

    def backend(self) -> SessionStore:
        """The open backend (opening it now if need be); raises the backend's error when it cannot open."""
        backend = self._backend
        if backend is None:
            with self._open_lock:
                if self._backend is None:
                    self._backend = self._open_backend(self.now)
                backend = self._backend
        return backend

    def _guarded(self, work: Callable[..., T], args: tuple) -> T:
        wait = self.breaker.cooling()
        if wait:  # the breaker opened while this call queued: do not give a hung store another thread
            raise unavailable(f"session store {self.kind} unavailable (failing; circuit open); retry", wait)
        try:
            result = work(self.backend(), *args)
        except BACKEND_ERRORS as error:
            self.breaker.failure()
            self.on_failure(getattr(work, "__name__", "call"))
            logger.warning("session store %s failed: %s: %s", self.kind, type(error).__name__, error)
            raise unavailable(f"session store {self.kind} unavailable ({type(error).__name__}); retry",
                              self.breaker.cooldown_s) from error
        except StoreError:
            self.breaker.failure()
            raise
        self.breaker.success()
        return result

    async def run(self, work: Callable[..., T], *args: Any) -> T:
        """``work(backend, *args)`` on a store thread; its result, or 503 when the store fails or is too slow.

        Raises
        ------
        StoreUnavailable
            On a backend error, a timeout or an open breaker (the app answers 503 with ``Retry-After``);
            whatever ``work`` raises otherwise (a :class:`~service.stores.base.StoreBusy` among them).
        """
        wait = self.breaker.admit()
        if wait:
            raise unavailable(f"session store {self.kind} unavailable (failing; circuit open); retry", wait)
        future = asyncio.get_running_loop().run_in_executor(self._executor, self._guarded, work, args)
        try:
            return await asyncio.wait_for(future, self.call_timeout_s)
        except asyncio.TimeoutError:
            self.breaker.failure()
            self.on_failure(getattr(work, "__name__", "call"))
            logger.warning("session store %s call exceeded %.1f s", self.kind, self.call_timeout_s)
            raise unavailable(f"session store {self.kind} did not answer within {self.call_timeout_s:g} s; retry",
                              self.breaker.cooldown_s) from None

    async def check(self) -> None:
        """Readiness: the store answers, can write, and (SQLite) passes its integrity check; 503 if not."""
        await self.run(lambda backend: backend.check())

    def close(self) -> None:
        self._executor.shutdown(wait=False, cancel_futures=True)
        with self._open_lock:
            backend, self._backend = self._backend, None
        if backend is not None:
            try:
                backend.close()
            except BACKEND_ERRORS as error:
                logger.warning("closing session store %s: %s", self.kind, error)
