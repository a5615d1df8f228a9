"""Network sessions: the schema <-> core translation and the logic of a session created with ``stations``.

A report's stations and measurements become core arrays the way a fix request's do: the same schema models
(:class:`service.schemas.Station` and the measurement models), the same converters
(:func:`service.convert.to_point`, :func:`service.convert.to_measurement`) and the same placement in the
common frame (:func:`core.problem.build.build_problems`), with the session's origin fixed at creation so that every
report lands in one frame. The tracker itself is core's (:mod:`core.tracking.network`): pure
``(state, reports) -> state``; this module decides what reports are, which are duplicates, and what the
stored record becomes, as :mod:`service.sessions.observer` does for paper-001 sessions.

The record's ``state`` holds the core state (``NetworkState.to_dict``; a session with ``"association": "auto"``
has the association's instead, :mod:`service.sessions.association`), the station registry (the latest known
position of every station), the tracks that ended lately and the last post's warnings.
"""

from __future__ import annotations

import functools
import math
from dataclasses import replace
from typing import Callable

import numpy as np

from core import geodesy
from core.error_summary import error_summary
from core.errors import LocalizationError
from core.measurements import Kind
from core.problem.frame import CommonFrame, GeodeticPoint
from core.problem.build import ProblemInputs, build_problems, checked_inputs
from core.tracking.network import (NetworkConfig, NetworkState, Report, apply_reports, in_track_axes,
                                   new_network_state, predict_tracks, validate_report)
from service.sessions import association as association_sessions
from service import schemas as fix_schemas
from service.schemas import sessions as schemas
from service.renderings.tracks import ended_cot, geojson, track_cot
from service.web.problems import ApiError, api_loc
from service.sessions.records import PrepareFirst, cot_options, decoded_states, etag, if_match_accepts, timestamp
from service.stores import SessionRecord

#: Ended tracks a record remembers (for the event stream and the state's ``ended_tracks``).
ENDED_KEPT = 50
_TOA = int(Kind.TOA)


def _problem(status: int, code: str, detail: str, loc=None) -> ApiError:
    return ApiError(status, code, detail, [{"loc": list(loc), "msg": detail}] if loc is not None else [])


def is_network(record: SessionRecord) -> bool:
    return "network" in record.config


def core_state(record: SessionRecord) -> NetworkState:
    """The record's core state, decoded (read it through :data:`service.sessions.records.decoded_states`)."""
    return NetworkState.from_dict(record.state["core"])


def core_config(record: SessionRecord) -> NetworkConfig:
    """The session's tracker settings (fixed for its life: ``decoded_states.get(..., fixed=True)``)."""
    return network_config(record.config["request"])


# -- creation ---------------------------------------------------------------------------------------------------

def network_config(request: dict | schemas.NetworkSessionCreate) -> NetworkConfig:
    """The core tracker settings of a create request (422 with the field path for what core refuses)."""
    if isinstance(request, dict):
        request = schemas.NetworkSessionCreate.model_validate(request)
    noise = request.process_noise
    try:
        return NetworkConfig(accel_sigma_mps2=noise.accel_sigma_mps2,
                             imm_accel_sigmas_mps2=tuple(noise.imm_accel_sigmas_mps2 or ()),
                             imm_mean_sojourn_s=noise.imm_mean_sojourn_s,
                             reorder_window_s=request.reorder_window_s, coast_after_s=request.coast_after_s,
                             end_after_s=request.end_after_s,
                             velocity_prior_sigma_mps=request.start.velocity_sigma_mps,
                             range_min_m=request.start.range_min_m, range_max_m=request.start.range_max_m,
                             vertical_accel_sigma_mps2=noise.vertical_accel_sigma_mps2,
                             vertical_velocity_prior_sigma_mps=request.start.vertical_velocity_sigma_mps)
    except LocalizationError as error:
        field = error.loc[0] if error.loc else None
        loc = {"accel_sigma_mps2": ("process_noise", "accel_sigma_mps2"),
               "imm_accel_sigmas_mps2": ("process_noise", "imm_accel_sigmas_mps2"),
               "imm_mean_sojourn_s": ("process_noise", "imm_mean_sojourn_s"),
               "reorder_window_s": ("reorder_window_s",), "coast_after_s": ("coast_after_s",),
               "end_after_s": ("end_after_s",), "velocity_prior_sigma_mps": ("start", "velocity_sigma_mps"),
               "range_min_m": ("start", "range_min_m"), "range_max_m": ("start", "range_max_m"),
               "vertical_accel_sigma_mps2": ("process_noise", "vertical_accel_sigma_mps2"),
               "vertical_velocity_prior_sigma_mps": ("start", "vertical_velocity_sigma_mps")}.get(field)
        if loc is not None and len(error.loc) > 1:
            loc = (*loc, *error.loc[1:])
        raise _problem(422, error.code, error.message, loc) from error


