"""Sessions: the schema <-> core translation and the session logic.

Paper-001 (``observer``) sessions are handled here; a network session (created with ``stations``) is
recognised by its record and handed to :mod:`service.sessions.network`, which follows the same pattern.

A route validates the request (``service.schemas.sessions``) and calls one
function here, which translates to core types (radians, SI), loads the record
from the store, runs the pure core filter step and saves what comes back.
Everything that decides a post's outcome (If-Match, duplicates, time order,
the filter steps) is decided against the record the store's atomic
read-modify-write writes over, so concurrent posts cannot interleave; the
filter steps of a long post run beforehand on a worker thread under the
request deadline (:class:`MeasurementsChange`), not on the store's threads
within its call deadline.
"""

from __future__ import annotations

import base64
import binascii
import math
import re
import secrets
from dataclasses import dataclass, replace
from typing import Callable

import numpy as np

from core import geodesy
from core.errors import LocalizationError
from core.parallel import Stopped
from core.tracking import Epoch as TrackerEpoch
from core.tracking import TrackerConfig, TrackState, new_state, step_many
from core.tracking.network import NetworkState
from service.schemas import sessions as schemas
from service.sessions import network as network_sessions
from service.sessions.records import cot_options, decoded_states, etag, if_match_accepts, timestamp
from service.stores import SessionRecord, SessionStore
from service.web.problems import ApiError

_SESSION_ID = re.compile(r"[0-9a-f]{32}")

#: Core config field -> request path, for errors the core raises on a session's settings.
_CONFIG_LOC = {
    "model": ("model",),
    "period_s": ("pulse", "period_s"),
    "period_known": ("pulse", "period_known"),
    "pulses_per_observation": ("pulse", "pulses_per_observation"),
    "sigma_azimuth_rad": ("noise", "sigma_azimuth_deg"),
    "sigma_elevation_rad": ("noise", "sigma_elevation_deg"),
    "sigma_azimuth_rate_rad_s": ("noise", "sigma_azimuth_rate_deg_s"),
    "sigma_toa_s": ("noise", "sigma_toa_s"),
    "accel_sigma_mps2": ("process_noise", "accel_sigma_mps2"),
    "imm_accel_sigmas_mps2": ("process_noise", "imm_accel_sigmas_mps2"),
    "imm_mean_sojourn_s": ("process_noise", "imm_mean_sojourn_s"),
}

#: Core epoch field -> request field.
_EPOCH_FIELD = {
    "time_s": "time_s",
    "azimuth_rad": "azimuth_deg",
    "elevation_rad": "elevation_deg",
    "azimuth_rate_rad_s": "azimuth_rate_deg_s",
    "toa_s": "toa_s",
}


def _problem(status: int, code: str, detail: str, loc: tuple | list | None = None, **kwargs) -> ApiError:
    errors = [{"loc": list(loc), "msg": detail}] if loc is not None else []
    return ApiError(status, code, detail, errors, **kwargs)


def not_found(session_id: str) -> ApiError:
    return _problem(404, "not_found", f"no session {session_id}")


# -- translation ------------------------------------------------------------------------------------------------

def tracker_config(request: schemas.SessionCreate) -> TrackerConfig:
    """The core filter settings of a create request (degrees -> radians)."""
    try:
        return TrackerConfig(
            model=request.model,
            period_s=request.pulse.period_s,
            period_known=request.pulse.period_known,
            pulses_per_observation=request.pulse.pulses_per_observation,
            sigma_azimuth_rad=math.radians(request.noise.sigma_azimuth_deg),
            sigma_elevation_rad=math.radians(request.noise.sigma_elevation_deg),
            sigma_azimuth_rate_rad_s=math.radians(request.noise.sigma_azimuth_rate_deg_s),
            sigma_toa_s=request.noise.sigma_toa_s,
            accel_sigma_mps2=request.process_noise.accel_sigma_mps2,
            imm_accel_sigmas_mps2=request.process_noise.imm_accel_sigmas_mps2,
            imm_mean_sojourn_s=request.process_noise.imm_mean_sojourn_s,
        )
    except LocalizationError as error:
        field = error.loc[0] if error.loc else None
        raise _problem(422, error.code, error.message, _CONFIG_LOC.get(field)) from error


