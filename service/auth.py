"""Bearer keys checked against configured SHA-256 digests (the service never holds a key itself)."""

from __future__ import annotations

import hashlib
import hmac


def key_digest(authorization: bytes | str | None) -> bytes | None:
    """The lower-case hex SHA-256 of the key in an ``Authorization: Bearer <key>`` value; None without one."""
    if not authorization:
        return None
    if isinstance(authorization, str):
        authorization = authorization.encode("latin-1", "replace")
    scheme, _, key = authorization.strip().partition(b" ")
    key = key.strip()
    if scheme.lower() != b"bearer" or not key:
        return None
    return hashlib.sha256(key).hexdigest().encode()


def authenticate(authorization: bytes | str | None, digests: frozenset[bytes]) -> bytes | None:
    """The digest of a configured key, or None (no key, or a wrong one).

    The presented key's digest is compared with every configured digest in
    constant time, each comparison made whatever the others gave, so neither
    the time nor the number of comparisons tells which digest came close.
    """
    digest = key_digest(authorization)
    if digest is None:
        return None
    found = False
    for configured in digests:
        found |= hmac.compare_digest(digest, configured)
    return digest if found else None


def owner_of(digest: bytes) -> str:
    """The owner id sessions are stored under: the first 32 hex digits of the key's digest."""
    return digest[:32].decode()