def _origin(request: schemas.NetworkSessionCreate) -> GeodeticPoint | None:
    """The session's frame origin, fixed for its life: the given one, else (wgs84) the create stations' centroid
    on the ellipsoid, as a fix places its frame, else None (a flat local plane)."""
    from service.convert import to_point

    if request.origin is not None:
        return to_point(request.origin)
    if request.frame != "wgs84":
        return None
    lat = np.radians([s.position.lat_deg for s in request.stations])
    lon = np.radians([s.position.lon_deg for s in request.stations])
    lat0, lon0 = geodesy.centroid_on_ellipsoid(lat, lon)
    return GeodeticPoint(float(lat0), float(lon0), 0.0)


def association_config(request: dict | schemas.NetworkSessionCreate):
    """An auto session's :class:`core.tracking.association.AssociationConfig` (422 with the field path)."""
    if isinstance(request, dict):
        request = schemas.NetworkSessionCreate.model_validate(request)
    return association_sessions.association_config(request, network_config(request))


def initial(request: schemas.NetworkSessionCreate) -> tuple[dict, dict]:
    """The record ``config`` and ``state`` of a new network session (422 with the field path for bad settings)."""
    config = network_config(request)
    association_sessions.refuse_settings(request)
    if request.association == "auto":
        association_config(request)
        tracker = {"auto": association_sessions.initial_state()}
    else:
        tracker = {"core": new_network_state(config).to_dict()}
    origin = _origin(request)
    stations = {s.id: {"position": s.position.model_dump(mode="json"), "moving": s.moving, "time_s": None}
                for s in request.stations}
    return ({"request": request.model_dump(mode="json"), "network": True,
             "origin": None if origin is None else [origin.lat_rad, origin.lon_rad, origin.alt_m]},
            {**tracker, "stations": stations, "ended": [], "warnings": []})


def _frame(record: SessionRecord) -> CommonFrame:
    origin = record.config["origin"]
    return _frame_at(None if origin is None else tuple(origin))


@functools.lru_cache(maxsize=256)
def _frame_at(origin: tuple[float, float, float] | None) -> CommonFrame:
    """The session frame at ``origin`` (radians, metres), one object per origin, so that its placement on the
    earth (:attr:`core.problem.frame.CommonFrame.placement`) is made once, not per response."""
    return CommonFrame(None if origin is None else GeodeticPoint(*origin))


# -- reports -> core ----------------------------------------------------------------------------------------------

