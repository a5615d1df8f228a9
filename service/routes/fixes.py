"""Fixes and planning bounds.

``POST /v1/fixes`` runs on the event loop: it validates and translates its
request, then awaits the app's :class:`~service.coalesce.Coalescer`, which
solves every fix queued at that moment in one batched call on a worker
thread (an idle service solves a lone request at once, alone).
"""

from __future__ import annotations

from fastapi import APIRouter, Depends, Request
from service.responses import JsonResponse

from core.accuracy import error_summary
from core.crlb import information_at
from core.errors import LocalizationError, UnobservableGeometry
from service import schemas, tak
from service.coalesce import Coalescer
from service.renderings import of_request
from service.deps import OwnerDep, get_owner
from service.translate import crlb_problem, error_dict, fix_to_dict, to_options, to_problem

router = APIRouter(prefix="/v1", tags=["fixes"])

_ERRORS = {422: {"model": schemas.Problem, "description": "invalid input or unobservable geometry"}}


async def _owner_on_loop(request: Request) -> str:
    """:func:`service.deps.get_owner` run on the event loop (a plain ``def`` dependency costs a thread hop)."""
    return get_owner(request)


def coalescer(app) -> Coalescer:
    """The app's coalescer of single fixes, made on first use (no module-level state)."""
    found = getattr(app.state, "fix_coalescer", None)
    if found is None:
        found = app.state.fix_coalescer = Coalescer()
    return found


@router.post("/fixes", operation_id="fixes-create", summary="Locate an emitter from one set of measurements",
             response_model=schemas.FixResponse, responses=_ERRORS)
async def create_fix(request: schemas.FixRequest, http: Request,
                     owner: str = Depends(_owner_on_loop)) -> JsonResponse:
    try:
        problem = to_problem(request)
        solved = await coalescer(http.app).solve(problem, request.method, to_options(request))
    except LocalizationError as error:
        http.app.state.metrics.fix(request.method, error.code)
        raise
    http.app.state.metrics.fix(solved.fix.method, "ok")
    body = fix_to_dict(problem, solved.fix, of_request(request), solved.summary, solved.index)
    tak.push_fix(http.app, body, of_request(request))
    return JsonResponse(body)


@router.post("/crlb", operation_id="fixes-crlb", summary="The Cramer-Rao bound of a geometry (planning)",
             response_model=schemas.CrlbResponse, responses=_ERRORS)
def crlb(request: schemas.CrlbRequest, owner: OwnerDep) -> JsonResponse:
    problem, target = crlb_problem(request)
    info = information_at(problem, target)
    if not info.observable[0]:
        raise UnobservableGeometry("these sensors do not determine the target position (singular information)")
    bound = info.covariance_enu_m2[0]
    return JsonResponse({"crlb_enu_m2": bound.tolist(), "error": error_dict(error_summary(bound))})