def tracker_epoch(epoch: schemas.Epoch) -> TrackerEpoch:
    return TrackerEpoch(
        time_s=epoch.time_s,
        azimuth_rad=math.radians(epoch.azimuth_deg),
        elevation_rad=math.radians(epoch.elevation_deg),
        azimuth_rate_rad_s=math.radians(epoch.azimuth_rate_deg_s),
        toa_s=epoch.toa_s,
    )


def track_state(record: SessionRecord) -> TrackState:
    """A paper-001 session's filter state, decoded (use it through :data:`service.sessions.records.decoded_states`)."""
    return TrackState.from_dict(record.state)


def track_config(record: SessionRecord) -> TrackerConfig:
    """A paper-001 session's filter settings (fixed at creation: use it through
    :data:`service.sessions.records.decoded_states` with ``fixed=True``)."""
    return TrackerConfig.from_dict(record.config["tracker"])


def _observer(record: SessionRecord) -> dict:
    return record.config["request"]["observer"]["position"]


def state_body(record: SessionRecord) -> dict:
    """The response body of a session (``SessionState``, or ``NetworkSessionState`` for a network session)."""
    if network_sessions.is_network(record):
        return network_sessions.state_body(record)
    request = record.config["request"]
    state = decoded_states.get(record, track_state)
    observer = _observer(record)
    body = {
        "id": record.id,
        "version": record.version,
        "model": request["model"],
        "frame": request["frame"],
        "observer": {"position": observer},
        "last_seq": record.last_seq,
        "last_time_s": record.last_time_s,
        "updates": record.updates,
        "initialized": state.initialized,
        "position": None,
        "position_local": None,
        "velocity_enu_mps": None,
        "range_m": None,
        "range_sigma_m": None,
        "pulse_period_s": state.pulse_period_s,
        "covariance_enu": None,
        "warnings": [{"code": code, "message": message} for code, message in state.warnings],
        "mode_probabilities": state.mode_probabilities,
        "created_at": timestamp(record.created_at),
        "updated_at": timestamp(record.updated_at),
        "expires_at": timestamp(record.expires_at),
        "ttl_s": record.ttl_s,
    }
    if state.initialized:
        enu = state.position_enu_m
        if request["frame"] == "wgs84":
            lat, lon, alt = geodesy.enu_to_geodetic(enu, math.radians(observer["lat_deg"]),
                                                    math.radians(observer["lon_deg"]), observer["alt_m"])
            body["position"] = {"lat_deg": math.degrees(lat), "lon_deg": math.degrees(lon), "alt_m": float(alt)}
            local = enu
        else:
            local = enu + np.array([observer["east_m"], observer["north_m"], observer["up_m"]])
        body["position_local"] = {"east_m": float(local[0]), "north_m": float(local[1]), "up_m": float(local[2])}
        body["velocity_enu_mps"] = state.velocity_enu_mps.tolist()
        body["range_m"] = state.range_m
        body["range_sigma_m"] = state.range_sigma_m
        body["covariance_enu"] = state.covariance_enu.tolist()
    return body


def rendered_state(record: SessionRecord, formats=(), at_time_s: float | None = None) -> dict:
    """:func:`state_body` with the renderings ``formats`` asks for (``"cot"``, ``"geojson"``); ``at_time_s``:
    a network session's tracks predicted to that time."""
    from service.renderings import points as renderings

    if network_sessions.is_network(record):
        return network_sessions.rendered_state(record, formats, at_time_s)
    if at_time_s is not None:
        raise _problem(422, "invalid_input", "at_time_s predicts a network session's tracks; this session tracks "
                                             "from one observer", ("query", "at_time_s"))
    body = state_body(record)
    if "cot" in formats:
        body["cot"] = renderings.session_cot(body, cot_options(record))
    if "geojson" in formats:
        body["geojson"] = renderings.session_geojson(body, cot_options(record))
    return body


def encode_cursor(session_id: str) -> str:
    return base64.urlsafe_b64encode(session_id.encode()).decode().rstrip("=")


