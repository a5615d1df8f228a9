"""Network sessions created with ``"association": "auto"``: unlabelled bearings to tracks.

The association is core's (:mod:`core.tracking.association`: gating with the frequency gate, JPDA or GNN, track
starts from three or more stations, M-of-N confirmation, coasting and ending); this module decides what it is
given and what the record keeps, as :mod:`service.sessions.network` does for labelled sessions (which turns the
API's reports into core reports, the same way for both, and renders the tracks, the same way for both).

**Late reports land where they belong.** Core's association processes scans strictly in time order, so the
record keeps two association states: ``settled``, every accepted report older than ``newest_s -
reorder_window_s`` applied (no report that old is accepted any more: it is ``late``, as in a labelled session),
and ``current``, the settled state with the younger reports (``pending``, kept in the record) applied. A post
adds its accepted reports to ``pending``, moves those now older than the window into ``settled``, and re-runs
``pending`` from ``settled``: a report that arrived out of order within the window is processed in its time
order, and the tracks equal those of the same reports posted in time order. A scan (one station's bearings at
one time) is never split between the two, since the cut is by time. Ids are core's (``t1``, ``t2``, ... in start
order, never reused): a track keeps its id while it lives; only one that started within the window can be
decided again (and numbered again) when a late report lands before its start.

**The window's cost is bounded.** Every post re-runs ``pending``, so its cost follows how many reports the window
holds, not how many the post brings: a long window on a busy network would make each post re-run an hour.
At most :data:`MAX_PENDING_REPORTS` reports stay pending (a scan is never split, so ties at the cut stay
together); older ones settle early, and a report older than the settled ones is late whatever the window says.

Record layout: ``state["auto"] = {"settled", "current"}`` (:meth:`AssociationState.to_dict`),
``"pending"`` (``[{"report": Report.to_dict(), "frequency_hz": float or None}]`` in time order),
``"newest_s"`` (the newest accepted report's time, or None) and ``"settled_before_s"`` (every report before
this time is settled: the late limit the pending bound set, or None).

**What is shown.** The state lists every track with its status (tentative, confirmed, coasting). CoT, GeoJSON
and the TAK feed leave tentative tracks out (:func:`on_map`): a tentative track may be a ghost of crossing
bearings, and a TAK map should not show one. A confirmed track that ends (no bearing for ``end_after_s``) is
announced once in ``ended_tracks``, the event stream and the TAK feed, even when it started and ended within
one post; a tentative track that fails M of N leaves unannounced (it was never on a map).
"""

from __future__ import annotations

import math
from dataclasses import replace
from typing import NamedTuple

from core.errors import LocalizationError
from core.tracking.association import (AssociationConfig, AssociationState, apply_reports_auto, current_tracks,
                                       new_association_state, observations_from_report, status_of)
from core.tracking.network import NetworkConfig, Report, Track, validate_report
from service.schemas import sessions as schemas
from service.web.problems import ApiError


def _invalid(detail: str, loc) -> ApiError:
    return ApiError(422, "invalid_input", detail, [{"loc": list(loc), "msg": detail}])


def is_auto(request: dict) -> bool:
    """Whether a network session's stored create request asks for ``"auto"`` association."""
    return request.get("association") == "auto"


# -- creation ---------------------------------------------------------------------------------------------------

def association_config(request: schemas.NetworkSessionCreate, network: NetworkConfig) -> AssociationConfig:
    """The core association settings of an auto session's create request (422 with the field path).

    Parameters
    ----------
    request : NetworkSessionCreate
    network : NetworkConfig
        The tracks' filter, as the request's labelled settings give it
        (:func:`service.sessions.network.network_config`).
    """
    chosen = request.association_config or schemas.AssociationSettings()
    if not chosen.range_max_m > chosen.range_min_m:
        raise _invalid("range_max_m must be above range_min_m", ("association_config", "range_max_m"))
    # The filter restarts a track after network.end_after_s without a report; the association ends it after
    # end_after_s without a bearing first, so the filter's limit goes beyond it (twice it: any value above does).
    network = replace(network, end_after_s=2.0 * request.end_after_s)
    try:
        return AssociationConfig(network=network, method=chosen.method,
                                 detection_probability=chosen.detection_probability,
                                 false_density_per_rad2=chosen.false_density_per_rad2,
                                 gate_probability=chosen.gate_probability,
                                 frequency_tolerance_hz=chosen.frequency_tolerance_hz,
                                 range_min_m=chosen.range_min_m, range_max_m=chosen.range_max_m,
                                 confirm_hits=chosen.confirm_hits, confirm_window=chosen.confirm_window,
                                 coast_after_s=request.coast_after_s, end_after_s=request.end_after_s)
    except LocalizationError as error:
        field = error.loc[0] if error.loc else None
        loc = (field,) if field in ("coast_after_s", "end_after_s") else ("association_config", field)
        raise _invalid(error.message, loc if field else ("association_config",)) from error


