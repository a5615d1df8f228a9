"""Monte Carlo accuracy of methods on a scenario (planning and method choice).

The one long computation of the service. It is priced before it starts
(``service.limits``: 422 ``over_limit`` above ``max_evaluation_cost``), runs
on the app's CPU pool (never the threads or the loop that serve the probes),
in chunks of trials that each ask whether to stop (:mod:`service.watch`): at
the request deadline (503 ``deadline_exceeded``), when the client
disconnects, or when the server shuts down. A stopped evaluation stops using
the CPU within one chunk.
"""

from __future__ import annotations

from fastapi import APIRouter, Request

from service import schemas
from service.deps import OwnerDep
from service.limits import check_evaluation, method_weight
from service.responses import JsonResponse
from service.translate import crlb_problem, evaluation_body
from service.watch import in_pool, watched

router = APIRouter(prefix="/v1", tags=["evaluations"])

#: Cost units (see service.limits) per chunk of trials: a chunk takes a few tenths of a second at most.
CHUNK_UNITS = 2000


@router.post("/evaluations", operation_id="evaluations-create",
             summary="Monte Carlo RMSE, bias, efficiency and NEES of methods for a scenario",
             response_model=schemas.EvaluationResponse,
             responses={422: {"model": schemas.Problem,
                              "description": "invalid scenario, or over max_evaluation_cost (code over_limit)"},
                        503: {"model": schemas.Problem,
                              "description": "not finished within the request deadline (code deadline_exceeded)"}})
async def create_evaluation(request: schemas.EvaluationRequest, owner: OwnerDep, http: Request) -> JsonResponse:
    settings = http.app.state.settings
    problem, target = crlb_problem(request.scenario)
    methods = list(dict.fromkeys(request.methods))
    rows = int(problem.kinds.size)
    exclude = request.options.outliers == "exclude"
    check_evaluation(request.trials, methods, rows, settings.max_evaluation_cost, exclude,
                     len(set(problem.source_index.tolist())))
    chunk = max(1, CHUNK_UNITS // (rows * max(method_weight(m) for m in methods) * (2 if exclude else 1)))

    metrics = http.app.state.metrics

    def chunk_done(done: int, total: int) -> None:
        metrics.evaluation_chunks.inc()

    def run(should_stop):
        with metrics.evaluations_running.track_inprogress():
            return evaluation_body(request, problem, target, methods, should_stop, chunk,
                                   settings.dask_scheduler or None, progress=chunk_done)

    body = await watched(http, in_pool(http.app.state.cpu_pool, run), "ask for fewer trials or methods")
    return JsonResponse(body)
