"""Fixes and planning bounds.

``POST /v1/fixes`` hands its decoded body (:mod:`service.fixes.decode`) to the app's
:class:`~service.fixes.coalesce.Coalescer`, which solves every fix queued at that
moment as one batch, through the same :func:`~service.fixes.pipeline.fix_results`
as ``POST /v1/fixes/batch``: a single fix is a batch of one. A fix whose cost
estimate is at most ``inline_fix_cost`` is solved on the event loop
(:meth:`~service.fixes.coalesce.Coalescer.inline`): it holds the loop a few hundred
microseconds at most, and is not watched. Larger ones are solved on a
worker thread and, like batches, wait under :func:`service.web.watch.watched`: 503
``deadline_exceeded`` past ``request_deadline_s``, and the solve stops between
parts once its clients are gone.
"""

from __future__ import annotations

import orjson
from fastapi import APIRouter, Request
from starlette.responses import Response

from service import schemas
from service.fixes.decode import decode_fix
from service.planning import crlb_response
from service.renderings import tak
from service.renderings.points import problem_renderings
from service.web.deps import OwnerDep, get_owner, json_request_body, parse_json, request_id
from service.web.problems import MEDIA_TYPE
from service.web.responses import JsonResponse
from service.web.watch import on_the_loop, watched

router = APIRouter(prefix="/v1", tags=["fixes"])

_ERRORS = {422: {"model": schemas.Problem, "description": "invalid input or unobservable geometry"}}
_DEADLINE = {503: {"model": schemas.Problem, "description": "not finished within the request deadline (code "
                                                           "deadline_exceeded), or the server is shutting down"}}
_HINT = "ask for fewer stations or measurements"


@router.post("/fixes", operation_id="fixes-create", summary="Locate an emitter from one set of measurements",
             response_model=schemas.FixResponse, responses={**_ERRORS, **_DEADLINE},
             openapi_extra={"requestBody": json_request_body(schemas.FixRequest)})
async def create_fix(http: Request) -> Response:
    # The body and the owner are read here rather than as dependencies: resolving two dependencies cost the
    # framework 50-80 us a request (measured in process), a sixth of this route's work besides the solve.
    raw = await http.body()
    body = decode_fix(raw) or parse_json(raw)
    get_owner(http)
    coalescer = http.app.state.fix_coalescer
    if coalescer.inline(body):
        result = await on_the_loop(coalescer.submit(body, request_id(http), inline=True))
    else:
        result = await watched(http, lambda should_stop: coalescer.submit(body, request_id(http), should_stop,
                                                                          inline=False), _HINT)
    if result["ok"]:
        fix = result["fix"]
        if type(body) is dict and body.get("cot") is not None:
            tak.push_fix(http.app, fix, problem_renderings(body))
        return JsonResponse(fix)
    error = result["error"]
    return Response(orjson.dumps(error), status_code=error["status"], media_type=MEDIA_TYPE)


@router.post("/crlb", operation_id="fixes-crlb", summary="The Cramer-Rao bound of a geometry (planning)",
             response_model=schemas.CrlbResponse, responses=_ERRORS)
def crlb(request: schemas.CrlbRequest, owner: OwnerDep) -> JsonResponse:
    return JsonResponse(crlb_response(request))