def core_reports(reports, first: int, registry: dict, frame: str, origin: GeodeticPoint | None,
                 check: Callable[[Report], object] = validate_report,
                 precheck: Callable[[schemas.Report, int], object] | None = None) -> list[Report]:
    """A post's API reports as core :class:`Report` values in the session's frame, each report's stations
    registered (:func:`_register`) once it is read, as the next report may use them.

    Each report is checked on its own (:func:`core.problem.build.checked_inputs`, naming its field); then all are
    placed in the session's frame in one batch (:func:`core.problem.build.build_problems`), so that a report's
    share of the placement is a row of one call rather than a call of its own.

    Parameters
    ----------
    reports : sequence of Report
        The post's new reports, in post order.
    first : int
        The index in the post of ``reports[0]`` (the error paths start ``reports, index``).
    registry : dict
        The session's stations: id -> ``{"position", "moving", "time_s"}`` (API positions); updated in place.
    frame : str
        ``"wgs84"`` or ``"local"``: which positions the report's stations must give.
    origin : GeodeticPoint or None
    check : callable
        Core's check of a report (its errors' paths become the request's): :func:`validate_report`, or an auto
        session's :func:`service.sessions.association.check_bearings`.
    precheck : callable, optional
        ``precheck(report, index)``: a check of the API report before it is read (an auto session's).

    Raises
    ------
    ApiError
        422 with the field path: a station position in the wrong frame or given twice, an unknown station, a
        moving station without its position, a lone TOA, a value core refuses.
    """
    inputs = []
    for index, report in enumerate(reports, start=first):
        if precheck is not None:
            precheck(report, index)
        inputs.append(_report_inputs(report, index, registry, frame, origin))
        _register(registry, report)
    batch = build_problems(inputs)
    out = []
    for b, (index, report) in enumerate(zip(range(first, first + len(reports)), reports)):
        used = batch.rows_in_use(b)
        rows, values, source = used.station_index, used.values, used.source_index
        toa = used.kinds == _TOA
        if toa.any():  # the client's own TOAs: core takes its own reference, so no digit is lost to a round trip
            values[toa] = [report.measurements[s].toa_s for s in source[toa]]
        ids = batch.station_ids[b]
        core = Report(seq=report.seq, time_s=report.time_s,
                      emitter_id=report.emitter_id or schemas.DEFAULT_EMITTER_ID,
                      station_ids=tuple(ids[s] for s in rows), stations_enu_m=batch.stations_enu_m[b, rows],
                      rotations=batch.station_rotations[b, rows], kinds=used.kinds, values=values,
                      sigmas=used.sigmas)
        try:
            check(core)
        except LocalizationError as error:
            raise _problem(422, error.code, f"reports[{index}]: {error.message}",
                           ("reports", index, *_core_loc(error.loc or (), source))) from error
        out.append(core)
    return out


def _report_inputs(report: schemas.Report, index: int, registry: dict, frame: str,
                   origin: GeodeticPoint | None) -> ProblemInputs:
    """One API report's stations and measurements, checked (:func:`core.problem.build.checked_inputs`), with the
    stations it measures from: given in the report, else the registry's (422 with the field path)."""
    from service.convert import to_measurement, to_point

    where = ("reports", index)
    wanted = fix_schemas.GeodeticPosition if frame == "wgs84" else fix_schemas.LocalPosition
    given: dict[str, object] = {}
    for k, station in enumerate(report.stations):
        if station.id in given:
            raise _problem(422, "invalid_input", f"reports[{index}] gives station {station.id!r} twice",
                           (*where, "stations", k, "id"))
        if not isinstance(station.position, wanted):
            raise _problem(422, "invalid_input", f"frame {frame!r} needs {wanted.__name__} station positions",
                           (*where, "stations", k, "position"))
        given[station.id] = station.position
    used: dict[str, object] = {}
    toa_stations: dict[str, int] = {}
    for j, m in enumerate(report.measurements):
        sid = m.station_id
        if sid not in used:
            if sid in given:
                used[sid] = given[sid]
            elif sid not in registry:
                raise _problem(422, "unknown_station", f"reports[{index}].measurements[{j}]: unknown station "
                                                       f"{sid!r} (give its position in the report's stations)",
                               (*where, "measurements", j, "station_id"))
            elif registry[sid]["moving"]:
                raise _problem(422, "station_position_missing",
                               f"reports[{index}].measurements[{j}]: station {sid!r} moves; the report must give "
                               "its position at time_s in its stations", (*where, "measurements", j, "station_id"))
            else:
                used[sid] = wanted.model_validate(registry[sid]["position"])
        if m.type == "toa":
            toa_stations.setdefault(sid, j)
    if len(toa_stations) == 1:
        j = next(iter(toa_stations.values()))
        raise _problem(422, "toa_without_partner",
                       f"reports[{index}].measurements[{j}]: a TOA needs a TOA from another station in the same "
                       "report (the emission time is unknown: one station's TOA alone says nothing)",
                       (*where, "measurements", j))
    try:
        return checked_inputs([(sid, to_point(p)) for sid, p in used.items()],
                              [to_measurement(m) for m in report.measurements], origin=origin)
    except LocalizationError as error:
        raise _problem(422, error.code, f"reports[{index}]: {error.message}",
                       (*where, *api_loc(error.loc or ()))) from error


