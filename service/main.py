"""ASGI entry point for servers: ``uvicorn service.main:app`` (settings from the environment)."""

from service.ops.kernel_cache import usable_cache_dir

usable_cache_dir()  # before any kernel is imported: numba skips a read-only cache directory

from service.app import create_app  # noqa: E402

app = create_app()
