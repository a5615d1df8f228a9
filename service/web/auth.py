"""Who a request is: bearer keys checked against configured SHA-256 digests (the service never holds a key).

The middleware works out a request's :class:`Identity` once, from its parsed ``Authorization``
(:mod:`service.web.headers`) and its peer address, before it reads any body; authentication (the 401), the rate
limiter's bucket and the owner that sessions are stored under all come from that one value, so they cannot
disagree about who is asking.
"""

from __future__ import annotations

import hashlib
import hmac
from dataclasses import dataclass

from service.web.headers import Credentials
from service.web.problems import ApiError

#: Paths whose every route depends on the caller's identity (and that answer 401 without a key when keys
#: are configured); the probes, the docs and the OpenAPI document stay open.
PROTECTED_PREFIX = "/v1/"

_CHALLENGE = 'Bearer realm="passive-locator"'


def protects(path: str) -> bool:
    """Whether a request to ``path`` needs a key (when keys are configured)."""
    return path.startswith(PROTECTED_PREFIX)


@dataclass(frozen=True)
class Identity:
    """Who a request is, as authentication and the rate limiter both see it.

    Attributes
    ----------
    owner : str or None
        The owner id sessions are stored under (``anonymous`` when keys are off); None when keys are
        configured and the request has no configured key.
    limiter_key : bytes
        The rate limiter's bucket: ``key:<digest>`` for an authenticated key, else ``addr:<peer address>``
        (a made-up key buys no fresh bucket).
    presented : bool
        Whether a bearer key was sent (a wrong key and a missing one are told apart in the 401).
    """

    owner: str | None
    limiter_key: bytes
    presented: bool


def key_digest(credentials: Credentials | None) -> bytes | None:
    """The lower-case hex SHA-256 of the key of ``Authorization: Bearer <key>``; None without one."""
    if credentials is None or credentials.scheme != "bearer" or not credentials.token:
        return None
    return hashlib.sha256(credentials.token).hexdigest().encode()


def authenticate(credentials: Credentials | None, digests: frozenset[bytes]) -> bytes | None:
    """The digest of a configured key, or None (no key, or a wrong one).

    The presented key's digest is compared with every configured digest in
    constant time, each comparison made whatever the others gave, so neither
    the time nor the number of comparisons tells which digest came close.
    """
    digest = key_digest(credentials)
    if digest is None:
        return None
    found = False
    for configured in digests:
        found |= hmac.compare_digest(digest, configured)
    return digest if found else None


def identify(credentials: Credentials | None, digests: frozenset[bytes], peer: str) -> Identity:
    """The request's one identity (see :class:`Identity`); ``digests`` empty means authentication is off."""
    address = b"addr:" + peer.encode("ascii", "backslashreplace")
    if not digests:
        return Identity("anonymous", address, key_digest(credentials) is not None)
    digest = authenticate(credentials, digests)
    if digest is None:
        return Identity(None, address, key_digest(credentials) is not None)
    return Identity(owner_of(digest), b"key:" + digest, True)


def unauthorized(identity: Identity | None, detail: str | None = None) -> ApiError:
    """The 401 (``WWW-Authenticate: Bearer``, RFC 6750) for a request without a configured key, or with a
    malformed ``Authorization`` (``detail``; ``identity`` None)."""
    if detail is not None:
        return ApiError(401, "unauthorized", detail,
                        headers={"WWW-Authenticate": f'{_CHALLENGE}, error="invalid_request"'})
    if identity is None or not identity.presented:
        return ApiError(401, "unauthorized", "missing bearer key (Authorization: Bearer <key>)",
                        headers={"WWW-Authenticate": _CHALLENGE})
    return ApiError(401, "unauthorized", "unknown bearer key",
                    headers={"WWW-Authenticate": f'{_CHALLENGE}, error="invalid_token"'})


def owner_of(digest: bytes) -> str:
    """The owner id sessions are stored under: the first 32 hex digits of the key's digest."""
    return digest[:32].decode()