def _core_loc(loc, source_index) -> list:
    """A core report error's ``loc`` as the API's path: a scalar measurement row becomes its request measurement
    (core names the row's ``value``, ``sigma`` or ``kind``, which the request spells per type: the path stops at
    the measurement)."""
    loc = list(loc)
    if len(loc) >= 2 and loc[0] == "measurements" and isinstance(loc[1], int) and 0 <= loc[1] < len(source_index):
        rest = [part for part in loc[2:] if part not in ("value", "sigma", "kind")]
        return ["measurements", int(source_index[loc[1]]), *api_loc(rest)]
    return api_loc(loc)


def _register(registry: dict, report: schemas.Report) -> None:
    """The report's station positions into the registry: a station new to the session is a moving one (every
    report that measures from it gives its position); a known one takes the newest position by time_s."""
    for station in report.stations:
        known = registry.get(station.id)
        if known is None:
            registry[station.id] = {"position": station.position.model_dump(mode="json"), "moving": True,
                                    "time_s": report.time_s}
        elif known["time_s"] is None or report.time_s >= known["time_s"]:
            known.update(position=station.position.model_dump(mode="json"), time_s=report.time_s)


def _warnings(items) -> list[dict]:
    out = []
    for w in items or ():
        if isinstance(w, dict):
            out.append({"code": str(w.get("code")), "message": str(w.get("message", ""))})
        elif isinstance(w, (tuple, list)) and len(w) == 2:
            out.append({"code": str(w[0]), "message": str(w[1])})
        elif hasattr(w, "code"):
            out.append({"code": str(w.code), "message": str(getattr(w, "message", ""))})
        else:
            out.append({"code": str(w), "message": str(w)})
    return out


