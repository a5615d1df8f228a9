"""Sessions: track a moving emitter from one fixed observer (paper 001), or emitters from a sensor network."""

from __future__ import annotations

import asyncio
from typing import Annotated

import orjson
from fastapi import APIRouter, Depends, Header, Query, Request
from starlette.responses import Response, StreamingResponse

from service.renderings import tak
from service.schemas import Problem
from service.schemas import sessions as schemas
from service.sessions import events
from service.sessions import network as network_sessions
from service.sessions import observer as sessions
from service.sessions.records import PrepareFirst
from service.stores.guard import GuardedStore
from service.web.deps import OwnerDep
from service.web.headers import of as parsed_headers
from service.web.problems import ApiError
from service.web.responses import JsonResponse
from service.web.watch import in_pool, watched


async def get_store(request: Request) -> GuardedStore:
    return request.app.state.store


StoreDep = Annotated[GuardedStore, Depends(get_store)]

router = APIRouter(prefix="/v1/sessions", tags=["sessions"])

_ETAG = {"ETag": {"description": "the session's version, quoted: send it back in If-Match",
                  "schema": {"type": "string"}}}
#: If-Match as the OpenAPI document declares it; a route reads the tags the middleware parsed
#: (:func:`service.web.headers.parse_if_match`), not this raw value.
IfMatchDoc = Annotated[str | None, Header(alias="If-Match", description='"<version>" from an ETag: apply only if '
                                                                        "the session is still at it")]
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
    "server-sent events (text/event-stream): `event: state` events (a network session's also `event: "
    "track_ended`), then `event: deleted`, the last (each a SessionEvent); lines starting with `:` are "
    "keep-alive comments")}
_EVENT = {"title": "SessionEvent", "description": "One server-sent event of a session's stream, as parsed.",
          "type": "object", "required": ["event", "data"], "properties": {
              "event": {"title": "Kind", "type": "string", "enum": ["state", "deleted", "track_ended"],
                        "description": "state: the session's state after an update; deleted: the session ended; "
                                       "track_ended: a network session's track coasted out (it leaves tracks)"},
              "id": {"type": "string", "pattern": "^[0-9]+$", "description": "the session's version (state events)"},
              "data": {"type": "string", "contentMediaType": "application/json",
                       "description": "one line of JSON: the SessionState or NetworkSessionState (state), {\"id\"} "
                                      "(deleted), {\"id\", \"track_id\", \"time_s\", \"version\"} (track_ended)",
                       "contentSchema": {"anyOf": [
                           {"$ref": "#/components/schemas/SessionState"},
                           {"$ref": "#/components/schemas/NetworkSessionState"},
                           {"type": "object", "required": ["id", "track_id"], "properties": {
                               "id": {"type": "string", "description": "the session's id"},
                               "track_id": {"type": "string", "description": "the track that ended"},
                               "time_s": {"type": "number", "description": "the time of its last estimate"},
                               "version": {"type": "integer", "description": "the session version whose post "
                                                                             "ended it"}}},
                           {"type": "object", "required": ["id"],
                            "properties": {"id": {"type": "string", "description": "the session's id"}}}]}}}}
_FORMATS = Query(pattern=r"^(cot|geojson)(,(cot|geojson))?$", description="comma-separated renderings: cot, geojson")
_AT_TIME = Query(ge=-schemas.MAX_ABS_TIME_S, le=schemas.MAX_ABS_TIME_S, allow_inf_nan=False,
                 description="network sessions: every track predicted to this time (session clock, s)")


def _state_response(record, status_code: int = 200, body: dict | None = None, headers=None) -> JsonResponse:
    return JsonResponse(body or sessions.state_body(record), status_code=status_code,
                        headers={"ETag": sessions.etag(record), **(headers or {})})


@router.post("", operation_id="sessions-create", status_code=201,
             summary="Start tracking a moving emitter (observer) or emitters from a sensor network (stations)",
             response_model=schemas.AnySessionState,
             responses={201: {"headers": {**_ETAG, "Location": {"description": "/v1/sessions/{id}",
                                                                 "schema": {"type": "string"}}}},
                        **_INVALID, **_UNAVAILABLE})
async def create_session(body: schemas.AnySessionCreate, owner: OwnerDep, store: StoreDep,
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
            response_model=schemas.AnySessionState,
            responses={200: {"headers": _ETAG}, **_NOT_FOUND, **_INVALID, **_UNAVAILABLE})
async def get_session(session_id: str, owner: OwnerDep, store: StoreDep,
                      formats: Annotated[str | None, _FORMATS] = None,
                      at_time_s: Annotated[float | None, _AT_TIME] = None) -> JsonResponse:
    record = await store.run(sessions.get, owner, session_id)
    return _state_response(record, body=sessions.rendered_state(record, formats.split(",") if formats else (),
                                                                at_time_s))


#: Times a post prepared on a worker thread may find its session moved on by other posts before the store
#: call decides it itself.
PREPARE_ATTEMPTS = 3


async def _apply(request: Request, store: GuardedStore, owner: str, session_id: str, change, count: int, apply,
                 too_long: str):
    """Apply a posted change (epochs or reports) to its session: a batch of more than ``INLINE_EPOCHS`` items,
    or a change that asks for it (:class:`service.sessions.records.PrepareFirst`), is prepared first in the CPU
    pool, under the request's deadline and cancellation, so that the store's atomic apply only checks and
    writes; ``too_long`` is the advice when that preparation runs out of time."""
    record = None
    prepare = count > sessions.INLINE_EPOCHS
    for _ in range(PREPARE_ATTEMPTS):
        if prepare:
            record = await store.run(sessions.get, owner, session_id)
            await watched(request, in_pool(None, lambda should_stop: change.prepare(record, should_stop)),
                          too_long)
        try:
            return await store.run(apply, owner, session_id, change, record)
        except PrepareFirst:
            prepare = True
    change.prepare_first = False  # overtaken by other posts on every try: decided within the store call
    return await store.run(apply, owner, session_id, change, record)


