"""Concurrent single fixes share one batched solve.

``POST /v1/fixes`` hands its parsed body to the app's :class:`Coalescer`.
One drain at a time takes *everything queued at that moment* (there is no
waiting window: a lone request on an idle service is solved at once, alone)
and runs :func:`service.translate.fix_results` on the drained bodies on a
worker thread: exactly what ``POST /v1/fixes/batch`` does with its problems,
so a single fix is slot 0 of a batch of one, and fixes that arrived together
share one batched read, solve and write. Requests that arrive while a drain
is running queue up for the next.

A body's result is what it gets alone (the batched core is row-independent);
its error stays its own. If the shared call fails with anything else (a
bug), it is logged and every body of that drain is solved again alone, so
the bug fails only the request that triggers it.

The coalescer belongs to one app (``app.state``, made in the lifespan) and
binds to no event loop until a drain runs; a drain ends in the same step that
resolves its last futures, so nothing is left running when the loop goes idle.
"""

from __future__ import annotations

import asyncio
import logging
import threading
from typing import Callable

from starlette.concurrency import run_in_threadpool

from core.parallel import Stopped
from service.translate import fix_results

logger = logging.getLogger("passive_locator")


def solve_together(items: list[tuple[object, str | None]],
                   should_stop: Callable[[], bool] | None = None) -> list[dict | BaseException]:
    """Results of ``(body, request_id)`` items as one :func:`fix_results` call; each gets its own result.

    A failure of the shared call falls back to solving each body alone, so
    one body's bug fails only its request. ``should_stop`` is asked between
    parts of the solve (raises :class:`core.parallel.Stopped`).
    """
    try:
        return fix_results([body for body, _ in items], [rid for _, rid in items], should_stop)
    except Stopped:
        raise
    except Exception:
        logger.exception("shared solve of %d fixes failed; solving each alone", len(items))
    out: list[dict | BaseException] = []
    for body, rid in items:
        try:
            out.append(fix_results([body], rid, should_stop)[0])
        except Exception as error:
            out.append(error)
    return out


def _never() -> bool:
    return False


class Coalescer:
    """Queues single fix bodies and solves whatever is queued together, one drain at a time.

    Attributes
    ----------
    drains, solved : int
        How many shared solves ran and how many problems they took (for tests and metrics).
    """

    def __init__(self, stopping: threading.Event | None = None) -> None:
        self._pending: list[tuple[object, str | None, Callable[[], bool], asyncio.Future]] = []
        self._loop: asyncio.AbstractEventLoop | None = None
        self._stopping = stopping or threading.Event()
        self.drains = 0
        self.solved = 0

    async def solve(self, body, request_id: str | None = None, should_stop: Callable[[], bool] | None = None) -> dict:
        """The result of one parsed FixRequest body (``{"index": 0, "ok", "fix" | "error"}``), solved
        together with whatever else is queued.

        A drain stops between parts (:class:`core.parallel.Stopped` for each of its requests) when the
        server stops or when every request of the drain says stop (``should_stop``: its deadline, its
        client gone).
        """
        loop = asyncio.get_running_loop()
        should_stop = should_stop or _never
        if self._loop is not None and self._loop is not loop:
            # A drain runs on another event loop (an odd test setup): solve this one alone, off the loop.
            (result,) = await run_in_threadpool(solve_together, [(body, request_id)], should_stop)
            return _unwrap(result)
        future = loop.create_future()
        self._pending.append((body, request_id, should_stop, future))
        if self._loop is None:
            self._loop = loop
            loop.create_task(self._drain())
        return _unwrap(await future)

    async def _drain(self) -> None:
        try:
            while self._pending:
                taken, self._pending = self._pending, []
                self.drains += 1
                self.solved += len(taken)
                stops = [item[2] for item in taken]

                def should_stop() -> bool:
                    return self._stopping.is_set() or all(stop() for stop in stops)

                try:
                    results = await run_in_threadpool(solve_together, [item[:2] for item in taken], should_stop)
                except Stopped as error:
                    results = [error] * len(taken)
                except BaseException:  # cancelled with the loop: nobody may wait forever
                    self._fail(taken)
                    raise
                for (*_, future), result in zip(taken, results):
                    if not future.done():  # a request whose client went away was cancelled
                        future.set_result(result)
        finally:
            # No await between resolving the last futures and this: the drain ends in the same step.
            self._loop = None
            self._fail(self._pending)
            self._pending = []

    @staticmethod
    def _fail(taken) -> None:
        for *_, future in taken:
            if not future.done():
                future.set_exception(RuntimeError("the shared solve was cancelled"))


def _unwrap(result: dict | BaseException) -> dict:
    if isinstance(result, BaseException):
        raise result
    return result
