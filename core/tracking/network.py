"""Network sessions: track emitters from the reports of any sensor network, reports arriving as they come.

Public API (pure functions; the state is an immutable value that round-trips through JSON exactly)::

    config = NetworkConfig(accel_sigma_mps2=0.3, reorder_window_s=2.0)
    state = new_network_state(config)
    outcome = apply_reports(state, [Report(...), ...], config)     # any time order within the window
    state = outcome.state                                          # outcome.applied, outcome.late
    tracks = predict_tracks(state, time_s, config)
    state = NetworkState.from_dict(state.to_dict())

Everything is in the session's common ENU frame (metres, exact: each measurement carries its station's
position and rotation at the report's time, so bearings use the station's own north and up and stations
may move).

The tracker (one per ``emitter_id``) is a constant-velocity filter on
``[east_m, north_m, up_m, east_mps, north_mps, up_mps]`` with white acceleration of power spectral density
``accel_sigma_mps2**2`` (:mod:`core.tracking.motion`; the up axis may take its own,
``vertical_accel_sigma_mps2``), updated with each report's measurements through the one measurement model
(:func:`core.measurements.measure_point`) by an unscented update iterated on the posterior (cubature points
over the position, ``linearisation_passes`` for a report with bearings, one without;
:mod:`core.tracking.network_kernel`). A report's TOAs share one unknown emission time, which the update
eliminates exactly (differences with their full noise covariance); a lone TOA carries nothing and is
reported, not used. With ``imm_accel_sigmas_mps2`` the track is an IMM over those acceleration levels
(:mod:`core.tracking.imm`).

Starting honestly. One bearing says where an emitter is seen, not how far. A track starts from its first
report: with a bearing, as a range-parameterised Gaussian sum along that line of sight over
``range_min_m .. range_max_m`` (sub-intervals of ratio 2, :func:`core.tracking.range_mixture.component_ranges`),
each component reweighted by its innovation density and pruned below 1e-3, the track reporting the sum's
moments; without a bearing, from the static fix (:func:`core.estimators.solve`) of the report's ranges and
TOAs with its CRLB, or, when that fix leaves the height open (four TOAs from stations on the ground), as a
Gaussian sum over heights of the fixes at known altitude. Velocity starts at zero with
``velocity_prior_sigma_mps`` per component (``vertical_velocity_prior_sigma_mps`` up). A sum whose components
all lie within half their own standard deviations of its mean becomes one Gaussian.

Status (computed against the newest applied report time, ``now``):

- ``tentative``: until confirmed;
- ``confirmed``: once, and from then on, the track's position covariance (a Gaussian sum's moments) is
  bounded (the largest standard deviation at most ``confirm_relative_sigma`` of the distance to the nearest
  station that reported it last) and the last ``confirm_updates`` updates each agreed with the prediction
  (NIS inside its chi-square 99 % point);
- ``coasting``: no report for more than ``coast_after_s``;
- ended: no report for more than ``end_after_s``: the track leaves ``tracks``; a later report of its
  ``emitter_id`` starts a new track.

Reports in any time order. The state keeps a checkpoint (every track before the reports of the last
``reorder_window_s``) and those reports, each with its track after it. A report older than the newest
applied one by more than the window is counted ``late`` and not applied; any other is inserted where it
belongs in time (order ``(time_s, seq)``) and its track re-filtered from the report before it, so the
result is bit-identical to that of the same reports applied in time order.

Layout: this module holds the session state and its API; the values it passes around (settings, report,
track) are :mod:`core.tracking.network_types`, and one report on one track (update, start, prediction) is
:mod:`core.tracking.network_update`. Imports run one way, from here down.
"""

from __future__ import annotations

import bisect
import math
from dataclasses import dataclass, field, replace
from typing import NamedTuple, Sequence

import numpy as np

from core.errors import InvalidInput
from core.linalg import symmetrized
from core.measurements import AZIMUTH, ELEVATION, KIND_NAMES, RANGE, TOA, Kind
from core.tracking.network_types import (
    NetworkConfig,
    Report,
    Track,
    check_real,
)
from core.tracking.network_update import (
    ReportRows,
    advance_track,
    predicted_track,
    report_rows,
)

