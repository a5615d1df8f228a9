"""Session stores behind one interface, chosen by URL (``sqlite:///path`` or ``redis://host:port/db``)."""

from __future__ import annotations

from service.stores.base import Clock, SessionRecord, SessionStore


def store_kind(url: str) -> str:
    """``"sqlite"`` or ``"redis"`` for a store URL; ValueError for an unknown scheme."""
    if url.startswith("sqlite://"):
        return "sqlite"
    if url.startswith(("redis://", "rediss://", "unix://")):
        return "redis"
    raise ValueError(f"unknown session store URL {url!r}: use sqlite:///path or redis://host:port/db")


def open_store(url: str, clock: Clock | None = None, timeout_s: float | None = None) -> SessionStore:
    """Open the store a URL names.

    Parameters
    ----------
    url : str
        ``sqlite:///relative/path``, ``sqlite:////absolute/path``, ``sqlite:///:memory:``, or
        ``redis://host:port/db`` with an optional ``?key_prefix=...``.
    clock : callable, optional
        Unix seconds for expiry; default :func:`time.time`.
    timeout_s : float, optional
        Redis connect and read timeout, or SQLite busy timeout (the backend's default when None).

    Raises
    ------
    ValueError
        For an unknown scheme.
    """
    kind = store_kind(url)
    extra = {} if timeout_s is None else {"timeout_s": timeout_s}
    if kind == "sqlite":
        from service.stores.sqlite import SqliteStore

        return SqliteStore.from_url(url, clock, **extra)
    from service.stores.redis import RedisStore

    return RedisStore.from_url(url, clock, **extra)


__all__ = ["SessionRecord", "SessionStore", "open_store", "store_kind"]
