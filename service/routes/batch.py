"""Many independent fixes in one request: the throughput path (API.md ``POST /v1/fixes/batch``).

The problems go through :func:`~service.fixes.pipeline.fix_results`, the same
read, solve and write as ``POST /v1/fixes``; a problem's error stays in its
slot; the solve stops between parts at the request deadline, when the
client goes away or when the server stops (:mod:`service.web.watch`: 503
``deadline_exceeded``). The body is decoded here (:mod:`service.fixes.decode`), not by the framework, and the
cyclic garbage collector is paused while the request's million small objects
are made and dropped (it would otherwise rescan them over and over: about
five times the work of the parse itself).
"""

from __future__ import annotations

import gc
import threading
from contextlib import contextmanager
from typing import Annotated

from fastapi import APIRouter, Depends, Request
from fastapi.exceptions import RequestValidationError
from pydantic import ValidationError

from service import schemas
from service.renderings import tak
from service.web.deps import OwnerDep, parse_json, request_id
from service.limits import check_batch, fix_cost_context
from service.renderings.points import batch_geojson
from service.web.responses import JsonResponse
from service.fixes.pipeline import fix_results
from service.web.watch import in_pool, watched
from service.fixes.decode import decode_batch

router = APIRouter(prefix="/v1", tags=["fixes"])

MAX_PROBLEMS = next(rule.max_length for rule in schemas.BatchRequest.model_fields["problems"].metadata
                    if getattr(rule, "max_length", None) is not None)

_ERRORS = {
    400: {"model": schemas.Problem, "description": "the body is not valid JSON"},
    422: {"model": schemas.Problem, "description": "the body is not {\"problems\": [...]} with 1..10000 problems, "
                                                   "or the batch is over max_batch_cost (code over_limit)"},
    503: {"model": schemas.Problem, "description": "not finished within the request deadline (code "
                                                   "deadline_exceeded), or the server is shutting down"},
}


def _request_body_schema() -> dict:
    schema = schemas.BatchRequest.model_json_schema()
    schema["properties"]["problems"]["items"] = {"$ref": "#/components/schemas/FixRequest"}
    return {"required": True, "content": {"application/json": {"schema": schema}}}


_gc_lock = threading.Lock()
_gc_holders = 0
_gc_was_enabled = True


@contextmanager
def gc_paused():
    """Pause the cyclic garbage collector (process-wide) while any batch is in flight.

    Drop the request's objects before leaving: the first allocation after the
    collector is back runs a collection over everything allocated meanwhile
    that is still alive (35 ms for a live 10,000-problem request).
    """
    global _gc_holders, _gc_was_enabled
    with _gc_lock:
        if _gc_holders == 0:
            _gc_was_enabled = gc.isenabled()
            gc.disable()
        _gc_holders += 1
    try:
        yield
    finally:
        with _gc_lock:
            _gc_holders -= 1
            if _gc_holders == 0 and _gc_was_enabled:
                gc.enable()


async def _raw_body(request: Request) -> bytes:
    return await request.body()


RawBody = Annotated[bytes, Depends(_raw_body)]


def _problems(raw: bytes, max_fix_cost: int | None) -> tuple[list, list]:
    """The ``problems`` list and ``formats`` of a batch body; 400/422 as for any body when it is not one
    (a problem over ``max_fix_cost``, the app's limit, among the errors).

    The problems are :class:`service.fixes.decode.FixBody` structs when every one decodes as such, else parsed JSON.
    """
    problems = decode_batch(raw)
    if problems is not None and 0 < len(problems) <= MAX_PROBLEMS:
        return problems, []
    data = parse_json(raw)
    if type(data) is dict and data.keys() == {"problems"}:
        problems = data["problems"]
        if type(problems) is list and 0 < len(problems) <= MAX_PROBLEMS:
            return problems, []
    try:
        schemas.BatchRequest.model_validate(data, context=fix_cost_context(max_fix_cost))
    except ValidationError as error:
        raise RequestValidationError([{**e, "loc": ("body", *e["loc"])} for e in error.errors()]) from None
    return data["problems"], data.get("formats", [])


@router.post("/fixes/batch", operation_id="fixes-batch", summary="Locate many emitters, each from its own measurements",
             description="Up to 10,000 independent fix requests; results in request order. A malformed or "
                         "unsolvable problem is reported in its own slot (`ok: false` with a problem+json "
                         "`error` whose `loc` is relative to the problem) and never fails the others.",
             response_model=schemas.BatchResponse, responses=_ERRORS, openapi_extra={"requestBody": _request_body_schema()})
async def create_batch(owner: OwnerDep, raw: RawBody, request: Request) -> JsonResponse:
    def run(should_stop) -> JsonResponse:
        with gc_paused():
            settings = request.app.state.settings
            problems, formats = _problems(raw, settings.max_fix_cost)
            check_batch(problems, settings.max_batch_cost)
            methods_run: list = []
            results = fix_results(problems, request_id(request), should_stop, methods_run, settings.max_fix_cost)
            request.app.state.metrics.count("batch_problems_total", len(problems))
            request.app.state.metrics.fixes_done(methods_run, results)
            tak.push_batch(request.app, problems, results)
            response = JsonResponse({"results": results,
                                     **({"geojson": batch_geojson(results, problems)} if formats else {})})
            del problems, results
        return response

    return await watched(request, in_pool(None, run), "send fewer problems per batch")