#: Version of the :meth:`NetworkState.to_dict` layout.
NETWORK_STATE_FORMAT = 1


#: Warning codes the network tracker raises, with what each means.
NETWORK_WARNING_CODES = {
    "toa_single": "a report holds one TOA: with the emission time unknown it carries no information; not used",
    "late_report": "a report older than the newest applied one by more than reorder_window_s: counted, not applied",
    "track_not_started": "the report's measurements do not place an emitter (no bearing, and its ranges and "
                         "TOAs give no fix); the track starts with a report that does",
    "numerical_failure": "an update produced a covariance that is not positive definite or non-finite numbers; "
                         "the track was predicted only",
    "innovation_outlier": "the report disagrees with the prediction beyond the chi-square 99.9 % point: a "
                          "manoeuvre (the model is constant velocity) or a bad measurement; the update is applied",
}


class HistoryEntry(NamedTuple):
    """A report inside the reorder window and its track (None: no track) right after it."""

    report: Report
    track: Track | None


@dataclass(frozen=True, eq=False)
class NetworkState:
    """Everything a network session carries between posts.

    Attributes
    ----------
    tracks : tuple of Track
        The live tracks (not ended), by id, status as of ``last_time_s``.
    last_time_s : float or None
        Newest applied report time.
    checkpoint : tuple of Track
        Every track before the reports of ``history``.
    history : tuple of HistoryEntry
        The applied reports of the reorder window, in ``(time_s, seq)`` order, each with its track after it.
    """

    tracks: tuple[Track, ...] = ()
    last_time_s: float | None = None
    checkpoint: tuple[Track, ...] = ()
    history: tuple[HistoryEntry, ...] = field(default=())

    def to_dict(self) -> dict:
        """Plain JSON-able data; exact inverse of :meth:`from_dict`."""
        return {"format": NETWORK_STATE_FORMAT, "tracks": [t.to_dict() for t in self.tracks],
                "last_time_s": self.last_time_s, "checkpoint": [t.to_dict() for t in self.checkpoint],
                "history": [{"report": e.report.to_dict(), "track": None if e.track is None else e.track.to_dict()}
                            for e in self.history]}

    @classmethod
    def from_dict(cls, data: dict) -> "NetworkState":
        """Rebuild a state from :meth:`to_dict` output (after a JSON round trip).

        Raises
        ------
        InvalidInput
            When the data is not a network state of a known format.
        """
        if not isinstance(data, dict) or data.get("format") != NETWORK_STATE_FORMAT:
            raise InvalidInput(f"network state must be a mapping with format {NETWORK_STATE_FORMAT}")
        try:
            last = data.get("last_time_s")
            return cls(tuple(Track.from_dict(t) for t in data["tracks"]), None if last is None else float(last),
                       tuple(Track.from_dict(t) for t in data["checkpoint"]),
                       tuple(HistoryEntry(Report.from_dict(e["report"]),
                                          None if e["track"] is None else Track.from_dict(e["track"]))
                             for e in data["history"]))
        except (KeyError, TypeError, ValueError) as error:
            raise InvalidInput(f"network state is malformed: {error}") from None

    def __eq__(self, other):
        if not isinstance(other, NetworkState):
            return NotImplemented
        return self.to_dict() == other.to_dict()

    __hash__ = None


class ApplyOutcome(NamedTuple):
    """What :func:`apply_reports` did.

    Attributes
    ----------
    state : NetworkState
    applied : int
        Reports applied (in time order, late-within-window included).
    late : int
        Reports older than the newest applied one by more than ``reorder_window_s``: counted, not applied.
    warnings : tuple of (str, str)
        ``(code, message)`` of the batch (first message per code, with a count).
    """

    state: NetworkState
    applied: int
    late: int
    warnings: tuple


def new_network_state(config: NetworkConfig) -> NetworkState:
    """The state of a network session before any report."""
    if not isinstance(config, NetworkConfig):
        raise InvalidInput("config must be a NetworkConfig")
    return NetworkState()


