"""Session stores behind one interface, chosen by URL (``sqlite:///path`` or ``redis://host:port/db``)."""

from __future__ import annotations

from service.stores.base import SessionStore


def open_store(url: str) -> SessionStore:
    """Open the store a URL names.

    Raises
    ------
    ValueError
        For an unknown scheme.
    """
    if url.startswith("sqlite://"):
        from service.stores.sqlite import SqliteStore

        return SqliteStore.from_url(url)
    if url.startswith(("redis://", "rediss://", "unix://")):
        from service.stores.redis import RedisStore

        return RedisStore.from_url(url)
    raise ValueError(f"unknown session store URL {url!r}: use sqlite:///path or redis://host:port/db")


__all__ = ["SessionStore", "open_store"]