def refuse_settings(request: schemas.NetworkSessionCreate) -> None:
    """422 at ``association_config`` when a labelled session's request gives one (it would be ignored)."""
    if request.association != "auto" and request.association_config is not None:
        raise _invalid("association_config is for association \"auto\" only", ("association_config",))


def settings_body(request: dict) -> dict | None:
    """The association settings an auto session runs with (its request's, defaults filled); None: labelled."""
    if not is_auto(request):
        return None
    return (schemas.AssociationSettings.model_validate(request["association_config"])
            if request.get("association_config") is not None else schemas.AssociationSettings()).model_dump()


#: The most reports an auto session keeps pending (re-run by every post). At the bench's busiest network (20
#: emitters x 10 stations, a bearing per station a second) that is 25 s of reports, about 0.5 s of work a post.
MAX_PENDING_REPORTS = 5000


def initial_state() -> dict:
    """A new auto session's ``state["auto"]`` (module docstring)."""
    empty = new_association_state().to_dict()
    return {"settled": empty, "current": empty, "pending": [], "newest_s": None, "settled_before_s": None}


# -- reports ----------------------------------------------------------------------------------------------------

def check_report(report: schemas.Report, index: int) -> None:
    """422 at ``reports, index, emitter_id`` for a labelled report: in an auto session the service decides which
    reports belong together, and a label it would not follow is refused rather than silently ignored."""
    if report.emitter_id is not None:
        raise _invalid(f"reports[{index}] names emitter_id {report.emitter_id!r}: an auto session takes "
                       "unlabelled reports (the service associates them)", ("reports", index, "emitter_id"))


def check_bearings(report: Report) -> None:
    """Core's checks of a report in an auto session: a valid report, and bearings only, at most one azimuth (and
    one elevation) per station (:func:`core.tracking.association.observations_from_report`)."""
    validate_report(report)
    observations_from_report(report)


class AutoOutcome(NamedTuple):
    """What a post does to an auto session.

    Attributes
    ----------
    auto : dict
        The record's new ``state["auto"]``.
    current : AssociationState
    applied, late : int
        Reports applied; reports older than the window (counted, not applied).
    ended : list of dict
        ``{"id", "time_s"}`` of the confirmed tracks that ended, in the order they were last seen.
    """

    auto: dict
    current: AssociationState
    applied: int
    late: int
    ended: list


def _time_order(entry: tuple[Report, float]):
    return entry[0].order_key


