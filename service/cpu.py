"""Long computations on the app's CPU pool: stopped at the request deadline, on disconnect and at shutdown.

The work runs on ``app.state.cpu_pool`` (never the threads or the loop that
serve the probes) and asks ``should_stop`` between its chunks. The route
awaits it while polling for a disconnected client; whatever ends the request
also tells the work to stop, so it stops using the CPU within one chunk.
"""

from __future__ import annotations

import asyncio
import threading
import time
from typing import Callable, TypeVar

from fastapi import Request

from service.problems import ApiError

T = TypeVar("T")

#: How often the route looks for a disconnected client while the work runs.
POLL_S = 0.2


async def run_stoppable(http: Request, work: Callable[[Callable[[], bool]], T], stopped: tuple[type, ...],
                        what: str, advice: str) -> T:
    """``work(should_stop)`` on the CPU pool; its ``stopped`` exceptions become 503 (deadline or shutdown).

    Parameters
    ----------
    http : Request
    work : callable(should_stop) -> result
        Raises one of ``stopped`` when ``should_stop()`` said True.
    stopped : tuple of exception types
    what : str
        Names the computation in the 503's detail ("the coverage map").
    advice : str
        What to ask for instead ("ask for a coarser grid").

    Raises
    ------
    ApiError
        499 ``client_closed``, 503 ``deadline_exceeded`` or ``shutting_down``.
    """
    settings = http.app.state.settings
    deadline = time.monotonic() + settings.request_deadline_s
    cancelled = threading.Event()
    stopping: threading.Event = http.app.state.stopping

    def should_stop() -> bool:
        return cancelled.is_set() or stopping.is_set() or time.monotonic() > deadline

    future = asyncio.get_running_loop().run_in_executor(http.app.state.cpu_pool, work, should_stop)
    try:
        while True:
            done, _ = await asyncio.wait({future}, timeout=POLL_S)
            if done:
                break
            if await http.is_disconnected():
                cancelled.set()
                future.cancel()
                raise ApiError(499, "client_closed", "the client went away")
        return future.result()
    except stopped:
        if time.monotonic() > deadline:
            raise ApiError(503, "deadline_exceeded",
                           f"{what} did not finish within request_deadline_s = {settings.request_deadline_s:g} s; "
                           f"{advice}", headers={"Retry-After": "1"}) from None
        raise ApiError(503, "shutting_down", "the server is shutting down; retry", headers={"Retry-After": "1"}) \
            from None
    finally:
        cancelled.set()  # the request is over, whatever ended it (a cancelled task at shutdown too)