class ReportsChange:
    """What a post of reports does to its network session: all of its new reports, or (on any error) none.

    As :class:`service.sessions.observer.MeasurementsChange`: called with a record it returns the new record (or None),
    depending on that record only; :meth:`prepare` decides it beforehand on a worker thread for a long post.

    Raises
    ------
    ApiError
        412 stale ``If-Match``; 422 a report that cannot be applied (with its field path), or a session that is
        not a network session.
    """

    def __init__(self, batch: schemas.ReportBatch, if_match: tuple[str, ...] | None, clock: Callable[[], float]):
        self.batch, self.if_match, self.clock = batch, if_match, clock
        self.applied = self.duplicates = self.late = 0
        self.ended: list[dict] = []
        #: The core state of the record the change made (None when it wrote nothing).
        self.state: NetworkState | None = None
        self._prepared: tuple | None = None
        #: Whether an auto session's post not prepared for the record it meets raises ``PrepareFirst``.
        self.prepare_first = True

    def prepare(self, record: SessionRecord, should_stop=None) -> None:
        new = self._change(record)
        self._prepared = (record.id, record.version, new, self.applied, self.duplicates, self.late, self.ended,
                          self.state)

    def __call__(self, record: SessionRecord) -> SessionRecord | None:
        prepared = self._prepared
        if prepared is not None and prepared[:2] == (record.id, record.version):
            new, self.applied, self.duplicates, self.late, self.ended, self.state = prepared[2:]
            return new
        if self.prepare_first and is_network(record) and association_sessions.is_auto(record.config["request"]):
            raise PrepareFirst()
        return self._change(record)

    def _change(self, record: SessionRecord) -> SessionRecord | None:

        if not is_network(record):
            raise _problem(422, "wrong_session_kind", f"session {record.id} tracks from one observer: post its "
                                                      "epochs to /measurements")
        if self.if_match is not None and not if_match_accepts(self.if_match, record.version):
            raise _problem(412, "precondition_failed",
                           f"If-Match {', '.join(self.if_match)} is stale: the session is at version {etag(record)}")
        reports = self.batch.reports
        first_new = 0
        if record.last_seq is not None:
            while first_new < len(reports) and reports[first_new].seq <= record.last_seq:
                first_new += 1
        fresh = reports[first_new:]
        self.duplicates, self.applied, self.late, self.ended, self.state = first_new, 0, 0, [], None
        if not fresh:
            return None
        request = record.config["request"]
        auto = association_sessions.is_auto(request)
        registry = {sid: dict(entry) for sid, entry in record.state["stations"].items()}
        origin = _frame(record).origin
        reports_in_frame = core_reports(fresh, first_new, registry, request["frame"], origin,
                                        association_sessions.check_bearings if auto else validate_report,
                                        association_sessions.check_report if auto else None)
        if auto:
            return self._auto(record, fresh, reports_in_frame, registry)
        config = decoded_states.get(record, core_config, fixed=True)
        before = decoded_states.get(record, core_state)
        try:
            outcome = apply_reports(before, reports_in_frame, config)
        except LocalizationError as error:
            loc = list(error.loc or ())
            if loc and isinstance(loc[0], int) and 0 <= loc[0] < len(fresh):  # core names the report by its index
                loc = ["reports", first_new + loc[0], *api_loc(loc[1:])]
            raise _problem(422, error.code, f"{error.message}; nothing of this post was applied",
                           api_loc(loc) if loc else None) from error
        self.applied, self.late, self.state = int(outcome.applied), int(outcome.late), outcome.state
        now_ids = {t.id for t in outcome.state.tracks}
        version = record.version + 1
        self.ended = [{"id": t.id, "time_s": float(t.time_s), "version": version}
                      for t in before.tracks if t.id not in now_ids]
        ended = (record.state.get("ended", []) + self.ended)[-ENDED_KEPT:]
        state = {"core": outcome.state.to_dict(), "stations": registry, "ended": ended,
                 "warnings": _warnings(outcome.warnings) if self.applied else record.state.get("warnings", [])}
        return self._written(record, state, fresh, outcome.state.last_time_s)

    def _auto(self, record: SessionRecord, fresh, core_reports: list[Report], registry: dict) -> SessionRecord:
        """An auto session's post (:mod:`service.sessions.association`)."""
        request = record.config["request"]
        try:
            outcome = association_sessions.apply_post(
                record.state["auto"], [(r, math.nan if f.frequency_hz is None else f.frequency_hz)
                                       for r, f in zip(core_reports, fresh)],
                request["reorder_window_s"], association_config(request),
                {e["id"] for e in record.state.get("ended", ())})
        except LocalizationError as error:
            raise _problem(422, error.code, f"{error.message}; nothing of this post was applied") from error
        self.applied, self.late, self.state = outcome.applied, outcome.late, outcome.current
        self.ended = [{**e, "version": record.version + 1} for e in outcome.ended]
        warnings = association_sessions.late_warnings(self.late, request["reorder_window_s"])
        state = {"auto": outcome.auto, "stations": registry,
                 "ended": (record.state.get("ended", []) + self.ended)[-ENDED_KEPT:],
                 "warnings": warnings if self.applied else record.state.get("warnings", [])}
        return self._written(record, state, fresh, outcome.auto["newest_s"])

    def _written(self, record: SessionRecord, state: dict, fresh, last_time: float | None) -> SessionRecord:
        """The record after a post that took ``fresh`` reports (the duplicates left out)."""
        now = self.clock()
        return replace(record, state=state, last_seq=fresh[-1].seq,
                       last_time_s=None if last_time is None else float(last_time),
                       updates=record.updates + self.applied, updated_at=now, expires_at=now + record.ttl_s)


# -- core -> responses ------------------------------------------------------------------------------------------

