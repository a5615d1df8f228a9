"""JSON responses serialised by orjson (fast, and it refuses nothing we emit: every float is finite)."""

from __future__ import annotations

from collections.abc import Mapping

import orjson
from starlette.responses import Response


class JsonObject(Mapping):
    """A JSON object already written as bytes, read as a mapping on demand.

    :func:`dumps` (and so :class:`JsonResponse`) writes the bytes as they are;
    its fields are parsed from them on first access, except those given as
    ``known`` (the same values, kept so that reading them parses nothing).

    Parameters
    ----------
    json : bytes
        The object's JSON text.
    known : dict, optional
        Some of its fields, as parsing ``json`` gives them.
    """

    __slots__ = ("_fields", "_known", "json")

    def __init__(self, json: bytes, known: dict | None = None):
        self.json = json
        self._known = known or {}
        self._fields = None

    @property
    def fields(self) -> dict:
        if self._fields is None:
            self._fields = orjson.loads(self.json)
        return self._fields

    def __getitem__(self, key):
        known = self._known.get(key, self)
        return self.fields[key] if known is self else known

    def __iter__(self):
        return iter(self.fields)

    def __len__(self) -> int:
        return len(self.fields)

    def __repr__(self) -> str:
        return f"JsonObject({self.json!r})"


def _written(value):
    if type(value) is JsonObject:
        return orjson.Fragment(value.json)
    raise TypeError(f"{type(value).__name__} is not JSON serialisable")


def dumps(content) -> bytes:
    """JSON bytes of ``content``: dicts, lists, numbers, strings, numpy arrays and :class:`JsonObject` values."""
    return orjson.dumps(content, option=orjson.OPT_SERIALIZE_NUMPY, default=_written)


class JsonResponse(Response):
    media_type = "application/json"

    def render(self, content) -> bytes:
        return dumps(content)
