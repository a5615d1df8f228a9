"""Typed dependencies shared by the routers (all run on the event loop: no thread hop for a header check)."""

from __future__ import annotations

import json
from typing import Annotated, Any

import orjson
from fastapi import Depends, Request
from fastapi.exceptions import RequestValidationError

from service.settings import Settings
from service.web.auth import unauthorized
from service.web.problems import ApiError


async def get_settings(request: Request) -> Settings:
    return request.app.state.settings


def get_owner(request: Request) -> str:
    """The caller's identity as the middleware worked it out (:mod:`service.web.auth`): the digest prefix of its
    bearer key, or ``anonymous`` when keys are off.

    Raises 401 (``WWW-Authenticate: Bearer``, RFC 6750) without a configured key when keys are configured
    (the middleware already answered it for every ``/v1/`` path, before reading the body).
    """
    identity = request.scope["state"]["identity"]
    if identity.owner is None:
        raise unauthorized(identity)
    return identity.owner


async def _owner(request: Request) -> str:
    return get_owner(request)


def parse_json(raw: bytes) -> Any:
    """A body parsed by orjson; malformed JSON is the same 400 as anywhere else in the service.

    ``NaN`` and ``Infinity`` literals (not JSON, but what some clients write for non-finite floats) are
    parsed, so that validation names the field that holds them in a 422.
    """
    try:
        return orjson.loads(raw)
    except orjson.JSONDecodeError as error:
        try:
            return json.loads(raw)
        except (ValueError, RecursionError):
            pass
        raise RequestValidationError([{"type": "json_invalid", "loc": ("body", error.pos), "msg": "JSON decode error",
                                       "input": {}, "ctx": {"error": error.msg}}]) from None


def request_id(request: Request) -> str | None:
    return request.scope.get("state", {}).get("request_id")


def json_request_body(model) -> dict:
    """An OpenAPI ``requestBody`` for routes that read their body themselves."""
    return {"required": True, "content": {"application/json": {"schema": {"$ref": f"#/components/schemas/{model.__name__}"}}}}


SettingsDep = Annotated[Settings, Depends(get_settings)]
OwnerDep = Annotated[str, Depends(_owner)]