def decode_cursor(cursor: str) -> str:
    try:
        session_id = base64.urlsafe_b64decode(cursor + "=" * (-len(cursor) % 4)).decode()
    except (binascii.Error, UnicodeDecodeError, ValueError):
        session_id = ""
    if not _SESSION_ID.fullmatch(session_id):
        raise _problem(422, "invalid_input", "cursor is not one this service gave", ("query", "cursor"))
    return session_id


# -- operations -------------------------------------------------------------------------------------------------

def create(store: SessionStore, owner: str,
           request: schemas.SessionCreate | schemas.NetworkSessionCreate) -> SessionRecord:
    if isinstance(request, schemas.NetworkSessionCreate):
        config, state = network_sessions.initial(request)
    else:
        tracker = tracker_config(request)
        config = {"request": request.model_dump(mode="json"), "tracker": tracker.to_dict()}
        state = new_state(tracker).to_dict()
    now = store.now()
    record = SessionRecord(
        id=f"{int(now * 1000):012x}{secrets.token_hex(10)}",
        owner=owner,
        config=config,
        state=state,
        version=1,
        last_seq=None,
        last_time_s=None,
        updates=0,
        created_at=now,
        updated_at=now,
        expires_at=now + request.ttl_s,
        ttl_s=request.ttl_s,
    )
    store.create(record)
    return record


def get(store: SessionStore, owner: str, session_id: str) -> SessionRecord:
    record = store.get(owner, session_id) if _SESSION_ID.fullmatch(session_id) else None
    if record is None:
        raise not_found(session_id)
    return record


def delete(store: SessionStore, owner: str, session_id: str) -> None:
    if not (_SESSION_ID.fullmatch(session_id) and store.delete(owner, session_id)):
        raise not_found(session_id)


def page(store: SessionStore, owner: str, limit: int, cursor: str | None) -> tuple[list[SessionRecord], str | None]:
    after = None if cursor is None else decode_cursor(cursor)
    records, more = store.page(owner, limit, after)
    return records, (encode_cursor(records[-1].id) if more and records else None)


@dataclass(frozen=True)
class PostOutcome:
    record: SessionRecord
    applied: int
    duplicates: int


#: Epochs a post's filter runs between two looks at its ``should_stop``.
STOP_CHECK_EPOCHS = 256
#: A post of at most this many epochs is decided within the store's update call (its filter steps take a few
#: ms at most, and two more hops would cost a real-time feed 10-20 % of its posts/s); a longer one is
#: prepared first on a worker thread, under the request deadline (:class:`MeasurementsChange`).
INLINE_EPOCHS = 32


