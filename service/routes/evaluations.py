"""Monte Carlo accuracy of methods on a scenario (planning and method choice).

The one long computation of the service. It is priced before it starts
(``service.limits``: 422 ``over_limit`` above ``max_evaluation_cost``), runs
on the app's CPU pool (never the threads or the loop that serve the probes),
in chunks of trials that each ask whether to stop (:mod:`service.web.watch`): at
the request deadline (503 ``deadline_exceeded``), when the client
disconnects, or when the server shuts down. A stopped evaluation stops using
the CPU within one chunk (for the network and multi-emitter scenes, one
trial).
"""

from __future__ import annotations

from typing import Annotated, Callable, NamedTuple, Union

from fastapi import APIRouter, Request
from pydantic import Discriminator, Tag

from service import schemas
from service.limits import check_evaluation, method_weight
from service.planning import crlb_problem, evaluation_body
from service.schemas import sessions as session_schemas
from service.sessions import multi_evaluation
from service.sessions import network as network_sessions
from service.web.deps import OwnerDep
from service.web.responses import JsonResponse
from service.web.watch import in_pool, watched

router = APIRouter(prefix="/v1", tags=["evaluations"])

#: Cost units (see service.limits) per chunk of trials: a chunk takes a few tenths of a second at most.
CHUNK_UNITS = 2000


def _evaluation_kind(value) -> str:
    """A body with ``network`` evaluates the network tracker on a scene, one with ``multi_emitter`` the
    association tracker on unlabelled bearings; any other, fix methods."""
    if isinstance(value, dict):
        if "scenario" not in value:
            if "network" in value:
                return "network_evaluation"
            if "multi_emitter" in value:
                return "multi_emitter_evaluation"
        return "fix_evaluation"
    if isinstance(value, session_schemas.NetworkEvaluationRequest):
        return "network_evaluation"
    if isinstance(value, session_schemas.MultiEmitterEvaluationRequest):
        return "multi_emitter_evaluation"
    return "fix_evaluation"


AnyEvaluationRequest = Annotated[
    Union[Annotated[schemas.EvaluationRequest, Tag("fix_evaluation")],
          Annotated[session_schemas.NetworkEvaluationRequest, Tag("network_evaluation")],
          Annotated[session_schemas.MultiEmitterEvaluationRequest, Tag("multi_emitter_evaluation")]],
    Discriminator(_evaluation_kind),
]


class _Tracking(NamedTuple):
    """A tracking evaluation: its request type and spec field, the cost check ``(spec, max_cost)``, the
    evaluation ``(spec, should_stop) -> body`` and the advice when it runs out of time."""

    request: type
    field: str
    check: Callable
    evaluate: Callable
    too_long: str


_TRACKING = (
    _Tracking(session_schemas.NetworkEvaluationRequest, "network", network_sessions.check_network_evaluation,
              network_sessions.network_evaluation_body, "ask for fewer trials"),
    _Tracking(session_schemas.MultiEmitterEvaluationRequest, "multi_emitter",
              multi_evaluation.check_multi_evaluation, multi_evaluation.multi_evaluation_body,
              "ask for fewer trials or a shorter duration_s"),
)


@router.post("/evaluations", operation_id="evaluations-create",
             summary="Monte Carlo RMSE, bias, efficiency and NEES of methods for a scenario, of the network "
                     "tracker on a scene (per epoch, against the posterior CRLB), or GOSPA of the multi-emitter "
                     "tracker on unlabelled bearings next to an intersection + DBSCAN baseline",
             response_model=Union[schemas.EvaluationResponse, session_schemas.NetworkEvaluationResponse,
                                  session_schemas.MultiEmitterEvaluationResponse],
             responses={422: {"model": schemas.Problem,
                              "description": "invalid scenario, or over max_evaluation_cost (code over_limit)"},
                        503: {"model": schemas.Problem,
                              "description": "not finished within the request deadline (code deadline_exceeded)"}})
async def create_evaluation(request: AnyEvaluationRequest, owner: OwnerDep, http: Request) -> JsonResponse:
    settings = http.app.state.settings
    for tracking in _TRACKING:
        if isinstance(request, tracking.request):
            spec = getattr(request, tracking.field)
            tracking.check(spec, settings.max_evaluation_cost)
            body = await watched(http, in_pool(http.app.state.cpu_pool,
                                               lambda should_stop: tracking.evaluate(spec, should_stop)),
                                 tracking.too_long)
            return JsonResponse(body)
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