def validate_report(report: Report) -> None:
    """Check what core needs of a report.

    Raises
    ------
    InvalidInput
        With ``loc`` naming the field (``("time_s",)``, ``("measurements", i, "value")``, ...).
    """
    if not isinstance(report, Report):
        raise InvalidInput("report must be a Report")
    check_real("time_s", report.time_s)
    if not report.emitter_id:
        raise InvalidInput("emitter_id must be a non-empty string", ("emitter_id",))
    m = report.kinds.shape[0] if report.kinds.ndim == 1 else -1
    if m < 1:
        raise InvalidInput("a report needs at least one measurement", ("measurements",))
    if (report.values.shape != (m,) or report.sigmas.shape != (m,) or report.stations_enu_m.shape != (m, 3)
            or report.rotations.shape != (m, 3, 3) or len(report.station_ids) != m):
        raise InvalidInput("a report's arrays must hold one entry per measurement", ("measurements",))
    placed = np.isfinite(report.stations_enu_m).all(axis=1) & np.isfinite(report.rotations).all(axis=(1, 2))
    for i in range(m):
        loc = ("measurements", i)
        kind = int(report.kinds[i])
        if kind not in (AZIMUTH, ELEVATION, RANGE, TOA):
            raise InvalidInput(f"unknown measurement kind {kind}", loc + ("kind",))
        value, sigma = float(report.values[i]), float(report.sigmas[i])
        if not math.isfinite(value):
            raise InvalidInput(f"{KIND_NAMES[kind]} must be a finite number", loc + ("value",))
        if not (math.isfinite(sigma) and sigma > 0.0):
            raise InvalidInput(f"sigma of the {KIND_NAMES[kind]} must be a finite number > 0", loc + ("sigma",))
        if kind == ELEVATION and abs(value) > 0.5 * math.pi:
            raise InvalidInput("elevation must be within [-90, 90] deg", loc + ("value",))
        if kind == RANGE and value < 0.0:
            raise InvalidInput("range must be >= 0", loc + ("value",))
        if not placed[i]:
            raise InvalidInput("station position must be finite", loc + ("station_id",))


def apply_reports(state: NetworkState, reports: Sequence[Report], config: NetworkConfig) -> ApplyOutcome:
    """Apply reports given in any order (module docstring: late reports, re-filtering).

    Parameters
    ----------
    state : NetworkState
    reports : sequence of Report
        In arrival (``seq``) order; lateness is judged against the newest report applied before each.
        Duplicates are the caller's to drop.
    config : NetworkConfig

    Returns
    -------
    ApplyOutcome

    Raises
    ------
    InvalidInput
        For the first bad report (``loc`` starts with its index in ``reports``); nothing is applied then.
    """
    for i, report in enumerate(reports):
        try:
            validate_report(report)
        except InvalidInput as error:
            raise InvalidInput(error.message, (i,) + (error.loc or ())) from None
    newest = state.last_time_s
    accepted, late = [], 0
    for report in reports:
        if newest is not None and report.time_s < newest - config.reorder_window_s:
            late += 1
            continue
        accepted.append(report)
        newest = report.time_s if newest is None else max(newest, report.time_s)
    gathered: dict[str, list] = {}
    if late:
        _gather(gathered, "late_report", f"{late} report(s) older than the newest applied one by more than "
                                         f"reorder_window_s {config.reorder_window_s:g} s were not applied", late)
    if not accepted:
        return ApplyOutcome(state, 0, late, _gathered(gathered))

    entries = list(state.history)
    keys = [e.report.order_key for e in entries]
    dirty: dict[str, int] = {}
    for report in sorted(accepted, key=lambda r: r.order_key):
        at = bisect.bisect_right(keys, report.order_key)
        entries.insert(at, HistoryEntry(report, None))
        keys.insert(at, report.order_key)
        for emitter, start in dirty.items():
            if start >= at:
                dirty[emitter] = start + 1
        dirty[report.emitter_id] = min(dirty.get(report.emitter_id, at), at)
    fresh = {id(r) for r in accepted}
    checkpoint = {t.id: t for t in state.checkpoint}
    for emitter, start in dirty.items():
        track = checkpoint.get(emitter)
        for entry in reversed(entries[:start]):
            if entry.report.emitter_id == emitter:
                track = entry.track
                break
        for i in range(start, len(entries)):
            report = entries[i].report
            if report.emitter_id != emitter:
                continue
            track, raised = advance_track(track, report, config)
            entries[i] = HistoryEntry(report, track)
            if id(report) in fresh:
                for code, message in raised:
                    _gather(gathered, code, message, 1)

    boundary = newest - config.reorder_window_s
    kept = bisect.bisect_left(keys, (boundary, -math.inf))
    for entry in entries[:kept]:
        if entry.track is None:
            checkpoint.pop(entry.report.emitter_id, None)
        else:
            checkpoint[entry.report.emitter_id] = entry.track
    entries = entries[kept:]
    checkpoint = {k: t for k, t in checkpoint.items() if t.time_s >= boundary - config.end_after_s}
    current = dict(checkpoint)
    for entry in entries:
        if entry.track is None:
            current.pop(entry.report.emitter_id, None)
        else:
            current[entry.report.emitter_id] = entry.track
    tracks = tuple(with_status(current[k], newest, config) for k in sorted(current)
                   if newest - current[k].time_s <= config.end_after_s)
    new_state = NetworkState(tracks, newest, tuple(checkpoint[k] for k in sorted(checkpoint)), tuple(entries))
    return ApplyOutcome(new_state, len(accepted), late, _gathered(gathered))


