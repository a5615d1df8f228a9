"""Typed dependencies shared by the routers."""

from __future__ import annotations

import hashlib
import hmac
from typing import Annotated

from fastapi import Depends, Request

from service.problems import ApiError
from service.settings import Settings


def get_settings(request: Request) -> Settings:
    return request.app.state.settings


def get_owner(request: Request) -> str:
    """The caller's identity: a digest of its bearer key, or ``anonymous`` when keys are off.

    Raises 401 without a key and 403 with a wrong one when keys are configured.
    """
    keys: list[str] = request.app.state.settings.api_keys
    if not keys:
        return "anonymous"
    header = request.headers.get("authorization", "")
    scheme, _, key = header.partition(" ")
    if scheme.lower() != "bearer" or not key:
        raise ApiError(401, "unauthorized", "missing bearer key", headers={"WWW-Authenticate": "Bearer"})
    if not any(hmac.compare_digest(key.encode(), k.encode()) for k in keys):
        raise ApiError(403, "forbidden", "unknown key")
    return hashlib.sha256(key.encode()).hexdigest()[:32]


SettingsDep = Annotated[Settings, Depends(get_settings)]
OwnerDep = Annotated[str, Depends(get_owner)]
