"""Monte Carlo accuracy of methods on a scenario (planning and method choice)."""

from __future__ import annotations

import math

import numpy as np
from fastapi import APIRouter

from core.simulation.measurements import evaluate
from service import schemas
from service.deps import OwnerDep
from service.responses import JsonResponse
from service.translate import crlb_problem

router = APIRouter(prefix="/v1", tags=["evaluations"])


def _finite(value):
    if isinstance(value, np.ndarray):
        return value.tolist() if np.all(np.isfinite(value)) else None
    return value if math.isfinite(value) else None


@router.post("/evaluations", operation_id="evaluations-create",
             summary="Monte Carlo RMSE, bias, efficiency and NEES of methods for a scenario",
             response_model=schemas.EvaluationResponse,
             responses={422: {"model": schemas.Problem, "description": "invalid scenario"}})
def create_evaluation(request: schemas.EvaluationRequest, owner: OwnerDep) -> JsonResponse:
    problem, target = crlb_problem(request.scenario)
    results = evaluate(problem, target, list(dict.fromkeys(request.methods)), request.trials,
                       np.random.default_rng(request.seed), request.noise)
    methods = {
        name: {
            "rmse_m": _finite(r.rmse_m),
            "rmse_enu_m": _finite(r.rmse_enu_m),
            "bias_enu_m": _finite(r.bias_enu_m),
            "crlb_rmse_m": r.crlb_rmse_m,
            "efficiency": _finite(r.efficiency),
            "nees_mean": _finite(r.nees_mean),
            "failures": r.failures,
        }
        for name, r in results.items()
    }
    return JsonResponse({"methods": methods, "trials": request.trials, "seed": request.seed, "noise": request.noise})