def apply_post(auto: dict, reports: list[tuple[Report, float]], window_s: float, config: AssociationConfig,
               announced=()) -> AutoOutcome:
    """A post's new reports (with their frequencies, NaN when absent) into the session (module docstring).

    Parameters
    ----------
    auto : dict
        The record's ``state["auto"]``.
    reports : list of (Report, float)
        In arrival (seq) order, each checked by :func:`check_bearings`. A report older than the newest accepted
        one (before it, this post's included) by more than ``window_s``, or older than the settled reports, is late.
    window_s : float
        The session's ``reorder_window_s``.
    config : AssociationConfig
    announced : collection of str
        Ids of the tracks already announced as ended (re-running the window ends them again: not announced twice).
    """
    newest = auto["newest_s"]
    settled_before = auto.get("settled_before_s")
    settled_before = -math.inf if settled_before is None else settled_before
    accepted, late = [], 0
    for report, frequency in reports:
        if newest is not None and report.time_s < max(newest - window_s, settled_before):
            late += 1
            continue
        accepted.append((report, frequency))
        newest = report.time_s if newest is None else max(newest, report.time_s)
    if not accepted:  # all late: the session is as it was
        return AutoOutcome(auto, AssociationState.from_dict(auto["current"]), 0, late, [])
    pending = sorted([(Report.from_dict(p["report"]), _nan_if_none(p["frequency_hz"])) for p in auto["pending"]]
                     + accepted, key=_time_order)
    if len(pending) > MAX_PENDING_REPORTS:
        settled_before = max(settled_before, pending[len(pending) - MAX_PENDING_REPORTS][0].time_s)
    cut = max(newest - window_s, settled_before)
    settling = [p for p in pending if p[0].time_s < cut]
    pending = [p for p in pending if not p[0].time_s < cut]
    before = AssociationState.from_dict(auto["current"])
    seen = {t.id: t for t in before.tracks}
    settled = _applied(AssociationState.from_dict(auto["settled"]), settling, config, seen)
    current = _applied(settled, pending, config, seen)
    live = {t.id for t in current.tracks}
    ended = [{"id": t.id, "time_s": float(t.track.time_s)} for t in seen.values()
             if t.confirmed and t.id not in live and t.id not in announced]
    stored = {"settled": settled.to_dict(), "current": current.to_dict(), "newest_s": newest,
              "settled_before_s": None if settled_before == -math.inf else settled_before,
              "pending": [{"report": r.to_dict(), "frequency_hz": None if math.isnan(f) else f} for r, f in pending]}
    return AutoOutcome(stored, current, len(accepted), late, ended)


def _applied(state: AssociationState, reports: list[tuple[Report, float]], config: AssociationConfig,
             seen: dict) -> AssociationState:
    """``reports`` (time order) applied to ``state``, every track's latest look put in ``seen`` (id -> MultiTrack).

    They are applied in steps spanning less than ``config.end_after_s`` each, cut between two report times (a
    scan is never split, so the result is that of one call): a track that ends within the post was live, and
    confirmed if it ever was, at the end of a step before it (no bearing for ``end_after_s`` after its
    confirming one), so ``seen`` holds every track a post ends.
    """
    start = 0
    while start < len(reports):
        stop = start + 1
        while stop < len(reports) and (reports[stop][0].time_s - reports[start][0].time_s < config.end_after_s
                                       or reports[stop][0].time_s == reports[stop - 1][0].time_s):
            stop += 1
        step = reports[start:stop]
        state = apply_reports_auto(state, [r for r, _ in step], [f for _, f in step], config).state
        seen.update((t.id, t) for t in state.tracks)
        start = stop
    return state


def _nan_if_none(value) -> float:
    return math.nan if value is None else float(value)


def late_warnings(late: int, window_s: float) -> list[dict]:
    """The post's ``late_report`` warning (the code labelled sessions raise), when it had late reports."""
    if not late:
        return []
    return [{"code": "late_report", "message": f"{late} report(s) older than the newest applied one by more than "
                                               f"reorder_window_s {window_s:g} s, or than the reports already "
                                               "settled, were not applied"}]


# -- core -> responses ------------------------------------------------------------------------------------------

def current(auto: dict) -> AssociationState:
    return AssociationState.from_dict(auto["current"])


def tracks(state: AssociationState, config: AssociationConfig, at_time_s: float | None = None
           ) -> tuple[Track, ...]:
    """Every track of the session with its status: each at its own time, or (``at_time_s``) predicted to it
    (:func:`core.tracking.association.current_tracks`)."""
    if at_time_s is not None:
        return current_tracks(state, at_time_s, config)
    return tuple(replace(t.track, status=status_of(t, state.last_time_s, config)) for t in state.tracks)


def on_map(body: dict, track: dict) -> bool:
    """Whether CoT, GeoJSON and the TAK feed show a track of the state ``body``: all of a labelled session's;
    an auto session's once confirmed (module docstring)."""
    return body["association"] != "auto" or track["status"] != "tentative"
