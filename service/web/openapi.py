"""The OpenAPI document as generated clients need it: every error declared, as it is sent.

FastAPI's generated document is completed here, once per app, by rules that
follow from how the service answers (so a new route gets them too):

- every error status an operation can answer is declared, with
  ``application/problem+json`` and the typed :class:`service.schemas.Problem`
  (FastAPI declares ``application/json`` and its own ``HTTPValidationError``,
  which this service never sends): 500 and 429 everywhere (the middleware's
  last resort and rate limit); 400, 413, 415 and 422 where there is a JSON
  body; 422 where there are query or path parameters; 401 and 403 on
  ``/v1/`` (every route there depends on :func:`service.web.deps.get_owner`);
  503 where the session store is used; whatever a route declares itself (404, 409, 412,
  503) with its own description;
- ``components.securitySchemes.bearer`` and, on the operations that check a
  key, ``security`` (bearer, or none when the service runs without keys);
- request bodies, responses and event-stream items given inline with a title
  become named components, so clients get readable model names; the models
  that routes reading their own body refer to (``FixRequest``) are added.
"""

from __future__ import annotations

from fastapi import FastAPI
from fastapi.openapi.utils import get_openapi

from service.web.auth import protects
from service.web.problems import MEDIA_TYPE

PROBLEM_REF = {"$ref": "#/components/schemas/Problem"}

_RETRY_AFTER = {"Retry-After": {"description": "seconds to wait before retrying", "schema": {"type": "integer"}}}

#: Status -> (description, headers) for statuses a route does not describe itself.
DEFAULT_ERRORS = {
    400: ("the body is not valid JSON, or a header field is malformed or sent twice (code invalid_header)", None),
    401: ("a bearer key is required (keys are configured) and none was sent",
          {"WWW-Authenticate": {"description": "Bearer", "schema": {"type": "string"}}}),
    403: ("the bearer key is not one of the configured keys", None),
    404: ("not found", None),
    413: ("the body is larger than the configured limit", None),
    415: ("the body is not application/json", None),
    422: ("invalid values, with the field path in errors[].loc", None),
    429: ("over the configured rate limit", _RETRY_AFTER),
    500: ("a bug: logged with the request id, which the body quotes", None),
    503: ("the session store is unavailable or busy; retry", _RETRY_AFTER),
}

_FASTAPI_VALIDATION = ("HTTPValidationError", "ValidationError")


def _has_parameters(operation: dict) -> bool:
    return any(p.get("in") in ("query", "path") for p in operation.get("parameters", []))


def _error_statuses(operation: dict, checks_key: bool, uses_store: bool) -> set[int]:
    statuses = {400, 429, 500}  # 400: every request's header fields are parsed (service.web.headers)
    if "requestBody" in operation:
        statuses |= {413, 415, 422}
    if _has_parameters(operation):
        statuses.add(422)
    if checks_key:
        statuses |= {401, 403}
    if uses_store:
        statuses.add(503)
    return statuses


def _problem_response(description: str, headers: dict | None) -> dict:
    response = {"description": description, "content": {MEDIA_TYPE: {"schema": PROBLEM_REF}}}
    if headers:
        response["headers"] = headers
    return response


def _name_inline_schemas(spec: dict) -> None:
    """Inline request and response schemas that have a title become components of that name (a generated client
    names its models after them, not after the operation and status)."""
    schemas = spec["components"]["schemas"]
    for operations in spec["paths"].values():
        for operation in operations.values():
            contents = [operation.get("requestBody", {}).get("content", {})]
            contents += [response.get("content", {}) for response in operation.get("responses", {}).values()]
            for media in (media for content in contents for media in content.values()):
                for key in ("schema", "itemSchema"):
                    schema = media.get(key, {})
                    title = schema.get("title")
                    if "$ref" not in schema and title and title not in schemas:
                        defs = schema.pop("$defs", {})
                        schemas[title] = schema
                        for name, definition in defs.items():
                            schemas.setdefault(name, definition)
                        media[key] = {"$ref": f"#/components/schemas/{title}"}


def build(app: FastAPI) -> dict:
    """The app's OpenAPI document, completed (see the module docstring)."""
    spec = get_openapi(title=app.title, version=app.version, summary=app.summary, description=app.description,
                       routes=app.routes)
    for path, operations in spec["paths"].items():
        for method, operation in operations.items():
            checks_key = protects(path)
            uses_store = path.startswith("/v1/sessions") or path == "/readyz"
            responses = operation["responses"]
            declared = {int(code) for code in responses if code.isdigit() and int(code) >= 400}
            for status in sorted(declared | _error_statuses(operation, checks_key, uses_store)):
                description, headers = DEFAULT_ERRORS.get(status, ("error", None))
                given = responses.get(str(status), {})
                if status in declared and given.get("description") not in (None, "Validation Error"):
                    description = given["description"]
                headers = {**(headers or {}), **given.get("headers", {})} or None
                responses[str(status)] = _problem_response(description, headers)
            operation["responses"] = dict(sorted(responses.items()))
            if checks_key:
                operation["security"] = [{"bearer": []}, {}]
    components = spec.setdefault("components", {})
    for name in _FASTAPI_VALIDATION:
        components.get("schemas", {}).pop(name, None)
    components["securitySchemes"] = {"bearer": {
        "type": "http", "scheme": "bearer",
        "description": "An API key as a bearer token, when the service is configured with keys (otherwise no "
                       "authentication); sessions belong to the key that created them."}}
    _name_inline_schemas(spec)
    _add_body_models(spec)
    return spec


def _add_body_models(spec: dict) -> None:
    """Components of the request models that routes reading their own body document by reference."""
    from service.schemas import FixRequest

    components = spec["components"].setdefault("schemas", {})
    for model in (FixRequest,):
        schema = model.model_json_schema(ref_template="#/components/schemas/{model}")
        for name, definition in schema.pop("$defs", {}).items():
            components.setdefault(name, definition)
        components.setdefault(model.__name__, schema)


def install(app: FastAPI) -> None:
    """Serve :func:`build`'s document at ``/openapi.json`` (built once)."""

    def openapi() -> dict:
        if app.openapi_schema is None:
            app.openapi_schema = build(app)
        return app.openapi_schema

    app.openapi = openapi
