"""What browsers need: the API docs served from this process (no CDN), and CORS when configured.

``/docs`` (Swagger UI) and ``/redoc`` load their scripts and styles from ``/docs/assets``, files that the
``fastapi-offline`` package ships (Swagger UI 5, which reads OpenAPI 3.1), so the docs work on a network
without Internet access. Cross-origin requests are refused unless ``PASSIVE_LOCATOR_CORS_ALLOW_ORIGINS``
names the origins allowed (a JSON list; ``["*"]`` for any, without credentials).
"""

from __future__ import annotations

import importlib.resources

from fastapi import FastAPI
from fastapi.openapi.docs import get_redoc_html, get_swagger_ui_html
from fastapi.staticfiles import StaticFiles
from starlette.middleware.cors import CORSMiddleware

ASSETS_URL = "/docs/assets"


def _assets_dir() -> str:
    return str(importlib.resources.files("fastapi_offline") / "static")


def install_docs(app: FastAPI) -> None:
    """Swagger UI at ``/docs`` and ReDoc at ``/redoc``, from local assets (create the app with docs_url=None)."""
    app.mount(ASSETS_URL, StaticFiles(directory=_assets_dir()), name="docs-assets")

    @app.get("/docs", include_in_schema=False)
    async def swagger_ui():
        return get_swagger_ui_html(openapi_url=app.openapi_url, title=f"{app.title} - API",
                                   swagger_js_url=f"{ASSETS_URL}/swagger-ui-bundle.js",
                                   swagger_css_url=f"{ASSETS_URL}/swagger-ui.css",
                                   swagger_favicon_url=f"{ASSETS_URL}/favicon.png")

    @app.get("/redoc", include_in_schema=False)
    async def redoc():
        return get_redoc_html(openapi_url=app.openapi_url, title=f"{app.title} - API",
                              redoc_js_url=f"{ASSETS_URL}/redoc.standalone.js",
                              redoc_favicon_url=f"{ASSETS_URL}/favicon.png", with_google_fonts=False)


def install_cors(app: FastAPI, allow_origins: list[str]) -> None:
    """Answer cross-origin requests from ``allow_origins`` (nothing is added when the list is empty)."""
    if not allow_origins:
        return
    app.add_middleware(
        CORSMiddleware, allow_origins=allow_origins, allow_credentials="*" not in allow_origins,
        allow_methods=["GET", "POST", "DELETE", "OPTIONS"],
        allow_headers=["Authorization", "Content-Type", "If-Match", "Last-Event-ID", "X-Request-ID"],
        expose_headers=["ETag", "Location", "Retry-After", "X-Request-ID"], max_age=600)
