"""problem+json (RFC 9457) responses, and the one place errors are mapped to them.

Core raises :class:`core.errors.LocalizationError` subclasses and the session
stores raise :class:`service.stores.base.StoreError` subclasses; each maps to
a status and a code here. Anything unmapped is a bug: logged with the request
id and answered 500.
"""

from __future__ import annotations

import logging
import math

import orjson
from fastapi import FastAPI, Request
from fastapi.exceptions import RequestValidationError
from starlette.exceptions import HTTPException as StarletteHTTPException
from starlette.responses import Response
from starlette.routing import Match

from core.errors import LocalizationError
from service.stores.base import StoreError

logger = logging.getLogger("passive_locator")

PROBLEM_BASE = "https://passive-locator.dev/problems/"
MEDIA_TYPE = "application/problem+json"

_TITLES = {
    400: "Malformed request",
    401: "Authentication required",
    403: "Forbidden",
    404: "Not found",
    405: "Method not allowed",
    406: "Not acceptable",
    409: "Conflict",
    412: "Precondition failed",
    408: "Request timeout",
    413: "Request body too large",
    415: "Unsupported media type",
    422: "Unprocessable request",
    429: "Too many requests",
    431: "Request header fields too large",
    500: "Internal server error",
    503: "Service unavailable",
}

#: Tokens pydantic inserts in error locations that are not field names.
_LOC_NOISE = {"body", "bearing", "range", "toa", "geodetic", "local", "function-after", "tagged-union",
              "observer_session", "network_session", "fix_evaluation", "network_evaluation",
              "multi_emitter_evaluation"}


class ApiError(Exception):
    """An HTTP error with a problem+json body, raised by routes and stores."""

    def __init__(self, status: int, code: str, detail: str, errors: list[dict] | None = None,
                 headers: dict[str, str] | None = None):
        super().__init__(detail)
        self.status, self.code, self.detail = status, code, detail
        self.errors = errors or []
        self.headers = headers or {}


def problem_body(status: int, code: str, detail: str, errors=None, request_id: str | None = None) -> dict:
    return {
        "type": PROBLEM_BASE + code,
        "title": _TITLES.get(status, "Error"),
        "status": status,
        "detail": detail,
        "code": code,
        "errors": errors or [],
        **_request_fields(request_id),
    }


def _request_fields(request_id: str | None) -> dict:
    return {"instance": None if request_id is None else f"urn:passive-locator:request:{request_id}",
            "request_id": request_id}


def for_request(body: dict, request_id: str | None) -> dict:
    """A problem body made without a request (a core error, a batch slot), tied to the request's id."""
    body.update(_request_fields(request_id))
    return body


def problem_response(status: int, code: str, detail: str, errors=None, request_id=None, headers=None) -> Response:
    return Response(orjson.dumps(problem_body(status, code, detail, errors, request_id)), status_code=status,
                    media_type=MEDIA_TYPE, headers=headers)


def clean_loc(loc) -> list:
    """A pydantic location without the ``body`` prefix and union tags."""
    return [part for part in loc if not (isinstance(part, str) and (part in _LOC_NOISE or part.startswith("function-")))]


#: A store that cannot serve a request now: the client retries after ``Retry-After``.
STORE_STATUS = 503


def store_headers(error: StoreError) -> dict[str, str]:
    """``Retry-After`` of a store error: whole seconds, at least 1."""
    return {"Retry-After": str(max(1, math.ceil(error.retry_after_s)))}


def localization_status(error: LocalizationError) -> tuple[int, str]:
    return 422, error.code


#: Core names in an error's ``loc`` -> the API's field path: the one table between the two.
API_PATH = {
    "azimuth_rad": ("azimuth_deg",),
    "elevation_rad": ("elevation_deg",),
    "sigma_azimuth_rad": ("sigma_azimuth_deg",),
    "sigma_elevation_rad": ("sigma_elevation_deg",),
    "lat_rad": ("lat_deg",),
    "lon_rad": ("lon_deg",),
    "altitude_m": ("constraints", "altitude_m"),
    "initial_guess": ("options", "initial_guess"),
    "variant": ("options", "variant"),
    "loss": ("options", "loss"),
    "loss_scale": ("options", "loss_scale"),
}


