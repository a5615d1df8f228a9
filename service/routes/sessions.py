"""Sessions: track a moving emitter from one fixed observer (paper 001)."""

from __future__ import annotations

import asyncio
from typing import Annotated

import orjson
from fastapi import APIRouter, Depends, Header, Query, Request
from starlette.concurrency import run_in_threadpool
from starlette.responses import Response, StreamingResponse

from service import events, sessions, tak
from service import session_schemas as schemas
from service.deps import OwnerDep
from service.headers import of as parsed_headers
from service.problems import ApiError
from service.responses import JsonResponse
from service.schemas import Problem
from service.stores.guard import GuardedStore
from service.watch import in_pool, watched


async def get_store(request: Request) -> GuardedStore:
    return request.app.state.store


StoreDep = Annotated[GuardedStore, Depends(get_store)]

router = APIRouter(prefix="/v1/sessions", tags=["sessions"])

_ETAG = {"ETag": {"description": "the session's version, quoted: send it back in If-Match",
                  "schema": {"type": "string"}}}
_NOT_FOUND = {404: {"model": Problem, "description": "no such session for this key (or it expired)"}}
_INVALID = {422: {"model": Problem, "description": "invalid values, with the field path"}}
_UNAVAILABLE = {503: {"model": Problem, "description": "the session store is unavailable, too slow, or could not "
                                                       "serialise this write in time (store_unavailable, "
                                                       "store_busy), or a post's filter steps did not finish "
                                                       "within the request deadline (deadline_exceeded); retry "
                                                       "after Retry-After",
                      "headers": {"Retry-After": {"description": "seconds", "schema": {"type": "string"}}}}}
#: The stream declared for generated clients as text (read as it comes: a client that parses the body as one
#: document never returns, as the stream lasts while the session lives), and each event as the stream's
#: ``itemSchema`` (OpenAPI 3.2's field for one event of a sequential media type; named SessionEvent).
_EVENT_STREAM = {"type": "string", "description": (
    "server-sent events (text/event-stream): `event: state` events, then `event: deleted`, the last (each a "
    "SessionEvent); lines starting with `:` are keep-alive comments")}
_EVENT = {"title": "SessionEvent", "description": "One server-sent event of a session's stream, as parsed.",
          "type": "object", "required": ["event", "data"], "properties": {
              "event": {"title": "Kind", "type": "string", "enum": ["state", "deleted"],
                        "description": "state: the session's state after an update; deleted: the session ended"},
              "id": {"type": "string", "pattern": "^[0-9]+$", "description": "the session's version (state events)"},
              "data": {"type": "string", "contentMediaType": "application/json",
                       "description": "one line of JSON: the SessionState (state), {\"id\"} (deleted)",
                       "contentSchema": {"anyOf": [
                           {"$ref": "#/components/schemas/SessionState"},
                           {"type": "object", "required": ["id"],
                            "properties": {"id": {"type": "string", "description": "the session's id"}}}]}}}}
_FORMATS = Query(pattern=r"^(cot|geojson)(,(cot|geojson))?$", description="comma-separated renderings: cot, geojson")


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
            responses={200: {"headers": _ETAG}, **_NOT_FOUND, **_INVALID, **_UNAVAILABLE})
async def get_session(session_id: str, owner: OwnerDep, store: StoreDep,
                      formats: Annotated[str | None, _FORMATS] = None) -> JsonResponse:
    record = await store.run(sessions.get, owner, session_id)
    return _state_response(record, body=sessions.rendered_state(record, formats.split(",") if formats else ()))


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
    change = sessions.MeasurementsChange(batch, if_match, store.now)
    record = None
    if len(batch.measurements) > sessions.INLINE_EPOCHS:
        record = await store.run(sessions.get, owner, session_id)
        await watched(request, in_pool(None, lambda should_stop: change.prepare(record, should_stop)),
                      "post fewer epochs at a time")
    outcome = await store.run(sessions.post_measurements, owner, session_id, change, record)
    metrics = request.app.state.metrics
    metrics.count("session_updates_total", 1 if outcome.applied else 0)
    metrics.count("session_epochs_applied_total", outcome.applied)
    metrics.count("session_epochs_duplicate_total", outcome.duplicates)
    body = {**sessions.state_body(outcome.record), "applied": outcome.applied, "duplicates": outcome.duplicates}
    if outcome.applied:
        await run_in_threadpool(events.bus(request.app).publish, session_id, outcome.record.version)
        metrics.count("events_published_total")
        tak.push_session(request.app, body, sessions.cot_options(outcome.record))
    return _state_response(outcome.record, body=body)


@router.delete("/{session_id}", operation_id="sessions-delete", status_code=204, summary="End a session",
               response_class=Response, responses={**_NOT_FOUND, **_UNAVAILABLE})
async def delete_session(session_id: str, owner: OwnerDep, store: StoreDep, request: Request) -> Response:
    await store.run(sessions.delete, owner, session_id)
    await run_in_threadpool(events.bus(request.app).publish, session_id, 0)
    return Response(status_code=204)


@router.get("/{session_id}/events", operation_id="sessions-events", summary="Server-sent events: the state after "
            "every applied update", response_class=StreamingResponse,
            description="`text/event-stream`. The first event is the current state (unless `Last-Event-ID` "
                        "already names its version); then one `state` event (`id`: the version, `data`: the "
                        "SessionState JSON, with the renderings `formats` asks for) whenever a post applies "
                        "epochs, on whichever replica (Redis pub/sub with the Redis store). States are "
                        "cumulative: a client that falls behind, or reconnects with `Last-Event-ID`, gets the "
                        "latest state, not every version in between. A `deleted` event ends the stream when "
                        "the session is deleted or expires; comments keep an idle connection open.",
            responses={200: {"description": "the event stream", "content": {"text/event-stream": {
                "schema": _EVENT_STREAM, "itemSchema": _EVENT}}}, **_NOT_FOUND, **_UNAVAILABLE})
async def session_events(session_id: str, owner: OwnerDep, store: StoreDep, request: Request,
                         formats: Annotated[str | None, _FORMATS] = None,
                         last_event_id: Annotated[str | None, Header(description="the id (version) of the last "
                                                                                 "event received")] = None,
                         ) -> StreamingResponse:
    record = await store.run(sessions.get, owner, session_id)
    wanted = formats.split(",") if formats else ()
    last = parsed_headers(request).last_event_id  # parsed strictly by the middleware (400 when malformed)

    async def stream():
        nonlocal record, last
        subscription = events.bus(request.app).subscribe(session_id)
        try:
            await asyncio.wait_for(subscription.ready.wait(), 10.0)
            record = await store.run(lambda backend: backend.get(owner, session_id)) or record
            while True:
                if last is None or record.version > last:
                    body = orjson.dumps(sessions.rendered_state(record, wanted), option=orjson.OPT_SERIALIZE_NUMPY)
                    yield events.sse("state", body, record.version)
                    last = record.version
                notice = await subscription.next(subscription.poll_s or events.HEARTBEAT_S)
                if notice is None:
                    yield b": keep-alive\n\n"
                try:
                    record = await store.run(sessions.get, owner, session_id)
                except ApiError as error:
                    if error.status != 404:
                        raise
                    yield events.sse("deleted", orjson.dumps({"id": session_id}))
                    return
        finally:
            await subscription.aclose()

    return StreamingResponse(stream(), media_type="text/event-stream",
                             headers={"Cache-Control": "no-cache", "X-Accel-Buffering": "no"})
