"""Session stores behind one interface, chosen by URL (``sqlite:///path`` or ``redis://host:port/db``)."""

from __future__ import annotations

from service.stores.base import Clock, SessionRecord, SessionStore


def open_store(url: str, clock: Clock | None = None) -> SessionStore:
    """Open the store a URL names.

    Parameters
    ----------
    url : str
        ``sqlite:///relative/path``, ``sqlite:////absolute/path``, ``sqlite:///:memory:``, or
        ``redis://host:port/db`` with an optional ``?key_prefix=...``.
    clock : callable, optional
        Unix seconds for expiry; default :func:`time.time`.

    Raises
    ------
    ValueError
        For an unknown scheme.
    """
    if url.startswith("sqlite://"):
        from service.stores.sqlite import SqliteStore

        return SqliteStore.from_url(url, clock)
    if url.startswith(("redis://", "rediss://", "unix://")):
        from service.stores.redis import RedisStore

        return RedisStore.from_url(url, clock)
    raise ValueError(f"unknown session store URL {url!r}: use sqlite:///path or redis://host:port/db")


__all__ = ["SessionRecord", "SessionStore", "open_store"]
