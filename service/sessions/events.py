"""Session update events: published after every post that applied epochs, streamed as server-sent events.

Two buses behind one interface, chosen by the session store:

- with the Redis store, Redis pub/sub (channel ``<key prefix>events:<session id>``), so a subscriber on
  one replica hears the updates that any replica applies;
- with SQLite, an in-process bus, plus a poll of the store every ``Settings.events_poll_s`` seconds for what other
  worker processes on the same file applied.

An event carries only the session id and its new version; a subscriber then reads the state it streams
from the store (under its own key), so nothing of a session travels on a channel. A slow subscriber
never holds up a post: it keeps only the latest notice (states are cumulative), and what it streams is
always the latest state.
"""

from __future__ import annotations

import asyncio
import logging
import threading

import orjson

logger = logging.getLogger("passive_locator")

#: Seconds between keep-alive comments on an idle stream with Redis (without it, ``Settings.events_poll_s``).
HEARTBEAT_S = 15.0


class LocalBus:
    """Publish to subscribers in this process (thread-safe: posts run on worker threads)."""

    #: Whether :meth:`publish` may block (then the routes call it off the event loop).
    blocking = False

    def __init__(self, metrics=None, poll_s: float = 2.0):
        self.metrics, self.poll_s = metrics, poll_s
        self._lock = threading.Lock()
        self._subscribers: dict[str, set[tuple[asyncio.AbstractEventLoop, asyncio.Queue]]] = {}

    def publish(self, session_id: str, version: int) -> None:
        with self._lock:
            targets = list(self._subscribers.get(session_id, ()))
        for loop, queue in targets:
            try:
                loop.call_soon_threadsafe(_offer, queue, version)
            except RuntimeError:  # that subscriber's loop has closed: nobody is listening there any more
                pass

    def subscribe(self, session_id: str) -> "Subscription":
        queue: asyncio.Queue = asyncio.Queue(maxsize=1)
        entry = (asyncio.get_running_loop(), queue)
        with self._lock:
            self._subscribers.setdefault(session_id, set()).add(entry)

        def close():
            with self._lock:
                found = self._subscribers.get(session_id)
                if found is not None:
                    found.discard(entry)
                    if not found:
                        del self._subscribers[session_id]

        return Subscription(queue, close, poll_s=self.poll_s, metrics=self.metrics)

    def close(self) -> None:
        pass


def _offer(queue: asyncio.Queue, version: int) -> None:
    """Keep only the newest notice."""
    while not queue.empty():
        queue.get_nowait()
    queue.put_nowait(version)


class Subscription:
    """Notices of new versions of one session.

    :meth:`next` waits up to ``timeout_s`` and returns a version, or None on timeout (the stream then
    sends a keep-alive and, without Redis, polls the store).
    """

    def __init__(self, queue: asyncio.Queue, close, poll_s: float | None = None, task: asyncio.Task | None = None,
                 ready: asyncio.Event | None = None, metrics=None):
        self.queue, self._close, self.poll_s, self._task = queue, close, poll_s, task
        self._open_streams = None if metrics is None else metrics.event_streams
        if self._open_streams is not None:
            self._open_streams.inc()
        if ready is None:
            ready = asyncio.Event()
            ready.set()
        self.ready = ready

    async def next(self, timeout_s: float) -> int | None:
        try:
            return await asyncio.wait_for(self.queue.get(), timeout_s)
        except asyncio.TimeoutError:
            return None

    async def aclose(self) -> None:
        if self._open_streams is not None:
            self._open_streams.dec()
            self._open_streams = None
        if self._task is not None:
            self._task.cancel()
            try:
                await self._task
            except (asyncio.CancelledError, Exception):  # a failed listener has nothing more to say
                pass
        result = self._close()
        if asyncio.iscoroutine(result):
            await result


class RedisBus:
    """Redis pub/sub: posts publish with the store's own client; each stream listens on its own connection."""

    blocking = True

    def __init__(self, store, url: str, metrics=None):
        self.store, self.metrics = store, metrics
        from service.stores.redis import split_url

        self.url, _ = split_url(url)
        self._async_client = None

    def channel(self, session_id: str) -> str:
        return f"{getattr(self.store.backend(), 'prefix', '')}events:{session_id}"

    def publish(self, session_id: str, version: int) -> None:
        """Publish (blocking: call it off the event loop), never failing the post that applied the update
        (it is stored; streams poll on timeout)."""
        import redis

        try:
            self.store.backend().client.publish(self.channel(session_id), orjson.dumps({"version": version}))
        except (redis.RedisError, OSError) as error:
            logger.warning("session event for %s not published: %s", session_id, error)
            if self.metrics is not None:
                self.metrics.store_errors.labels("publish").inc()

    def subscribe(self, session_id: str) -> Subscription:
        import redis.asyncio

        if self._async_client is None:
            self._async_client = redis.asyncio.Redis.from_url(self.url, socket_connect_timeout=5.0)
        pubsub = self._async_client.pubsub(ignore_subscribe_messages=True)
        queue: asyncio.Queue = asyncio.Queue(maxsize=1)
        ready = asyncio.Event()

        async def listen():
            await pubsub.subscribe(self.channel(session_id))
            ready.set()
            async for message in pubsub.listen():
                if message.get("type") == "message":
                    _offer(queue, int(orjson.loads(message["data"])["version"]))

        task = asyncio.get_running_loop().create_task(listen())
        return Subscription(queue, pubsub.aclose, poll_s=None, task=task, ready=ready, metrics=self.metrics)

    def close(self) -> None:
        pass


def bus(app):
    """The app's event bus, made on first use from its store."""
    found = getattr(app.state, "event_bus", None)
    if found is None:
        store = app.state.store
        found = RedisBus(store, app.state.settings.store, app.state.metrics) if store.kind == "redis" else \
            LocalBus(app.state.metrics, app.state.settings.events_poll_s)
        app.state.event_bus = found
    return found


async def publish(app, session_id: str, version: int) -> None:
    """Publish a session's new version on the app's bus: on a worker thread when that may block (Redis), else
    here (the in-process bus only schedules wake-ups, cheaper than the hop to a thread)."""
    found = bus(app)
    if found.blocking:
        from starlette.concurrency import run_in_threadpool

        await run_in_threadpool(found.publish, session_id, version)
    else:
        found.publish(session_id, version)


def sse(event: str, data: bytes, event_id: int | None = None) -> bytes:
    """One server-sent event (data is one line of JSON)."""
    head = b"" if event_id is None else f"id: {event_id}\n".encode()
    return head + f"event: {event}\n".encode() + b"data: " + data + b"\n\n"