def _track_body(track, frame: CommonFrame) -> dict:
    """One core track as the API's track JSON, its errors in the east/north/up axes at the track."""
    from service.convert import error_dict

    mean = np.asarray(track.mean_enu, dtype=float)
    velocity_enu_mps, at_track = in_track_axes(track, frame)
    position = None
    if frame.is_geodetic:
        lat, lon, alt = frame.to_geodetic(mean[:3])
        position = {"lat_deg": math.degrees(float(lat)), "lon_deg": math.degrees(float(lon)), "alt_m": float(alt)}
    return {
        "id": track.id,
        "status": track.status,
        "time_s": float(track.time_s),
        "position": position,
        "position_local": {"east_m": float(mean[0]), "north_m": float(mean[1]), "up_m": float(mean[2])},
        "velocity_enu_mps": velocity_enu_mps.tolist(),
        "covariance_enu": at_track.tolist(),
        "error": error_dict(error_summary(at_track[None, :3, :3]), np.array([math.nan])),
        "updates": int(track.updates),
        "warnings": _warnings(track.warnings),
        "mode_probabilities": getattr(track, "mode_probabilities", None),
    }


def _tracks(record: SessionRecord, at_time_s: float | None, state) -> tuple:
    """The session's core tracks (each at its own time, or predicted to ``at_time_s``) with their status."""
    request = record.config["request"]
    if association_sessions.is_auto(request):
        if state is None:
            state = association_sessions.current(record.state["auto"])
        return association_sessions.tracks(state, association_config(request), at_time_s)
    if state is None:
        state = decoded_states.get(record, core_state)
    return state.tracks if at_time_s is None else predict_tracks(state, at_time_s, network_config(request))


def state_body(record: SessionRecord, at_time_s: float | None = None, state=None) -> dict:
    """The response body of a network session (``NetworkSessionState``); ``at_time_s``: every track predicted to
    that time; ``state``: the record's core state (``NetworkState``, or an auto session's ``AssociationState``)
    when the caller has it already (else read from the record)."""

    request = record.config["request"]
    frame = _frame(record)
    tracks = _tracks(record, at_time_s, state)
    origin = frame.origin
    body = {
        "id": record.id,
        "version": record.version,
        "model": request["model"],
        "frame": request["frame"],
        "origin": None if origin is None else {"lat_deg": math.degrees(origin.lat_rad),
                                               "lon_deg": math.degrees(origin.lon_rad), "alt_m": origin.alt_m},
        "association": request["association"],
        "association_config": association_sessions.settings_body(request),
        "reorder_window_s": request["reorder_window_s"],
        "stations": [{"id": sid, **entry} for sid, entry in record.state["stations"].items()],
        "last_seq": record.last_seq,
        "last_time_s": record.last_time_s,
        "updates": record.updates,
        "tracks": [_track_body(t, frame) for t in tracks],
        "ended_tracks": list(record.state.get("ended", [])),
        "warnings": list(record.state.get("warnings", [])),
        "created_at": timestamp(record.created_at),
        "updated_at": timestamp(record.updated_at),
        "expires_at": timestamp(record.expires_at),
        "ttl_s": record.ttl_s,
    }
    if at_time_s is not None:
        body["at_time_s"] = at_time_s
    return body


# -- renderings (:mod:`service.renderings.tracks`) --------------------------------------------------------

def rendered_state(record: SessionRecord, formats=(), at_time_s: float | None = None) -> dict:
    """:func:`state_body` with the renderings ``formats`` asks for (``"cot"``, ``"geojson"``)."""

    body = state_body(record, at_time_s)
    cot = cot_options(record)
    if "cot" in formats:
        for track in body["tracks"]:
            track["cot"] = track_cot(body, track, cot) if association_sessions.on_map(body, track) else None
    if "geojson" in formats:
        body["geojson"] = geojson(body, cot)
    return body


def tak_events(record: SessionRecord, body: dict, ended: list[dict]) -> list[str]:
    """The TAK feed's events of a post: one CoT track event per track, and a delete event per ended track."""

    cot = cot_options(record)
    events = [event for track in body["tracks"]
              if association_sessions.on_map(body, track) and (event := track_cot(body, track, cot)) is not None]
    if record.config["request"]["frame"] == "wgs84" or record.config["origin"] is not None:
        events += [ended_cot(record.id, e["id"], cot) for e in ended]
    return events


