"""Concurrent single fixes share one batched solve.

``POST /v1/fixes`` validates and translates each request on its own, then
hands ``(problem, method, options)`` to the app's :class:`Coalescer`. One
drain at a time takes *everything queued at that moment* (there is no
waiting window: a lone request on an idle service is solved at once, alone)
and runs :func:`core.estimators.solve_many` on a worker thread, so ML
problems that arrived together share one batched Levenberg-Marquardt and
one batched error summary; other methods run as they would alone. Requests
that arrive while a solve is running queue up for the next drain.

A problem's result is what a lone :func:`core.estimators.solve` gives it
(the batched core is row-independent); its :class:`~core.errors.LocalizationError`
stays its own. If the shared solve fails with anything else (a bug), every
problem of that drain is solved again alone, so the bug fails only the
request that triggers it.

The coalescer belongs to one app (``app.state``) and binds to no event loop
until a drain runs; a drain ends in the same step that resolves its last
futures, so nothing is left running when the loop goes idle.
"""

from __future__ import annotations

import asyncio
import logging
from dataclasses import dataclass

import numpy as np
from starlette.concurrency import run_in_threadpool

from core.accuracy import ErrorSummary, error_summary
from core.errors import LocalizationError
from core.estimators import Fix, SolveOptions, solve, solve_many
from core.problem import Problem

logger = logging.getLogger("passive_locator")


@dataclass(frozen=True)
class Solved:
    """One request's share of a drain: its fix and the drain's error summaries (``summary`` row ``index``)."""

    fix: Fix
    summary: ErrorSummary
    index: int


def solve_together(items: list[tuple[Problem, str, SolveOptions]]) -> list[Solved | BaseException]:
    """Solve problems as one :func:`solve_many` call; each gets its :class:`Solved` or its own exception.

    A failure of the shared call that is not a :class:`LocalizationError`
    falls back to solving each problem alone, so one problem's bug fails only it.
    """
    try:
        fixes: list = solve_many([p for p, _, _ in items], [m for _, m, _ in items], [o for _, _, o in items])
    except Exception:
        logger.exception("shared solve of %d problems failed; solving each alone", len(items))
        fixes = []
        for problem, method, options in items:
            try:
                fixes.append(solve(problem, method, options))
            except Exception as error:
                fixes.append(error)
    good = [i for i, fix in enumerate(fixes) if isinstance(fix, Fix)]
    out: list[Solved | BaseException] = list(fixes)
    if good:
        try:
            summary = error_summary(np.stack([fixes[i].covariance_enu_m2 for i in good]))
            for k, i in enumerate(good):
                out[i] = Solved(fixes[i], summary, k)
        except Exception:
            logger.exception("shared error summary of %d fixes failed; summarising each alone", len(good))
            for i in good:
                try:
                    out[i] = Solved(fixes[i], error_summary(fixes[i].covariance_enu_m2), 0)
                except Exception as error:
                    out[i] = error
    return out


class Coalescer:
    """Queues single problems and solves whatever is queued together, one drain at a time.

    Attributes
    ----------
    drains, solved : int
        How many shared solves ran and how many problems they took (for tests and metrics).
    """

    def __init__(self) -> None:
        self._pending: list[tuple[Problem, str, SolveOptions, asyncio.Future]] = []
        self._loop: asyncio.AbstractEventLoop | None = None
        self.drains = 0
        self.solved = 0

    async def solve(self, problem: Problem, method: str, options: SolveOptions) -> Solved:
        """The fix of one problem, solved together with whatever else is queued.

        Raises
        ------
        LocalizationError
            As :func:`core.estimators.solve` would for this problem alone.
        """
        loop = asyncio.get_running_loop()
        if self._loop is not None and self._loop is not loop:
            # A drain runs on another event loop (an odd test setup): solve this one alone, off the loop.
            (result,) = await run_in_threadpool(solve_together, [(problem, method, options)])
            return _unwrap(result)
        future = loop.create_future()
        self._pending.append((problem, method, options, future))
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
                try:
                    results = await run_in_threadpool(solve_together, [item[:3] for item in taken])
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


def _unwrap(result: Solved | BaseException) -> Solved:
    if isinstance(result, BaseException):
        raise result
    return result
