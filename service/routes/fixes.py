"""Fixes and planning bounds."""

from __future__ import annotations

from fastapi import APIRouter
from service.responses import JsonResponse

from core.accuracy import error_summary
from core.crlb import information_at
from core.errors import UnobservableGeometry
from core.estimators import solve
from service import schemas
from service.deps import OwnerDep
from service.translate import crlb_problem, error_dict, fix_to_dict, to_options, to_problem

router = APIRouter(prefix="/v1", tags=["fixes"])

_ERRORS = {422: {"model": schemas.Problem, "description": "invalid input or unobservable geometry"}}


@router.post("/fixes", operation_id="fixes-create", summary="Locate an emitter from one set of measurements",
             response_model=schemas.FixResponse, responses=_ERRORS)
def create_fix(request: schemas.FixRequest, owner: OwnerDep) -> JsonResponse:
    problem = to_problem(request)
    fix = solve(problem, request.method, to_options(request))
    return JsonResponse(fix_to_dict(problem, fix, request.formats))


@router.post("/crlb", operation_id="fixes-crlb", summary="The Cramer-Rao bound of a geometry (planning)",
             response_model=schemas.CrlbResponse, responses=_ERRORS)
def crlb(request: schemas.CrlbRequest, owner: OwnerDep) -> JsonResponse:
    problem, target = crlb_problem(request)
    info = information_at(problem, target)
    if not info.observable[0]:
        raise UnobservableGeometry("these sensors do not determine the target position (singular information)")
    bound = info.covariance_enu_m2[0]
    return JsonResponse({"crlb_enu_m2": bound.tolist(), "error": error_dict(error_summary(bound))})
