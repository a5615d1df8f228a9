"""Many independent fixes in one request: the throughput path (API.md ``POST /v1/fixes/batch``).

Problems the lean reader vouches for (plainly valid ML requests) go straight
from the parsed JSON into one core batch and come back as dicts built from
the batch's arrays. Every other problem takes the single-fix path (schema
validation, :func:`~service.translate.to_problem`, ``solve_many``), which
decides and words its errors. Either way a problem's error stays in its slot.

The body is parsed here with orjson, not by the framework, and the cyclic
garbage collector is paused while the request's million small objects are
made and dropped (it would otherwise rescan them over and over: about five
times the work of the parse itself). A large batch is solved in parts on up
to two worker threads (the numeric work runs outside the GIL) while this
thread turns finished parts into response bodies.
"""

from __future__ import annotations

import gc
import os
import threading
from concurrent.futures import ThreadPoolExecutor
from contextlib import contextmanager, nullcontext
from typing import Annotated

import numpy as np
import orjson
from fastapi import APIRouter, Depends, Request
from fastapi.exceptions import RequestValidationError
from pydantic import ValidationError

from core.accuracy import error_summary
from core.batch import size_groups
from core.errors import LocalizationError
from core.estimators import SolveOptions, solve_many
from core.estimators.ml import solve_ml_problem_batch
from service import schemas
from service.deps import OwnerDep
from service.limits import check_batch
from service.problems import localization_problem, problem_body, validation_errors
from service.responses import JsonResponse
from service.translate import (batch_error_summary, fix_batch_to_dicts, fix_to_dict, to_options, to_problem,
                               to_problem_batch)

router = APIRouter(prefix="/v1", tags=["fixes"])

#: The lean problems are solved in parts of this many; with more than one part, worker threads solve
#: the next parts (numpy releases the GIL in its loops) while this thread builds the bodies of the last.
PART_PROBLEMS = 2048
MAX_WORKERS = min(2, os.cpu_count() or 1)

MAX_PROBLEMS = next(rule.max_length for rule in schemas.BatchRequest.model_fields["problems"].metadata
                    if getattr(rule, "max_length", None) is not None)

_ERRORS = {
    400: {"model": schemas.Problem, "description": "the body is not valid JSON"},
    422: {"model": schemas.Problem, "description": "the body is not {\"problems\": [...]} with 1..10000 problems, "
                                                   "or the batch is over max_batch_cost (code over_limit)"},
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


def _problems(raw: bytes) -> list:
    """The ``problems`` list of a batch body; 400/422 as for any body when it is not one."""
    try:
        data = orjson.loads(raw)
    except orjson.JSONDecodeError as error:
        raise RequestValidationError([{"type": "json_invalid", "loc": ("body", error.pos), "msg": "JSON decode error",
                                       "input": {}, "ctx": {"error": error.msg}}]) from None
    if type(data) is dict and data.keys() == {"problems"}:
        problems = data["problems"]
        if type(problems) is list and 0 < len(problems) <= MAX_PROBLEMS:
            return problems
    try:
        schemas.BatchRequest.model_validate(data)
    except ValidationError as error:
        raise RequestValidationError([{**e, "loc": ("body", *e["loc"])} for e in error.errors()]) from None
    return data["problems"]


def _slot_error(body: dict, request_id: str | None) -> dict:
    body["request_id"] = request_id
    return body


def _invalid(error: ValidationError, request_id: str | None) -> dict:
    errors = validation_errors(error.errors())
    first = errors[0] if errors else {"loc": [], "msg": "invalid problem"}
    detail = f"{'.'.join(map(str, first['loc'])) or 'problem'}: {first['msg']}"
    return problem_body(422, "invalid_input", detail, errors, request_id)


def solve_batch(problems: list, request_id: str | None = None) -> list[dict]:
    """The ``results`` of a batch: one ``{"index", "ok", "fix" | "error"}`` per problem, in request order."""
    results: list[dict | None] = [None] * len(problems)

    def put(slot: int, fix: dict | None = None, error: dict | None = None) -> None:
        results[slot] = {"index": slot, "ok": True, "fix": fix} if error is None else \
            {"index": slot, "ok": False, "error": error}

    slots, options, formats, batch, rest = to_problem_batch(problems)
    if batch is not None:
        parts = []
        keys: dict[tuple, list[int]] = {}
        for row, key in enumerate(options):
            keys.setdefault(key, []).append(row)
        for key, rows in keys.items():
            rows = np.asarray(rows)
            for group in size_groups(batch.n_measurements[rows], batch.n_stations[rows]):
                parts.extend((key, rows[group[i:i + PART_PROBLEMS]]) for i in range(0, group.size, PART_PROBLEMS))
        workers = min(MAX_WORKERS, len(parts))

        def solve_part(part):
            key, chosen = part
            fixes = solve_ml_problem_batch(batch.take(chosen), SolveOptions(*key))
            return chosen, fixes, batch_error_summary(fixes)

        with ThreadPoolExecutor(workers) if workers > 1 else nullcontext() as pool:
            solved = pool.map(solve_part, parts) if pool is not None else map(solve_part, parts)
            for chosen, fixes, summary in solved:
                bodies = fix_batch_to_dicts(fixes, [formats[r] for r in chosen], summary)
                for j, (row, body) in enumerate(zip(chosen.tolist(), bodies)):
                    if body is None:
                        put(slots[row], error=_slot_error(localization_problem(fixes.errors[j]), request_id))
                    else:
                        put(slots[row], body)

    parsed = []
    for slot in rest:
        try:
            request = schemas.FixRequest.model_validate(problems[slot])
        except ValidationError as error:
            put(slot, error=_invalid(error, request_id))
            continue
        try:
            parsed.append((slot, request, to_problem(request)))
        except LocalizationError as error:
            put(slot, error=_slot_error(localization_problem(error), request_id))
    if parsed:
        solved = solve_many([p for _, _, p in parsed], [r.method for _, r, _ in parsed],
                            [to_options(r) for _, r, _ in parsed])
        fixed = [i for i, fix in enumerate(solved) if not isinstance(fix, LocalizationError)]
        summary = error_summary(np.array([solved[i].covariance_enu_m2 for i in fixed])) if fixed else None
        where = {i: k for k, i in enumerate(fixed)}
        for i, ((slot, request, problem), fix) in enumerate(zip(parsed, solved)):
            if isinstance(fix, LocalizationError):
                put(slot, error=_slot_error(localization_problem(fix), request_id))
            else:
                put(slot, fix_to_dict(problem, fix, request.formats, summary, where[i]))
    return results


@router.post("/fixes/batch", operation_id="fixes-batch", summary="Locate many emitters, each from its own measurements",
             description="Up to 10,000 independent fix requests; results in request order. A malformed or "
                         "unsolvable problem is reported in its own slot (`ok: false` with a problem+json "
                         "`error` whose `loc` is relative to the problem) and never fails the others.",
             response_model=schemas.BatchResponse, responses=_ERRORS, openapi_extra={"requestBody": _request_body_schema()})
def create_batch(owner: OwnerDep, raw: RawBody, request: Request) -> JsonResponse:
    request_id = request.scope.get("state", {}).get("request_id")
    with gc_paused():
        problems = _problems(raw)
        check_batch(problems, request.app.state.settings.max_batch_cost)
        results = solve_batch(problems, request_id)
        request.app.state.metrics.count("batch_problems_total", len(problems))
        response = JsonResponse({"results": results})
        del problems, results
    return response
