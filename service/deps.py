"""Typed dependencies shared by the routers (all run on the event loop: no thread hop for a header check)."""

from __future__ import annotations

from typing import Annotated

from fastapi import Depends, Request

from service.auth import authenticate, key_digest, owner_of
from service.problems import ApiError
from service.settings import Settings


async def get_settings(request: Request) -> Settings:
    return request.app.state.settings


def get_owner(request: Request) -> str:
    """The caller's identity: the digest prefix of its bearer key, or ``anonymous`` when keys are off.

    Raises 401 (``WWW-Authenticate: Bearer``, RFC 6750) without a key or with a wrong one when keys are
    configured.
    """
    digests: frozenset[bytes] = request.app.state.key_digests
    if not digests:
        return "anonymous"
    header = request.headers.get("authorization")
    digest = authenticate(header, digests)
    if digest is None:
        if key_digest(header) is None:
            raise ApiError(401, "unauthorized", "missing bearer key (Authorization: Bearer <key>)",
                           headers={"WWW-Authenticate": 'Bearer realm="passive-locator"'})
        raise ApiError(401, "unauthorized", "unknown bearer key",
                       headers={"WWW-Authenticate": 'Bearer realm="passive-locator", error="invalid_token"'})
    return owner_of(digest)


async def _owner(request: Request) -> str:
    return get_owner(request)


SettingsDep = Annotated[Settings, Depends(get_settings)]
OwnerDep = Annotated[str, Depends(_owner)]