class MeasurementsChange:
    """What a batch of epochs does to its session: all of its new epochs, or (on any error) none.

    Called with a record, it returns the new record (or None: nothing new), and depends on that record
    only, as :meth:`service.stores.SessionStore.update` requires. The filter steps are the expensive part,
    so for a long post a route first calls :meth:`prepare` with the record it read, on a worker thread; the
    store's update, which must not hold its thread and deadline for them, then finds the session still at
    that version and takes the prepared record. A post that another write overtook is decided again there,
    against the latest record.

    Raises
    ------
    ApiError
        When called or prepared: 412 stale ``If-Match``; 409 a new epoch's ``time_s`` not after the previous
        one's; 422 an epoch the filter refuses.
    core.parallel.Stopped
        When ``should_stop`` (of :meth:`prepare`) said so.
    """

    def __init__(self, batch: schemas.MeasurementBatch, if_match: tuple[str, ...] | None,
                 clock: Callable[[], float]):
        self.batch, self.if_match, self.clock = batch, if_match, clock
        self.applied = self.duplicates = 0
        #: The filter state of the record the change made (None when it wrote nothing).
        self.state: TrackState | None = None
        self._prepared: tuple | None = None

    def prepare(self, record: SessionRecord, should_stop=None) -> None:
        """Decide the change for ``record`` now (``should_stop`` is asked every :data:`STOP_CHECK_EPOCHS`
        epochs)."""
        new = self._change(record, should_stop)
        self._prepared = (record.id, record.version, new, self.applied, self.duplicates, self.state)

    def __call__(self, record: SessionRecord) -> SessionRecord | None:
        prepared = self._prepared
        if prepared is not None and prepared[:2] == (record.id, record.version):
            new, self.applied, self.duplicates, self.state = prepared[2:]
            return new
        return self._change(record, None)

    def _change(self, record: SessionRecord, should_stop) -> SessionRecord | None:
        batch, if_match = self.batch, self.if_match
        if network_sessions.is_network(record):
            raise _problem(422, "wrong_session_kind", f"session {record.id} is a network session: post its reports "
                                                      "to /reports")
        if if_match is not None and not if_match_accepts(if_match, record.version):
            raise _problem(412, "precondition_failed",
                           f"If-Match {', '.join(if_match)} is stale: the session is at version {etag(record)}")
        first_new = 0
        if record.last_seq is not None:
            while first_new < len(batch.measurements) and batch.measurements[first_new].seq <= record.last_seq:
                first_new += 1
        fresh = batch.measurements[first_new:]
        self.applied, self.duplicates, self.state = len(fresh), first_new, None
        previous_time, previous_seq = record.last_time_s, record.last_seq
        for i, epoch in enumerate(fresh, start=first_new):
            if previous_time is not None and not epoch.time_s > previous_time:
                raise _problem(409, "time_not_increasing",
                               f"measurements[{i}] (seq {epoch.seq}) has time_s {epoch.time_s!r}, not after "
                               f"{previous_time!r} of seq {previous_seq}; nothing of this post was applied",
                               ("measurements", i, "time_s"))
            previous_time, previous_seq = epoch.time_s, epoch.seq
        if not fresh:
            return None
        config = decoded_states.get(record, track_config, fixed=True)
        current = [first_new]

        def epochs():
            for i, epoch in enumerate(fresh, start=first_new):
                if should_stop is not None and (i - first_new) % STOP_CHECK_EPOCHS == 0 and should_stop():
                    raise Stopped()
                current[0] = i
                yield tracker_epoch(epoch)

        try:
            state = step_many(decoded_states.get(record, track_state), epochs(), config)
        except LocalizationError as error:
            i = current[0]
            field = _EPOCH_FIELD.get(error.loc[0]) if error.loc else None
            loc = ("measurements", i) if field is None else ("measurements", i, field)
            raise _problem(422, error.code, f"measurements[{i}] (seq {batch.measurements[i].seq}): {error.message}; "
                                            "nothing of this post was applied", loc) from error
        now = self.clock()
        self.state = state
        return replace(record, state=state.to_dict(), last_seq=fresh[-1].seq, last_time_s=fresh[-1].time_s,
                       updates=record.updates + len(fresh), updated_at=now, expires_at=now + record.ttl_s)


def post_measurements(store: SessionStore, owner: str, session_id: str, change: MeasurementsChange,
                      read: SessionRecord | None = None) -> PostOutcome:
    """Apply a :class:`MeasurementsChange` to its session, atomically (404 unknown session); ``read``: the
    record it was prepared for (:meth:`SessionStore.update`)."""
    record = store.update(owner, session_id, change, read) if _SESSION_ID.fullmatch(session_id) else None
    if record is None:
        raise not_found(session_id)
    if isinstance(change.state, NetworkState):  # what the write made, committed: the next post starts from it
        decoded_states.remember(record, track_state, change.state)
    return PostOutcome(record, change.applied, change.duplicates)


@dataclass(frozen=True)
class ReportsOutcome:
    record: SessionRecord
    applied: int
    duplicates: int
    late: int
    ended: list
    #: The record's core state when this post wrote it (None: the record is as it was).
    state: object = None


def post_reports(store: SessionStore, owner: str, session_id: str, change: network_sessions.ReportsChange,
                 read: SessionRecord | None = None) -> ReportsOutcome:
    """Apply a :class:`service.sessions.network.ReportsChange` to its session, atomically (404 unknown session)."""
    record = store.update(owner, session_id, change, read) if _SESSION_ID.fullmatch(session_id) else None
    if record is None:
        raise not_found(session_id)
    if change.state is not None:  # what the write made, committed: the next post of this session starts from it
        decoded_states.remember(record, network_sessions.core_state, change.state)
    return ReportsOutcome(record, change.applied, change.duplicates, change.late, change.ended, change.state)
