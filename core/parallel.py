"""Work split into chunks that run in this process or on a Dask distributed cluster.

A long computation (a Monte Carlo evaluation, a coverage map) is cut into
chunks of a fixed size that do not depend on how many workers there are;
chunk ``k`` of a seeded run draws from child ``k`` of the run's
``numpy.random.SeedSequence``. The result for a seed is then the same
whether the chunks run here, one after the other, or on any number of
Dask workers.
"""

from __future__ import annotations

from typing import Any, Callable, Sequence

import numpy as np


class Stopped(Exception):
    """The work stopped between chunks because ``should_stop`` said so (deadline, cancellation, shutdown)."""


def chunk_slices(total: int, per_chunk: int) -> list[slice]:
    """``[0, total)`` cut into consecutive slices of ``per_chunk`` items (the last may be shorter)."""
    per_chunk = max(1, int(per_chunk))
    return [slice(start, min(start + per_chunk, total)) for start in range(0, total, per_chunk)]


def chunk_seeds(seed: int | np.random.SeedSequence, count: int) -> list[np.random.SeedSequence]:
    """One independent child seed per chunk, fixed by the run's seed and the chunk's index alone."""
    root = seed if isinstance(seed, np.random.SeedSequence) else np.random.SeedSequence(seed)
    return root.spawn(count)


def run_chunks(function: Callable[..., Any], chunks: Sequence[tuple], *, scheduler: Any = None,
               should_stop: Callable[[], bool] | None = None,
               progress: Callable[[int, int], None] | None = None) -> list:
    """``[function(*chunk) for chunk in chunks]``, here or on a Dask cluster, in chunk order.

    Parameters
    ----------
    function : callable
        Pure: its result depends on its arguments only (a chunk carries its own seed).
        It must be importable by name on the workers when a scheduler is given.
    chunks : sequence of tuple
        The arguments of each call.
    scheduler : str or distributed.Client, optional
        A scheduler address (``"tcp://host:8786"``) or a connected client; None runs in this process.
    should_stop : callable returning bool, optional
        Asked before each chunk here, and as results arrive from a cluster (pending chunks are then
        cancelled); True raises :class:`Stopped`.
    progress : callable(done, total), optional
        Called after each finished chunk.

    Raises
    ------
    Stopped
        When ``should_stop`` returned True.
    """
    total = len(chunks)
    if scheduler is None:
        results = []
        for chunk in chunks:
            if should_stop is not None and should_stop():
                raise Stopped()
            results.append(function(*chunk))
            if progress is not None:
                progress(len(results), total)
        return results
    return _run_on_cluster(function, chunks, scheduler, should_stop, progress)


def _run_on_cluster(function, chunks, scheduler, should_stop, progress) -> list:
    from distributed import Client, as_completed

    client = scheduler if isinstance(scheduler, Client) else Client(scheduler)
    try:
        futures = [client.submit(function, *chunk, pure=False) for chunk in chunks]
        index = {future.key: k for k, future in enumerate(futures)}
        results: list = [None] * len(futures)
        done = 0
        for future in as_completed(futures):
            if should_stop is not None and should_stop():
                client.cancel(futures)
                raise Stopped()
            results[index[future.key]] = future.result()
            done += 1
            if progress is not None:
                progress(done, len(futures))
        return results
    finally:
        if client is not scheduler:
            client.close()
