"""The application factory: ``create_app(settings)``.

The app owns its resources (the session store, metrics, rate limiter) in its
lifespan; nothing lives at module level, so tests build as many apps as they
like with different settings.
"""

from __future__ import annotations

import importlib.metadata
import logging
from contextlib import asynccontextmanager

from fastapi import FastAPI

from service import openapi, problems, web
from service.coalesce import Coalescer
from service.metrics import InFlight, Metrics
from service.middleware import ServiceMiddleware, TokenBucket
from service.routes import ROUTERS
from service.settings import Settings
from service.stores import open_store

API_VERSION = importlib.metadata.version("passive-locator")


def create_app(settings: Settings | None = None) -> FastAPI:
    """Build the service.

    Parameters
    ----------
    settings : Settings, optional
        Default: read from the environment.
    """
    settings = settings or Settings()
    metrics = Metrics()

    @asynccontextmanager
    async def lifespan(app: FastAPI):
        store = open_store(settings.store)
        app.state.store = store
        app.state.fix_coalescer = Coalescer()
        try:
            yield
        finally:
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
    problems.install(app)
    openapi.install(app)
    web.install_docs(app)
    for router in ROUTERS:
        app.include_router(router)
    limiter = TokenBucket(settings.rate_limit_per_s, settings.rate_limit_burst) if settings.rate_limit_per_s else None
    app.add_middleware(ServiceMiddleware, max_body_bytes=settings.max_body_bytes, metrics=metrics,
                       rate_limiter=limiter)
    app.add_middleware(InFlight, metrics=metrics)
    web.install_cors(app, settings.cors_allow_origins)
    logging.getLogger("passive_locator").setLevel(settings.log_level.upper())
    return app
