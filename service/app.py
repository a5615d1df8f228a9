"""The application factory: ``create_app(settings)``.

The app owns its resources (the session store, metrics, rate limiter, the
thread pool of the CPU-bound routes) in its lifespan; nothing lives at module
level, so tests build as many apps as they like with different settings.
"""

from __future__ import annotations

import asyncio
import importlib.metadata
import logging
import threading
from concurrent.futures import ThreadPoolExecutor
from contextlib import asynccontextmanager

from fastapi import FastAPI

from service.ops import logs
from service.web import openapi, problems, browsers as web
from service.renderings import tak
from service.ops import kernel_cache
from service.fixes.coalesce import Coalescer
from service.fixes.pipeline import compile_kernels
from service.ops.metrics import InFlight, Metrics
from service.web.middleware import ServiceMiddleware, TokenBucket
from service.routes import ROUTERS
from service.settings import Settings
from service.stores import open_store, store_kind
from service.stores.base import StoreError
from service.stores.guard import GuardedStore

API_VERSION = importlib.metadata.version("passive-locator")

logger = logging.getLogger("passive_locator")


def make_store(settings: Settings) -> GuardedStore:
    """The app's store: opened on first use, guarded (bounded threads, deadline, breaker)."""
    url = settings.store

    def open_backend(clock):
        if store_kind(url) == "sqlite":
            from service.stores.sqlite import SqliteStore

            return SqliteStore.from_url(url, clock, settings.store_timeout_s, settings.sqlite_integrity_interval_s)
        return open_store(url, clock, settings.store_timeout_s)

    return GuardedStore(open_backend, store_kind(url), workers=settings.store_workers,
                        call_timeout_s=settings.store_call_timeout_s,
                        failure_threshold=settings.store_breaker_failures,
                        cooldown_s=settings.store_breaker_cooldown_s)


def create_app(settings: Settings | None = None) -> FastAPI:
    """Build the service.

    Parameters
    ----------
    settings : Settings, optional
        Default: read from the environment.
    """
    settings = settings or Settings()
    metrics = Metrics()
    logs.configure(settings.log_level, settings.log_format)

    @asynccontextmanager
    async def lifespan(app: FastAPI):
        store = make_store(settings)
        store.on_failure = lambda operation: metrics.store_errors.labels(operation).inc()
        app.state.store = store
        app.state.stopping = threading.Event()
        app.state.fix_coalescer = Coalescer(app.state.stopping, metrics, settings.max_fix_cost,
                                            settings.inline_fix_cost)
        app.state.cpu_pool = ThreadPoolExecutor(settings.cpu_workers, thread_name_prefix="cpu")
        await asyncio.get_running_loop().run_in_executor(app.state.cpu_pool, kernel_cache.load_kernels,
                                                         compile_kernels)
        try:
            await store.run(lambda backend: None)  # open now when we can; a store that is down opens later
        except StoreError as error:
            logger.warning("session store not available at start: %s", error.detail)
        try:
            yield
        finally:
            app.state.stopping.set()  # long computations stop at their next chunk
            app.state.cpu_pool.shutdown(wait=False, cancel_futures=True)
            app.state.fix_coalescer.close()
            tak.close(app)
            store.close()

    app = FastAPI(
        title="passive-locator",
        version=API_VERSION,
        summary="Locate radio emitters from passive bearings, ranges and times of arrival.",
        description=(
            "Fixes with covariance, the Cramer-Rao bound and error ellipse from azimuth/elevation bearings, "
            "ranges and TOAs; planning bounds; Monte Carlo evaluations; and sessions that track a moving "
            "emitter from one fixed observer. Errors are application/problem+json (RFC 9457)."
        ),
        lifespan=lifespan,
        docs_url=None,
        redoc_url=None,
    )
    app.state.settings = settings
    app.state.metrics = metrics
    app.state.key_digests = settings.key_digests()
    problems.install(app)
    openapi.install(app)
    web.install_docs(app)
    for router in ROUTERS:
        app.include_router(router)
    limiter = TokenBucket(settings.rate_limit_per_s, settings.rate_limit_burst, settings.rate_limit_clients) \
        if settings.rate_limit_per_s else None
    app.state.rate_limiter = limiter
    app.add_middleware(ServiceMiddleware, max_body_bytes=settings.max_body_bytes, metrics=metrics,
                       rate_limiter=limiter, key_digests=app.state.key_digests, routes=app.router.routes)
    app.add_middleware(InFlight, metrics=metrics)
    web.install_cors(app, settings.cors_allow_origins)
    return app
