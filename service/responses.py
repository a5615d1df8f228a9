"""JSON responses serialised by orjson (fast, and it refuses nothing we emit: every float is finite)."""

from __future__ import annotations

import orjson
from starlette.responses import Response


class JsonResponse(Response):
    media_type = "application/json"

    def render(self, content) -> bytes:
        return orjson.dumps(content, option=orjson.OPT_SERIALIZE_NUMPY)