def api_loc(loc) -> list:
    """A core error's ``loc`` as the API's field path (:data:`API_PATH`)."""
    out: list = []
    for part in loc:
        out.extend(API_PATH.get(part, (part,)) if isinstance(part, str) else (part,))
    return out


def localization_problem(error: LocalizationError, prefix: tuple = ()) -> dict:
    """The problem body for a core error (also used per slot in a batch)."""
    status, code = localization_status(error)
    errors = [{"loc": [*prefix, *api_loc(error.loc)], "msg": error.message}] if error.loc else []
    return problem_body(status, code, error.message, errors)


def validation_errors(errors, prefix: tuple = ()) -> list[dict]:
    return [{"loc": [*prefix, *clean_loc(e["loc"])], "msg": e["msg"], "type": e.get("type")} for e in errors]


_METHODS = ("DELETE", "GET", "HEAD", "OPTIONS", "PATCH", "POST", "PUT")


def allowed_methods(request: Request) -> list[str]:
    """Every method some route serves at this request's path (the router reports only the first route's)."""
    return [method for method in _METHODS
            if any(route.matches({**request.scope, "method": method})[0] == Match.FULL
                   for route in request.app.router.routes)]


def _request_id(request: Request) -> str | None:
    return request.scope.get("state", {}).get("request_id")


def install(app: FastAPI) -> None:
    """Register every exception handler of the service."""

    @app.exception_handler(RequestValidationError)
    async def _validation(request: Request, exc: RequestValidationError):
        errors = exc.errors()
        if any(e.get("type") == "json_invalid" for e in errors):
            detail = "; ".join(str(e.get("ctx", {}).get("error", e["msg"])) for e in errors)
            return problem_response(400, "malformed_json", f"the body is not valid JSON: {detail}",
                                    request_id=_request_id(request))
        cleaned = validation_errors(errors)
        first = cleaned[0] if cleaned else {"loc": [], "msg": "invalid request"}
        detail = f"{'.'.join(map(str, first['loc'])) or 'body'}: {first['msg']}"
        return problem_response(422, "invalid_input", detail, cleaned, _request_id(request))

    @app.exception_handler(LocalizationError)
    async def _localization(request: Request, exc: LocalizationError):
        body = for_request(localization_problem(exc), _request_id(request))
        return Response(orjson.dumps(body), status_code=body["status"], media_type=MEDIA_TYPE)

    @app.exception_handler(ApiError)
    async def _api(request: Request, exc: ApiError):
        return problem_response(exc.status, exc.code, exc.detail, exc.errors, _request_id(request), exc.headers)

    @app.exception_handler(StoreError)
    async def _store(request: Request, exc: StoreError):
        return problem_response(STORE_STATUS, exc.code, exc.detail, request_id=_request_id(request),
                                headers=store_headers(exc))

    @app.exception_handler(StarletteHTTPException)
    async def _http(request: Request, exc: StarletteHTTPException):
        code = {404: "not_found", 405: "method_not_allowed"}.get(exc.status_code, "http_error")
        headers = dict(getattr(exc, "headers", None) or {})
        if exc.status_code == 405:
            headers["Allow"] = ", ".join(allowed_methods(request))
        return problem_response(exc.status_code, code, str(exc.detail), request_id=_request_id(request),
                                headers=headers)

    @app.exception_handler(Exception)
    async def _bug(request: Request, exc: Exception):
        rid = _request_id(request)
        logger.exception("unhandled error", exc_info=exc)
        return problem_response(500, "internal_error", f"internal error; quote request id {rid}", request_id=rid)
