"""Every field a response can carry is described in the OpenAPI document (what a generated client's docstrings
and a reader of the spec see): the walk follows every response of every operation through references,
unions, arrays, maps, event-stream items and embedded JSON."""

from __future__ import annotations

import json

from scripts.write_openapi import render


def _undescribed(spec: dict) -> tuple[set[str], set[str]]:
    """Response properties without a description (``Schema.property``), and the named schemas walked."""
    components = spec["components"]["schemas"]
    missing: set[str] = set()
    walked: set[str] = set()

    def walk(schema: dict, where: str) -> None:
        if "$ref" in schema:
            name = schema["$ref"].rsplit("/", 1)[-1]
            if name not in walked:
                walked.add(name)
                walk(components[name], name)
            return
        for key in ("anyOf", "oneOf", "allOf", "prefixItems"):
            for member in schema.get(key, []):
                walk(member, where)
        for key in ("items", "additionalProperties", "contentSchema"):
            if isinstance(schema.get(key), dict):
                walk(schema[key], where)
        for name, field in schema.get("properties", {}).items():
            if not str(field.get("description", "")).strip():
                missing.add(f"{where}.{name}")
            walk(field, f"{where}.{name}")

    for path, operations in spec["paths"].items():
        for method, operation in operations.items():
            for status, response in operation["responses"].items():
                for media_type, media in response.get("content", {}).items():
                    for key in ("schema", "itemSchema"):
                        if key in media:
                            walk(media[key], f"{method.upper()} {path} {status} {media_type}")
    return missing, walked


def test_every_response_property_has_a_description():
    missing, walked = _undescribed(json.loads(render()))
    # the walk reaches the responses' models, nested ones included
    assert {"FixResponse", "ErrorSummary", "Ellipse", "Fit", "Residual", "BatchResult", "CrlbGridResponse",
            "CellProperties", "SessionState", "SessionEvent", "EvaluationResponse", "Problem"} <= walked
    assert not missing, "response properties without a description: " + ", ".join(sorted(missing))


def test_the_walk_finds_an_undescribed_property():
    spec = {"components": {"schemas": {"Inner": {"properties": {"bare": {"type": "number"}}}}},
            "paths": {"/x": {"get": {"responses": {"200": {"content": {"application/json": {"schema": {
                "anyOf": [{"type": "array", "items": {"$ref": "#/components/schemas/Inner"}}, {"type": "null"}]}}}}}}}}}
    assert _undescribed(spec)[0] == {"Inner.bare"}