@router.post("/{session_id}/measurements", operation_id="sessions-post-measurements",
             summary="Apply a batch of epochs (duplicates by seq are acknowledged and skipped)",
             response_model=schemas.MeasurementResult,
             responses={200: {"headers": _ETAG}, **_NOT_FOUND,
                        409: {"model": Problem, "description": "a new epoch's time_s is not after the previous "
                                                               "one's; nothing of the batch was applied"},
                        412: {"model": Problem, "description": "If-Match is stale"}, **_INVALID, **_UNAVAILABLE})
async def post_measurements(session_id: str, batch: schemas.MeasurementBatch, owner: OwnerDep, store: StoreDep,
                      request: Request,
                      if_match: IfMatchDoc = None,
                      ) -> JsonResponse:
    change = sessions.MeasurementsChange(batch, parsed_headers(request).if_match, store.now)
    outcome = await _apply(request, store, owner, session_id, change, len(batch.measurements),
                           sessions.post_measurements, "post fewer epochs at a time")
    metrics = request.app.state.metrics
    metrics.count("session_updates_total", 1 if outcome.applied else 0)
    metrics.count("session_epochs_applied_total", outcome.applied)
    metrics.count("session_epochs_duplicate_total", outcome.duplicates)
    body = {**sessions.state_body(outcome.record), "applied": outcome.applied, "duplicates": outcome.duplicates}
    if outcome.applied:
        await events.publish(request.app, session_id, outcome.record.version)
        metrics.count("events_published_total")
        tak.push_session(request.app, body, sessions.cot_options(outcome.record))
    return _state_response(outcome.record, body=body)


@router.post("/{session_id}/reports", operation_id="sessions-post-reports",
             summary="Apply a batch of a network session's reports, in any time order (duplicates by seq are "
                     "acknowledged and skipped; reports older than reorder_window_s are counted late)",
             response_model=schemas.ReportResult,
             responses={200: {"headers": _ETAG}, **_NOT_FOUND,
                        412: {"model": Problem, "description": "If-Match is stale"},
                        422: {"model": Problem, "description": "invalid values, with the field path "
                                                               "(reports, i, ...): unknown_station, "
                                                               "station_position_missing, toa_without_partner, "
                                                               "invalid_input (in an auto session also an "
                                                               "emitter_id, or a measurement that is not a "
                                                               "bearing); wrong_session_kind for a paper-001 "
                                                               "session; nothing of the post was applied"},
                        **_UNAVAILABLE})
async def post_reports(session_id: str, batch: schemas.ReportBatch, owner: OwnerDep, store: StoreDep,
                       request: Request,
                       if_match: IfMatchDoc = None,
                       ) -> JsonResponse:
    change = network_sessions.ReportsChange(batch, parsed_headers(request).if_match, store.now)
    outcome = await _apply(request, store, owner, session_id, change, len(batch.reports), sessions.post_reports,
                           "post fewer reports at a time")
    metrics = request.app.state.metrics
    metrics.count("session_report_posts_total", 1 if outcome.applied else 0)
    metrics.count("session_reports_applied_total", outcome.applied)
    metrics.count("session_reports_duplicate_total", outcome.duplicates)
    metrics.count("session_reports_late_total", outcome.late)
    body = {**network_sessions.state_body(outcome.record, state=outcome.state), "applied": outcome.applied,
            "duplicates": outcome.duplicates, "late": outcome.late}
    if outcome.applied or outcome.ended:
        await events.publish(request.app, session_id, outcome.record.version)
        metrics.count("events_published_total")
        if tak.feed(request.app) is not None:
            for event in network_sessions.tak_events(outcome.record, body, outcome.ended):
                tak.push(request.app, event)
    return _state_response(outcome.record, body=body)


@router.delete("/{session_id}", operation_id="sessions-delete", status_code=204, summary="End a session",
               response_class=Response, responses={**_NOT_FOUND, **_UNAVAILABLE})
async def delete_session(session_id: str, owner: OwnerDep, store: StoreDep, request: Request) -> Response:
    await store.run(sessions.delete, owner, session_id)
    await events.publish(request.app, session_id, 0)
    return Response(status_code=204)


@router.get("/{session_id}/events", operation_id="sessions-events", summary="Server-sent events: the state after "
            "every applied update", response_class=StreamingResponse,
            description="`text/event-stream`. The first event is the current state (unless `Last-Event-ID` "
                        "already names its version); then one `state` event (`id`: the version, `data`: the "
                        "SessionState JSON, with the renderings `formats` asks for) whenever a post applies "
                        "epochs, on whichever replica (Redis pub/sub with the Redis store). States are "
                        "cumulative: a client that falls behind, or reconnects with `Last-Event-ID`, gets the "
                        "latest state, not every version in between. A `deleted` event ends the stream when "
                        "the session is deleted or expires; comments keep an idle connection open. A network "
                        "session's state events carry its NetworkSessionState (reports applied), and a track that "
                        "coasted out is announced by a `track_ended` event (`data`: id, track_id, time_s, "
                        "version) before the state that no longer lists it (a client that resumes with "
                        "`Last-Event-ID` gets those of the versions it missed, of the latest 50).",
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
                if last is not None and record.version > last:
                    for ended in record.state.get("ended", ()) if network_sessions.is_network(record) else ():
                        if ended["version"] > last:
                            yield events.sse("track_ended", orjson.dumps({"id": session_id, "track_id": ended["id"],
                                                                          "time_s": ended["time_s"],
                                                                          "version": ended["version"]}))
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
