"""Sessions: track a moving emitter from one fixed observer (paper 001)."""

from __future__ import annotations

from typing import Annotated

from fastapi import APIRouter, Depends, Header, Query, Request
from starlette.responses import Response

from service import session_schemas as schemas
from service import sessions
from service.deps import OwnerDep
from service.responses import JsonResponse
from service.schemas import Problem
from service.stores.guard import GuardedStore


async def get_store(request: Request) -> GuardedStore:
    return request.app.state.store


StoreDep = Annotated[GuardedStore, Depends(get_store)]

router = APIRouter(prefix="/v1/sessions", tags=["sessions"])

_ETAG = {"ETag": {"description": "the session's version, quoted: send it back in If-Match",
                  "schema": {"type": "string"}}}
_NOT_FOUND = {404: {"model": Problem, "description": "no such session for this key (or it expired)"}}
_INVALID = {422: {"model": Problem, "description": "invalid values, with the field path"}}
_UNAVAILABLE = {503: {"model": Problem, "description": "the session store is unavailable, too slow, or could not "
                                                       "serialise this write in time; retry after Retry-After",
                      "headers": {"Retry-After": {"description": "seconds", "schema": {"type": "string"}}}}}


def _state_response(record, status_code: int = 200, body: dict | None = None, headers=None) -> JsonResponse:
    return JsonResponse(body or sessions.state_body(record), status_code=status_code,
                        headers={"ETag": sessions.etag(record), **(headers or {})})


@router.post("", operation_id="sessions-create", status_code=201, summary="Start tracking a moving emitter",
             response_model=schemas.SessionState,
             responses={201: {"headers": {**_ETAG, "Location": {"description": "/v1/sessions/{id}",
                                                                 "schema": {"type": "string"}}}},
                        **_INVALID, **_UNAVAILABLE})
async def create_session(body: schemas.SessionCreate, owner: OwnerDep, store: StoreDep,
                         request: Request) -> JsonResponse:
    record = await store.run(sessions.create, owner, body)
    request.app.state.metrics.count("sessions_created_total")
    return _state_response(record, 201, headers={"Location": f"/v1/sessions/{record.id}"})


@router.get("", operation_id="sessions-list", summary="This key's live sessions, oldest first (paged)",
            response_model=schemas.SessionList, responses={**_INVALID, **_UNAVAILABLE})
async def list_sessions(owner: OwnerDep, store: StoreDep,
                  limit: Annotated[int, Query(ge=1, le=500, description="sessions per page")] = 50,
                  cursor: Annotated[str | None, Query(max_length=200,
                                                      description="next_cursor of the previous page")] = None,
                  ) -> JsonResponse:
    records, next_cursor = await store.run(sessions.page, owner, limit, cursor)
    return JsonResponse({"sessions": [sessions.state_body(r) for r in records], "next_cursor": next_cursor})


@router.get("/{session_id}", operation_id="sessions-get", summary="A session's state",
            response_model=schemas.SessionState,
            responses={200: {"headers": _ETAG}, **_NOT_FOUND, **_UNAVAILABLE})
async def get_session(session_id: str, owner: OwnerDep, store: StoreDep) -> JsonResponse:
    return _state_response(await store.run(sessions.get, owner, session_id))


@router.post("/{session_id}/measurements", operation_id="sessions-post-measurements",
             summary="Apply a batch of epochs (duplicates by seq are acknowledged and skipped)",
             response_model=schemas.MeasurementResult,
             responses={200: {"headers": _ETAG}, **_NOT_FOUND,
                        409: {"model": Problem, "description": "a new epoch's time_s is not after the previous "
                                                               "one's; nothing of the batch was applied"},
                        412: {"model": Problem, "description": "If-Match is stale"}, **_INVALID, **_UNAVAILABLE})
async def post_measurements(session_id: str, batch: schemas.MeasurementBatch, owner: OwnerDep, store: StoreDep,
                      request: Request,
                      if_match: Annotated[str | None, Header(description='"<version>" from an ETag: apply only '
                                                                         "if the session is still at it")] = None,
                      ) -> JsonResponse:
    outcome = await store.run(sessions.post_measurements, owner, session_id, batch, if_match)
    metrics = request.app.state.metrics
    metrics.count("session_epochs_applied_total", outcome.applied)
    metrics.count("session_epochs_duplicate_total", outcome.duplicates)
    body = {**sessions.state_body(outcome.record), "applied": outcome.applied, "duplicates": outcome.duplicates}
    return _state_response(outcome.record, body=body)


@router.delete("/{session_id}", operation_id="sessions-delete", status_code=204, summary="End a session",
               response_class=Response, responses={**_NOT_FOUND, **_UNAVAILABLE})
async def delete_session(session_id: str, owner: OwnerDep, store: StoreDep) -> Response:
    await store.run(sessions.delete, owner, session_id)
    return Response(status_code=204)