# -- evaluation: the tracker on a simulated scene against the posterior CRLB --------------------------------------

#: Cost units (:mod:`service.limits`) per scalar measurement of a network evaluation's trial: what a filter
#: step and the bound's recursion take, as measured on the three scenes.
NETWORK_EVALUATION_UNITS_PER_ROW = 3


def network_evaluation_cost(spec: schemas.NetworkEvaluationSpec) -> int:
    """``trials x the scene's scalar measurements x`` :data:`NETWORK_EVALUATION_UNITS_PER_ROW`."""
    from core.simulation.network import SCENES, report_schedule

    scene = SCENES[spec.scene]()
    rows = sum(2 if scene.stations[i].measures == "bearing" else 1
               for _, members in report_schedule(scene) for i in members)
    return spec.trials * rows * NETWORK_EVALUATION_UNITS_PER_ROW


def check_network_evaluation(spec: schemas.NetworkEvaluationSpec, limit: int) -> None:
    """422 ``over_limit`` (at ``network.trials``) when the evaluation costs more than ``limit``."""
    from service.limits import over_limit

    cost = network_evaluation_cost(spec)
    if cost > limit:
        raise over_limit("max_evaluation_cost", cost, limit, ["network", "trials"],
                         f"{spec.trials} trials of the {spec.scene} scene")


def network_evaluation(spec: schemas.NetworkEvaluationSpec, should_stop=None):
    """Run core's Monte Carlo of a network scene (:func:`core.simulation.network.evaluate_network`) with the
    request's tracker settings over the scene's; ``should_stop`` is asked between trials."""
    from core.simulation.network import SCENES, evaluate_network

    scene = SCENES[spec.scene]()
    config = scene.config
    changes = {}
    if spec.process_noise is not None:
        noise = spec.process_noise
        changes.update(accel_sigma_mps2=noise.accel_sigma_mps2,
                       imm_accel_sigmas_mps2=tuple(noise.imm_accel_sigmas_mps2 or ()),
                       imm_mean_sojourn_s=noise.imm_mean_sojourn_s,
                       vertical_accel_sigma_mps2=noise.vertical_accel_sigma_mps2)
    if spec.reorder_window_s is not None:
        changes["reorder_window_s"] = spec.reorder_window_s
    if changes:
        try:
            config = replace(config, **changes)
        except LocalizationError as error:
            raise _problem(422, error.code, error.message, ("network", *api_loc(error.loc or ()))) from error
    return evaluate_network(scene, spec.trials, spec.seed, config, should_stop=should_stop)


def _finite_list(values) -> list:
    return [float(v) if math.isfinite(v) else None for v in np.asarray(values, dtype=float).tolist()]


def _finite(value) -> float | None:
    return float(value) if math.isfinite(value) else None


def network_evaluation_body(spec: schemas.NetworkEvaluationSpec, should_stop=None) -> dict:
    """The response body of a network evaluation (``NetworkEvaluationResponse``)."""
    result = network_evaluation(spec, should_stop)
    return {
        "scene": spec.scene, "trials": spec.trials, "seed": spec.seed,
        "converged_after_s": float(result.converged_after_s), "rmse_over_pcrb": _finite(result.rmse_over_pcrb),
        "nees_after": _finite(result.nees_after), "nees_interval_99": [float(v) for v in result.nees_interval_99],
        "late_reports": int(result.late_reports),
        "epochs": {"time_s": [float(t) for t in result.times_s],
                   "rmse_position_m": _finite_list(result.rmse_position_m),
                   "pcrb_position_m": _finite_list(result.pcrb_position_m),
                   "rmse_velocity_mps": _finite_list(result.rmse_velocity_mps),
                   "pcrb_velocity_mps": _finite_list(result.pcrb_velocity_mps),
                   "nees_position": _finite_list(result.nees_position),
                   "nees_state": _finite_list(result.nees_state),
                   "tracked_fraction": _finite_list(result.tracked_fraction),
                   "confirmed_fraction": _finite_list(result.confirmed_fraction)},
    }