def predict_tracks(state: NetworkState, time_s: float, config: NetworkConfig) -> tuple[Track, ...]:
    """Every live track predicted (constant velocity, IMM-mixed) to ``time_s`` (a track newer than ``time_s``
    is returned as it is); status as of ``max(time_s, state.last_time_s)``."""
    check_real("time_s", time_s)
    now = time_s if state.last_time_s is None else max(time_s, state.last_time_s)
    out = []
    for track in state.tracks:
        track = with_status(track, now, config)  # against its last report, before the prediction moves time_s
        out.append(predicted_track(track, time_s, config) if time_s > track.time_s else track)
    return tuple(out)


def with_status(track: Track, now_s: float, config: NetworkConfig) -> Track:
    """``track`` with its status as of ``now_s`` (module docstring)."""
    if now_s - track.time_s > config.coast_after_s:
        status = "coasting"
    else:
        status = "confirmed" if track.confirmed else "tentative"
    return track if status == track.status else replace(track, status=status)


def _gather(gathered: dict, code: str, message: str, count: int) -> None:
    entry = gathered.setdefault(code, [message, 0])
    entry[1] += count


def _gathered(gathered: dict) -> tuple:
    return tuple((code, message if count == 1 or code == "late_report" else f"{message} (and {count - 1} more)")
                 for code, (message, count) in gathered.items())


__all__ = ["NETWORK_WARNING_CODES", "ApplyOutcome", "HistoryEntry", "Kind", "NetworkConfig", "NetworkState",
           "Report", "ReportRows", "Track", "advance_track", "apply_reports", "new_network_state",
           "predict_tracks", "report_rows", "validate_report", "with_status"]


def in_track_axes(track: Track, frame) -> tuple[np.ndarray, np.ndarray]:
    """A track's velocity and covariance in the east/north/up axes at its own position.

    The common frame's axes are those at its origin; away from it they turn (meridian convergence, the
    earth's curvature), so a track's sigma up and course are read in its own axes, as a fix's are.

    Parameters
    ----------
    track : Track
    frame : core.problem.frame.CommonFrame
        The session's frame (:meth:`~core.problem.frame.CommonFrame.local_axes` gives the rotation).

    Returns
    -------
    velocity_enu_mps : ndarray, shape (3,)
    covariance_enu : ndarray, shape (6, 6)
        ``[east_m, north_m, up_m, east_mps, north_mps, up_mps]`` at the track, symmetric.
    """
    mean = np.asarray(track.mean_enu, dtype=float)
    axes = frame.local_axes(mean[:3])
    turn = np.zeros((6, 6))
    turn[:3, :3] = turn[3:, 3:] = axes
    return axes @ mean[3:], symmetrized(turn @ np.asarray(track.covariance_enu, dtype=float) @ turn.T)

