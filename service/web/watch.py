"""The one way a route runs long work: watched for its deadline, its client and the server's shutdown.

A route hands :func:`watched` a function that starts its work given a
``should_stop`` (a :class:`RequestWatch`); the work checks it between chunks
(``core.parallel.run_chunks`` and the like raise ``core.parallel.Stopped``).
Meanwhile the route waits on the event loop, looking for a disconnected
client every :data:`POLL_S` seconds, and answers

- 503 ``deadline_exceeded`` (``Retry-After``) at ``settings.request_deadline_s``,
  once the work has stopped at its next check (or after :data:`STOP_GRACE_S`,
  for work that cannot stop before it ends);
- 499 ``client_closed`` when the client went away;
- 503 ``shutting_down`` when the server stops.

Whatever ends the request, the watch then says stop, so the work stops
using the CPU within one chunk.
"""

from __future__ import annotations

import asyncio
import contextvars
import threading
import time
from typing import Any, Awaitable, Callable

from fastapi import Request
from starlette.concurrency import run_in_threadpool

from core.parallel import Stopped
from service.web.problems import ApiError

#: How often a waiting route looks for a disconnected client.
POLL_S = 0.2
#: How long a stopped request waits for its work to reach its next check before it answers.
STOP_GRACE_S = 1.0

_STOPPED = (Stopped,)


class RequestWatch:
    """``should_stop`` of one request: past its deadline, abandoned, or the server is stopping.

    Thread-safe: work on any thread may call it.
    """

    def __init__(self, http: Request):
        self.deadline_s = http.app.state.settings.request_deadline_s
        self.deadline = time.monotonic() + self.deadline_s
        self.ended = threading.Event()
        self.stopping: threading.Event = http.app.state.stopping

    def expired(self) -> bool:
        return time.monotonic() > self.deadline

    def __call__(self) -> bool:
        return self.ended.is_set() or self.stopping.is_set() or self.expired()

    def error(self, hint: str) -> ApiError:
        """The answer to a request this watch stopped."""
        if self.expired():
            return ApiError(503, "deadline_exceeded",
                            f"not finished within request_deadline_s = {self.deadline_s:g} s; {hint}",
                            headers={"Retry-After": "1"})
        return shutting_down()


def shutting_down() -> ApiError:
    """The answer to a request the server's shutdown stopped."""
    return ApiError(503, "shutting_down", "the server is shutting down; retry", headers={"Retry-After": "1"})


async def on_the_loop(work: Awaitable[Any]) -> Any:
    """The result of ``work`` solved on the event loop, which is not watched (it holds the loop a few hundred
    microseconds at most); 503 ``shutting_down`` when the server's shutdown stopped it."""
    try:
        return await work
    except _STOPPED:
        raise shutting_down() from None


def _retrieve(future: asyncio.Future) -> None:
    """Consume the outcome of work nobody waits for any more (no 'exception never retrieved')."""
    if not future.cancelled():
        future.exception()


async def watched(http: Request, start: Callable[[RequestWatch], Awaitable[Any]], hint: str) -> Any:
    """The result of ``start(should_stop)``, or the ApiError of the watch that stopped it.

    Parameters
    ----------
    http : Request
    start : callable
        Given the request's :class:`RequestWatch`, returns an awaitable of the result (a coroutine, or an
        executor future from :func:`in_pool`).
    hint : str
        What the client can do about a deadline (``"ask for fewer trials or methods"``).
    """
    watch = RequestWatch(http)
    future = asyncio.ensure_future(start(watch))
    future.add_done_callback(_retrieve)
    try:
        while True:
            remaining = watch.deadline - time.monotonic()
            done, _ = await asyncio.wait({future}, timeout=max(0.0, min(POLL_S, remaining)))
            if done:
                break
            if watch.expired() or watch.stopping.is_set():
                watch.ended.set()
                await asyncio.wait({future}, timeout=STOP_GRACE_S)  # chunked work is at its next check by then
                if future.done():
                    break  # stopped at its check, or finished after all: either is the answer
                future.cancel()
                raise watch.error(hint)
            if await http.is_disconnected():
                future.cancel()
                raise ApiError(499, "client_closed", "the client went away")
        try:
            return future.result()
        except _STOPPED:
            raise watch.error(hint) from None
    finally:
        watch.ended.set()  # the request is over, whatever ended it (a cancelled task at shutdown too)


def in_pool(pool, work: Callable[[RequestWatch], Any]) -> Callable[[RequestWatch], Awaitable[Any]]:
    """A ``start`` for :func:`watched` that runs ``work(should_stop)`` on an executor, in the request's context
    (its context variables); None: the threads that serve plain ``def`` routes."""
    def start(watch: RequestWatch) -> Awaitable[Any]:
        if pool is None:
            return run_in_threadpool(work, watch)
        context = contextvars.copy_context()
        return asyncio.get_running_loop().run_in_executor(pool, context.run, work, watch)
    return start
