"""Concurrent single fixes share one batched solve.

``POST /v1/fixes`` hands its decoded body to the app's :class:`Coalescer`.
One drain at a time takes *everything queued at that moment* (there is no
waiting window: a lone request on an idle service is solved at once, alone)
and runs :func:`service.fixes.pipeline.fix_results` on the drained bodies on its own
worker thread: exactly what ``POST /v1/fixes/batch`` does with its problems,
so a single fix is slot 0 of a batch of one, and fixes that arrived together
share one batched read, solve and write. Requests that arrive while a drain
is running queue up for the next.

A body's result is what it gets alone (the batched core is row-independent);
its error stays its own, and so does a bug's 500 (:func:`fix_results` solves
each body alone when the shared call fails).

A small fix is solved on the event loop instead (:meth:`Coalescer.inline`):
one whose cost estimate (:func:`service.limits.body_fix_cost`) is at most the
app's ``inline_fix_cost``, set where a fix holds the loop for a few hundred
microseconds (``python -m bench.inline_threshold``). For such a fix the hop to
the worker thread and back (two thread switches, the GIL handed over each
way) and the watch of its deadline are a large share of its time, and the
solve holds the GIL wherever it runs. Small fixes
queued in one loop step are still solved together, one step later, as one
batch on the loop; larger ones go to the worker as before, with their
deadline and their clients watched.

The coalescer belongs to one app (``app.state``, made in the lifespan) and
binds to no event loop until a drain runs; a drain ends in the same step that
resolves its last futures, so nothing is left running when the loop goes idle.
"""

from __future__ import annotations

import asyncio
import contextvars
import threading
import time
from concurrent.futures import ThreadPoolExecutor
from typing import Callable

from core.parallel import Stopped
from service.limits import body_fix_cost
from service.fixes.pipeline import fix_results


def _never() -> bool:
    return False


class Coalescer:
    """Queues single fix bodies and solves whatever is queued together, one drain at a time.

    A drain is a call on the coalescer's own worker thread; it starts one loop
    step after the first body that finds the coalescer idle (so every body
    queued in that step joins it), and when it ends the next one starts with
    whatever queued meanwhile. No task waits on the loop for it: the
    callbacks of its executor future resolve each request's future.

    Attributes
    ----------
    drains, solved : int
        How many shared solves ran and how many problems they took (for tests and metrics).
    inline_drains : int
        How many of those drains ran on the event loop (:meth:`inline`).

    Parameters
    ----------
    stopping : threading.Event, optional
        Set when the server stops: a drain stops between parts.
    metrics : service.ops.metrics.Metrics, optional
        Told each drain's results, under the method each ran with, and each fix's time from submission.
    max_fix_cost : int, optional
        The app's ``max_fix_cost``, checked on every body (None: no limit).
    inline_fix_cost : int, optional
        The app's ``inline_fix_cost``: a body whose cost estimate is at most this is solved on the event loop
        (None: every body on the worker thread).
    """

    def __init__(self, stopping: threading.Event | None = None, metrics=None, max_fix_cost: int | None = None,
                 inline_fix_cost: int | None = None) -> None:
        self._max_fix_cost = max_fix_cost
        self._inline_fix_cost = inline_fix_cost
        self._inline_pending: dict[asyncio.AbstractEventLoop, list] = {}
        self._pending: list[tuple[object, str | None, Callable[[], bool], asyncio.Future, float]] = []
        self._metrics = metrics
        self._loop: asyncio.AbstractEventLoop | None = None
        self._stopping = stopping or threading.Event()
        self._worker = ThreadPoolExecutor(1, thread_name_prefix="fixes")
        self.drains = 0
        self.solved = 0
        self.inline_drains = 0

    def inline(self, body) -> bool:
        """Whether ``body`` is solved on the event loop: its cost estimate
        (:func:`service.limits.body_fix_cost`) is at most ``inline_fix_cost``."""
        return self._inline_fix_cost is not None and body_fix_cost(body) <= self._inline_fix_cost

    def submit(self, body, request_id: str | None = None, should_stop: Callable[[], bool] | None = None,
               inline: bool | None = None) -> asyncio.Future:
        """A future of one FixRequest body's result (``{"index": 0, "ok", "fix" | "error"}``), solved
        together with whatever else is queued.

        A drain stops between parts (the future raises :class:`core.parallel.Stopped`) when the server stops
        or when every request of the drain says stop (``should_stop``: its deadline, its client gone). An
        ``inline`` body (default :meth:`inline`) is solved on this event loop one step later, with the other
        inline bodies queued by then; it stops only when the server stops.
        """
        loop = asyncio.get_running_loop()
        future = loop.create_future()
        item = (body, request_id, should_stop or _never, future, time.perf_counter())
        if self.inline(body) if inline is None else inline:
            pending = self._inline_pending.get(loop)
            if pending is None:
                self._inline_pending[loop] = pending = []
                loop.call_soon(self._drain_inline, loop)
            pending.append(item)
            return future
        if self._loop is not None and self._loop is not loop:
            # A drain runs on another event loop (an odd test setup): this one is solved alone.
            self._run(loop, [item])
            return future
        self._pending.append(item)
        if self._loop is None:
            self._loop = loop
            loop.call_soon(self._drain)
        return future

    async def solve(self, body, request_id: str | None = None, should_stop: Callable[[], bool] | None = None) -> dict:
        """:meth:`submit`, awaited."""
        return await self.submit(body, request_id, should_stop)

    def close(self) -> None:
        """Stop the worker thread once its drain (if any) ends."""
        self._worker.shutdown(wait=False)

    def _drain_inline(self, loop) -> None:
        taken = self._inline_pending.pop(loop)
        self.drains += 1
        self.inline_drains += 1
        self.solved += len(taken)
        methods_run: list = []
        try:
            results = fix_results([item[0] for item in taken], [item[1] for item in taken], self._stopping.is_set,
                                  methods_run, self._max_fix_cost)
        except Stopped as error:
            results, methods_run = [error] * len(taken), None
        except Exception as error:  # nobody may wait forever
            results, methods_run = [RuntimeError(f"the shared solve failed ({error!r})")] * len(taken), None
        self._resolve(taken, results, methods_run)

    def _drain(self) -> None:
        taken, self._pending = self._pending, []
        if not taken:
            self._loop = None
            return
        self._run(self._loop, taken, then=self._drain)

    def _run(self, loop, taken, then=None) -> None:
        self.drains += 1
        self.solved += len(taken)
        stops = [item[2] for item in taken]

        def should_stop() -> bool:
            return self._stopping.is_set() or all(stop() for stop in stops)

        methods_run: list = []
        try:
            work = loop.run_in_executor(self._worker, contextvars.copy_context().run, fix_results,
                                        [item[0] for item in taken], [item[1] for item in taken], should_stop,
                                        methods_run, self._max_fix_cost)
        except RuntimeError:  # the worker is shut down: the app is stopping
            work = loop.create_future()
            work.set_exception(Stopped())

        def finished(work: asyncio.Future) -> None:
            try:
                results, ran = work.result(), methods_run
            except Stopped as error:
                results, ran = [error] * len(taken), None
            except BaseException as error:  # cancelled with the loop or the worker: nobody may wait forever
                results, ran = [RuntimeError(f"the shared solve was cancelled ({error!r})")] * len(taken), None
            self._resolve(taken, results, ran)
            if then is not None:
                then()

        work.add_done_callback(finished)

    def _resolve(self, taken: list, results: list, methods_run: list | None) -> None:
        """Each taken request's future gets its result (or exception); metrics are told of a drain that solved
        (``methods_run``: the method of each body; None for a drain that stopped or failed)."""
        if self._metrics is not None and methods_run is not None:
            now = time.perf_counter()
            self._metrics.fixes_done(methods_run, results, [now - item[4] for item in taken])
        for (*_, future, _), result in zip(taken, results):
            if future.done():  # a request whose client went away was cancelled
                continue
            if isinstance(result, BaseException):
                future.set_exception(result)
            else:
                future.set_result(result)

