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
over the position, ``linearisation_passes``; :mod:`core.tracking.network_kernel`). A report's TOAs share one unknown emission time, which the update
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
- ``confirmed``: once, and from then on, the track is one Gaussian (or IMM), its position covariance is
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
"""

from __future__ import annotations

import bisect
import functools
import math
import numbers
from dataclasses import dataclass, field, replace
from typing import NamedTuple, Sequence

import numpy as np
from scipy.stats import chi2

from core.errors import InvalidInput, LocalizationError
from core.measurements import AZIMUTH, ELEVATION, KIND_NAMES, RANGE, SPEED_OF_LIGHT_MPS, TOA, Kind
from core.tracking import imm
from core.tracking.motion import transitions
from core.tracking.network_kernel import STATE_SIZE, UPDATED, network_ukf_kernel, predict_kernel
from core.tracking.range_mixture import component_ranges, moments, pruned, reweighted
from core.tracking.state import freeze, frozen_array

#: Version of the :meth:`NetworkState.to_dict` layout.
NETWORK_STATE_FORMAT = 1

STATUSES = ("tentative", "confirmed", "coasting")
#: A track's filter: a Gaussian sum along the first line of sight, one Gaussian, or IMM modes.
STAGES = ("mixture", "single", "imm")

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

#: Components of a start's Gaussian sum closer than this (standard deviations of the sum) are one.
MERGE_DISTANCE = 0.5

_CHI2_OUTLIER = 0.999
_CHI2_AGREE = 0.99


@dataclass(frozen=True)
class NetworkConfig:
    """Settings of a network session's tracker; validated on construction.

    Attributes
    ----------
    accel_sigma_mps2 : float
        White-acceleration intensity of the constant-velocity model: power spectral density
        ``accel_sigma_mps2**2`` (m^2/s^3) on each axis (and the model of a track's start before an IMM).
    imm_accel_sigmas_mps2 : tuple of float
        Non-empty (2 to 4 levels): once a track is one Gaussian, an IMM over these intensities.
    reorder_window_s : float
        A report up to this much older than the newest applied one is applied in time order; older: late.
    imm_mean_sojourn_s : float
        Mean time in one IMM mode (the Markov switching matrix, :func:`core.tracking.imm.switching_matrix`).
    velocity_prior_sigma_mps : float
        Standard deviation of each velocity component at a track's start (zero mean).
    range_min_m, range_max_m : float
        The ranges along a first line of sight the emitter may be at.
    azimuth_only_elevation_sigma_rad : float
        A first bearing without elevation: the line of sight's elevation is taken as 0 with this sigma.
    confirm_updates : int
        Consecutive agreeing updates (NIS inside the 99 % point) needed to confirm.
    confirm_relative_sigma : float
        Largest position standard deviation, as a fraction of the distance to the nearest reporting station,
        at which a track may be confirmed.
    coast_after_s, end_after_s : float
        Without a report for longer than these, a track is ``coasting``, then ended.
    linearisation_passes : int
        Passes of the iterated posterior linearisation of each update (1: the plain unscented update; see
        :mod:`core.tracking.network_kernel`).
    start_altitudes_m : tuple of 2 floats
        Heights (the common frame's up, m) a track started from ranges and TOAs alone may be at, when its first
        fix does not place it in height (``_fix_start``).
    start_altitude_step_m : float
        Their spacing, and the vertical standard deviation a first fix must reach to be used alone.
    vertical_accel_sigma_mps2 : float or None
        The white acceleration's intensity on the up axis (aircraft and ground vehicles hold their height far
        better than their course); None: ``accel_sigma_mps2`` (isotropic). An IMM scales each level's up axis
        by the same ratio.
    vertical_velocity_prior_sigma_mps : float or None
        The start's up-velocity standard deviation; None: ``velocity_prior_sigma_mps``.
    """

    accel_sigma_mps2: float = 1.0
    imm_accel_sigmas_mps2: tuple[float, ...] = ()
    reorder_window_s: float = 2.0
    imm_mean_sojourn_s: float = 60.0
    velocity_prior_sigma_mps: float = 100.0
    range_min_m: float = 1e3
    range_max_m: float = 200e3
    azimuth_only_elevation_sigma_rad: float = 0.25
    confirm_updates: int = 3
    confirm_relative_sigma: float = 0.05
    coast_after_s: float = 10.0
    end_after_s: float = 60.0
    linearisation_passes: int = 3
    start_altitudes_m: tuple[float, float] = (-500.0, 20_000.0)
    vertical_accel_sigma_mps2: float | None = None
    vertical_velocity_prior_sigma_mps: float | None = None
    start_altitude_step_m: float = 500.0

    def __post_init__(self):
        for name in ("accel_sigma_mps2", "velocity_prior_sigma_mps", "range_min_m", "range_max_m",
                     "azimuth_only_elevation_sigma_rad", "confirm_relative_sigma", "coast_after_s",
                     "end_after_s", "imm_mean_sojourn_s"):
            _check_positive(name, getattr(self, name))
        _check_real("reorder_window_s", self.reorder_window_s)
        if self.reorder_window_s < 0.0:
            raise InvalidInput("reorder_window_s must be >= 0", ("reorder_window_s",))
        levels = tuple(self.imm_accel_sigmas_mps2)
        object.__setattr__(self, "imm_accel_sigmas_mps2", tuple(float(v) for v in levels))
        if levels and not 2 <= len(levels) <= 4:
            raise InvalidInput("imm_accel_sigmas_mps2 must hold 2 to 4 levels", ("imm_accel_sigmas_mps2",))
        for i, value in enumerate(levels):
            _check_positive("imm_accel_sigmas_mps2", value, ("imm_accel_sigmas_mps2", i))
        _check_positive("start_altitude_step_m", self.start_altitude_step_m)
        for name in ("vertical_accel_sigma_mps2", "vertical_velocity_prior_sigma_mps"):
            if getattr(self, name) is not None:
                _check_positive(name, getattr(self, name))
        low, high = (float(v) for v in self.start_altitudes_m)
        object.__setattr__(self, "start_altitudes_m", (low, high))
        if not (math.isfinite(low) and math.isfinite(high) and high >= low):
            raise InvalidInput("start_altitudes_m must be finite, low to high", ("start_altitudes_m",))
        if not self.range_max_m > self.range_min_m:
            raise InvalidInput("range_max_m must be above range_min_m", ("range_max_m",))
        for name in ("confirm_updates", "linearisation_passes"):
            value = getattr(self, name)
            if isinstance(value, bool) or not isinstance(value, int) or not 1 <= value <= 20:
                raise InvalidInput(f"{name} must be an integer from 1 to 20", (name,))
        if not self.end_after_s > max(self.coast_after_s, self.reorder_window_s):
            raise InvalidInput("end_after_s must be above coast_after_s and reorder_window_s", ("end_after_s",))


@dataclass(frozen=True, eq=False)
class Report:
    """One report: measurements taken at one time, each by a station at its position then.

    Attributes
    ----------
    seq : int
        The client's sequence number (ties in ``time_s`` are applied in ``seq`` order).
    time_s : float
        Session clock (s).
    emitter_id : str
        The track it belongs to.
    station_ids : tuple of str, length M
        Which station took each measurement.
    stations_enu_m : ndarray, shape (M, 3)
        That station's position at ``time_s``, common frame.
    rotations : ndarray, shape (M, 3, 3)
        Station ENU <- common ENU.
    kinds : ndarray of int, shape (M,)
        :class:`core.measurements.Kind` codes.
    values : ndarray, shape (M,)
        Radians (angles), metres (range), seconds (TOA, as the client sent them).
    sigmas : ndarray, shape (M,)
        Radians, metres, seconds.
    """

    seq: int
    time_s: float
    emitter_id: str
    station_ids: tuple[str, ...]
    stations_enu_m: np.ndarray
    rotations: np.ndarray
    kinds: np.ndarray
    values: np.ndarray
    sigmas: np.ndarray

    def __post_init__(self):
        object.__setattr__(self, "stations_enu_m", frozen_array(self.stations_enu_m))
        object.__setattr__(self, "rotations", frozen_array(self.rotations))
        kinds = np.array(self.kinds, dtype=np.int64)
        kinds.flags.writeable = False
        object.__setattr__(self, "kinds", kinds)
        object.__setattr__(self, "values", frozen_array(self.values))
        object.__setattr__(self, "sigmas", frozen_array(self.sigmas))
        object.__setattr__(self, "station_ids", tuple(self.station_ids))

    @property
    def order_key(self) -> tuple[float, int]:
        """Where the report belongs in time: ``(time_s, seq)``."""
        return (self.time_s, self.seq)

    def to_dict(self) -> dict:
        return {"seq": self.seq, "time_s": self.time_s, "emitter_id": self.emitter_id,
                "station_ids": list(self.station_ids), "stations_enu_m": self.stations_enu_m.tolist(),
                "rotations": self.rotations.tolist(), "kinds": self.kinds.tolist(), "values": self.values.tolist(),
                "sigmas": self.sigmas.tolist()}

    @classmethod
    def from_dict(cls, data: dict) -> "Report":
        m = len(data["kinds"])
        return cls(int(data["seq"]), float(data["time_s"]), str(data["emitter_id"]), tuple(data["station_ids"]),
                   np.array(data["stations_enu_m"], dtype=float).reshape(m, 3),
                   np.array(data["rotations"], dtype=float).reshape(m, 3, 3), data["kinds"], data["values"],
                   data["sigmas"])


@dataclass(frozen=True, eq=False)
class Track:
    """One emitter's track.

    Attributes
    ----------
    id : str
    status : str
        ``"tentative"``, ``"confirmed"`` or ``"coasting"`` (module docstring).
    time_s : float
        Time of the estimate (its last report, or the time it was predicted to).
    mean_enu : ndarray, shape (6,)
        ``[east_m, north_m, up_m, east_mps, north_mps, up_mps]``, common frame: the moments of the filter.
    covariance_enu : ndarray, shape (6, 6)
    updates : int
        Reports applied to it.
    warnings : tuple of (str, str)
        ``(code, message)`` raised by its last report; codes in :data:`NETWORK_WARNING_CODES`.
    stage : str
        ``"mixture"``, ``"single"`` or ``"imm"``.
    weights : ndarray, shape (C,)
        Component weights (mixture) or mode probabilities (IMM); ``[1.0]`` for one Gaussian.
    means : ndarray, shape (C, 6)
    covariances : ndarray, shape (C, 6, 6)
    agreeing : int
        Consecutive updates whose NIS was inside its 99 % point.
    confirmed : bool
        Whether the track has met the confirmation rule.
    reference_range_m : float
        Distance from the estimate to the nearest station of its last report before confirmation (for the
        confirmation rule; kept from then on).
    """

    id: str
    status: str
    time_s: float
    mean_enu: np.ndarray
    covariance_enu: np.ndarray
    updates: int
    warnings: tuple
    stage: str
    weights: np.ndarray
    means: np.ndarray
    covariances: np.ndarray
    agreeing: int = 0
    confirmed: bool = False
    reference_range_m: float = math.inf

    @property
    def mode_probabilities(self) -> list[float] | None:
        """The IMM's mode probabilities (in ``imm_accel_sigmas_mps2`` order), None before it runs."""
        return self.weights.tolist() if self.stage == "imm" else None

    def to_dict(self) -> dict:
        return {"id": self.id, "status": self.status, "time_s": self.time_s, "mean_enu": self.mean_enu.tolist(),
                "covariance_enu": self.covariance_enu.tolist(), "updates": self.updates,
                "warnings": [list(w) for w in self.warnings], "stage": self.stage, "weights": self.weights.tolist(),
                "means": self.means.tolist(), "covariances": self.covariances.tolist(), "agreeing": self.agreeing,
                "confirmed": self.confirmed,
                "reference_range_m": None if math.isinf(self.reference_range_m) else self.reference_range_m}

    @classmethod
    def from_dict(cls, data: dict) -> "Track":
        reference = data.get("reference_range_m")
        return cls(str(data["id"]), str(data["status"]), float(data["time_s"]), frozen_array(data["mean_enu"]),
                   frozen_array(data["covariance_enu"]), int(data["updates"]),
                   tuple(tuple(w) for w in data["warnings"]), str(data["stage"]), frozen_array(data["weights"]),
                   frozen_array(data["means"]), frozen_array(data["covariances"]), int(data["agreeing"]),
                   bool(data["confirmed"]), math.inf if reference is None else float(reference))


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
    _check_real("time_s", report.time_s)
    if not report.emitter_id:
        raise InvalidInput("emitter_id must be a non-empty string", ("emitter_id",))
    m = report.kinds.shape[0] if report.kinds.ndim == 1 else -1
    if m < 1:
        raise InvalidInput("a report needs at least one measurement", ("measurements",))
    if (report.values.shape != (m,) or report.sigmas.shape != (m,) or report.stations_enu_m.shape != (m, 3)
            or report.rotations.shape != (m, 3, 3) or len(report.station_ids) != m):
        raise InvalidInput("a report's arrays must hold one entry per measurement", ("measurements",))
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
        if not (np.all(np.isfinite(report.stations_enu_m[i])) and np.all(np.isfinite(report.rotations[i]))):
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
    _check_real("time_s", time_s)
    now = time_s if state.last_time_s is None else max(time_s, state.last_time_s)
    out = []
    for track in state.tracks:
        track = with_status(track, now, config)  # against its last report, before the prediction moves time_s
        out.append(_predicted(track, time_s, config) if time_s > track.time_s else track)
    return tuple(out)


def with_status(track: Track, now_s: float, config: NetworkConfig) -> Track:
    """``track`` with its status as of ``now_s`` (module docstring)."""
    if now_s - track.time_s > config.coast_after_s:
        status = "coasting"
    else:
        status = "confirmed" if track.confirmed else "tentative"
    return track if status == track.status else replace(track, status=status)


# ---------------------------------------------------------------------------------------------------------------
# One report on one track


class ReportRows(NamedTuple):
    """A report in the units of the measurement model (:func:`report_rows`).

    Attributes
    ----------
    values : ndarray, shape (M,)
        Radians, metres; a TOA as ``c (toa - toa_reference)`` (m, 0 for the reference itself).
    variances : ndarray, shape (M,)
    rows : ndarray of int, shape (R,)
        The measurements an update uses (every one but the TOA reference and a lone TOA).
    toa_reference : int
        Index of the reference TOA, -1 when fewer than two TOAs.
    warnings : tuple of (str, str)
    """

    values: np.ndarray
    variances: np.ndarray
    rows: np.ndarray
    toa_reference: int
    warnings: tuple


def report_rows(report: Report) -> ReportRows:
    """The report's model values, variances and update rows; its TOAs referred to one of them (the one with
    the smallest sigma), subtracted in seconds first so that epoch-sized TOAs keep their digits."""
    kinds = report.kinds
    is_toa = kinds == TOA
    if not is_toa.any():
        return ReportRows(report.values, report.sigmas * report.sigmas, _all_rows(kinds.size), -1, ())
    values = report.values.copy()
    sigmas = report.sigmas.copy()
    toa_index = np.flatnonzero(is_toa)
    warnings = ()
    reference = -1
    use = np.ones(kinds.size, dtype=bool)
    if toa_index.size == 1:
        use[toa_index] = False
        warnings = (("toa_single", f"report seq {report.seq}: one TOA (station {report.station_ids[toa_index[0]]!r}) "
                                   "carries no information without a second one to difference it with; not used"),)
    elif toa_index.size > 1:
        reference = int(toa_index[np.argmin(sigmas[toa_index])])
        values[is_toa] = (values[is_toa] - report.values[reference]) * SPEED_OF_LIGHT_MPS
        sigmas[is_toa] *= SPEED_OF_LIGHT_MPS
        use[reference] = False
    return ReportRows(values, sigmas * sigmas, np.flatnonzero(use).astype(np.int64), reference, warnings)


@functools.lru_cache(maxsize=64)
def _all_rows(count: int) -> np.ndarray:
    rows = np.arange(count, dtype=np.int64)
    rows.flags.writeable = False
    return rows


def advance_track(track: Track | None, report: Report, config: NetworkConfig) -> tuple[Track | None, tuple]:
    """Apply one report to its emitter's track (start it if there is none, or the old one has ended).

    Returns
    -------
    track : Track or None
        None when no track exists and the report cannot start one.
    warnings : tuple of (str, str)
    """
    rows = report_rows(report)
    if track is None or report.time_s - track.time_s > config.end_after_s:
        return _start(report, rows, config)
    warnings = rows.warnings
    if rows.rows.size == 0:
        return replace(track, warnings=warnings), warnings
    dt = report.time_s - track.time_s
    weights = track.weights
    means = np.array(track.means)
    covs = np.array(track.covariances)
    if track.stage == "imm":
        switching = imm.switching_matrix(weights.size, dt, config.imm_mean_sojourn_s)
        weights, means, covs = imm.mixed(weights, means, covs, switching)
        levels = config.imm_accel_sigmas_mps2
    else:
        levels = (config.accel_sigma_mps2,) * weights.size
    phi, noises = motion_model(config, dt, levels)
    new_means, new_covs, nis, log_det, status = _update(means, covs, phi, noises, dt > 0.0, report, rows,
                                                        config.linearisation_passes)
    dof = rows.rows.size
    ok = status == UPDATED
    if not ok.any() or (track.stage != "mixture" and not ok.all()):
        warnings += (("numerical_failure", f"report seq {report.seq}: the update failed; the track was predicted"),)
        return _finish(track, report, weights, means, covs, np.nan, dof, config, warnings)
    if weights.size == 1:
        weights = np.ones(1)
    else:
        weights = reweighted(weights, np.where(ok, -0.5 * (nis + log_det), -np.inf))
        if track.stage == "imm":
            weights = imm.floored(weights)
    combined_nis = float(nis[ok][np.argmax(weights[ok])]) if track.stage == "mixture" else float(
        np.dot(weights, np.where(ok, nis, 0.0)))
    if track.stage == "mixture":
        weights, new_means, new_covs = _pruned_mixture(weights, new_means, new_covs)
    if combined_nis > _chi2_point(_CHI2_OUTLIER, dof):
        warnings += (("innovation_outlier", f"report seq {report.seq}: NIS {combined_nis:.1f} on {dof} degrees "
                                            "of freedom"),)
    return _finish(track, report, weights, new_means, new_covs, combined_nis, dof, config, warnings)


def _update(means, covs, phi, noises, predict: bool, report: Report, rows: ReportRows, passes: int):
    count = means.shape[0]
    new_means, new_covs = np.empty((count, STATE_SIZE)), np.empty((count, STATE_SIZE, STATE_SIZE))
    nis, log_det, status = np.empty(count), np.empty(count), np.empty(count, dtype=np.int64)
    network_ukf_kernel(means, covs, phi, noises, predict, report.stations_enu_m, report.rotations, report.kinds,
                       rows.values, rows.variances, rows.rows, rows.toa_reference, passes, new_means, new_covs, nis,
                       log_det, status)
    return new_means, new_covs, nis, log_det, status


def _finish(track: Track | None, report: Report, weights, means, covs, nis: float, dof: int, config: NetworkConfig,
            warnings: tuple, stage: str | None = None) -> tuple[Track, tuple]:
    """The track after a report: stage change (a mixture collapsed to one), moments, confirmation."""
    stage = stage or track.stage
    if stage == "mixture" and weights.size == 1:
        stage = "single"
    if stage == "single" and config.imm_accel_sigmas_mps2:
        modes = imm.uniform_modes(means[0], covs[0], len(config.imm_accel_sigmas_mps2))
        stage, weights, means, covs = "imm", modes.weights, modes.means, modes.covariances
    if weights.size == 1:
        mean, cov = np.array(means[0]), np.array(covs[0])
    else:
        mean, cov = moments(np.asarray(weights), np.asarray(means), np.asarray(covs))
    agreeing = 0 if track is None else track.agreeing
    agreeing = agreeing + 1 if math.isfinite(nis) and nis <= _chi2_point(_CHI2_AGREE, dof) else 0
    if track is not None and track.confirmed:
        confirmed, reference_range_m = True, track.reference_range_m
    else:
        reference_range_m = float(np.linalg.norm(report.stations_enu_m - mean[:3], axis=1).min())
        confirmed = (stage != "mixture" and agreeing >= config.confirm_updates
                     and math.sqrt(max(np.linalg.eigvalsh(cov[:3, :3])[-1], 0.0))
                     <= config.confirm_relative_sigma * reference_range_m)
    updates = 1 if track is None else track.updates + 1
    out = Track(report.emitter_id, "confirmed" if confirmed else "tentative", report.time_s, freeze(mean),
                freeze(cov), updates, warnings, stage, freeze(np.asarray(weights, dtype=float)),
                freeze(np.asarray(means, dtype=float)), freeze(np.asarray(covs, dtype=float)), agreeing,
                bool(confirmed), reference_range_m)
    return out, warnings


def _start(report: Report, rows: ReportRows, config: NetworkConfig) -> tuple[Track | None, tuple]:
    """A new track from its first report (module docstring)."""
    warnings = rows.warnings
    azimuths = np.flatnonzero(report.kinds == AZIMUTH)
    if azimuths.size:
        first = int(azimuths[0])
        station = report.station_ids[first]
        elevations = [i for i in np.flatnonzero(report.kinds == ELEVATION) if report.station_ids[i] == station]
        elevation = int(elevations[0]) if elevations else -1
        weights, means, covs = _line_of_sight_mixture(report, first, elevation, config)
        rest = np.array([r for r in rows.rows if r not in (first, elevation)], dtype=np.int64)
        nis = np.nan
        if rest.size:
            rows_rest = rows._replace(rows=rest)
            phi, noises = motion_model(config, 0.0, (config.accel_sigma_mps2,) * weights.size)
            new_means, new_covs, nis_all, log_det, status = _update(means, covs, phi, noises, False, report, rows_rest,
                                                                config.linearisation_passes)
            ok = status == UPDATED
            if ok.any():
                weights = reweighted(weights, np.where(ok, -0.5 * (nis_all + log_det), -np.inf))
                weights, means, covs = _pruned_mixture(weights, new_means, new_covs)
        return _finish(None, report, weights, means, covs, nis, max(rest.size, 1), config, warnings, "mixture")
    started = _fix_start(report, rows, config)
    if started is None:
        warnings += (("track_not_started", f"report seq {report.seq}: no bearing and no fix from its ranges and TOAs; "
                                           f"the track of {report.emitter_id!r} starts with a report that places it"),)
        return None, warnings
    weights, means, covs = started
    return _finish(None, report, weights, means, covs, np.nan, 1, config, warnings, "mixture")


def motion_model(config: NetworkConfig, dt_s: float, accel_sigmas_mps2: tuple[float, ...]):
    """Transition ``(6, 6)`` and process noises ``(C, 6, 6)`` over ``dt_s`` of the constant-velocity model at
    each horizontal intensity (:func:`core.tracking.motion.transitions`), the vertical axis at
    ``vertical_accel_sigma_mps2 / accel_sigma_mps2`` of it when that is set."""
    phi, noises = transitions(STATE_SIZE, (3,), True, dt_s, tuple(q * q for q in accel_sigmas_mps2))
    if config.vertical_accel_sigma_mps2 is not None:
        scale = np.ones(STATE_SIZE)
        scale[[2, 5]] = config.vertical_accel_sigma_mps2 / config.accel_sigma_mps2
        noises = noises * np.outer(scale, scale)
    return phi, noises


def velocity_prior(config: NetworkConfig) -> np.ndarray:
    """Covariance ``(3, 3)`` of the velocity at a track's start."""
    vertical = config.velocity_prior_sigma_mps if config.vertical_velocity_prior_sigma_mps is None else \
        config.vertical_velocity_prior_sigma_mps
    return np.diag([config.velocity_prior_sigma_mps ** 2] * 2 + [vertical ** 2])


def _pruned_mixture(weights, means, covs):
    """The Gaussian sum without components below :data:`core.tracking.range_mixture.MIN_WEIGHT`, and collapsed
    to its moments once every component's mean lies within :data:`MERGE_DISTANCE` of its own standard
    deviations from the sum's mean (Mahalanobis, under the component's covariance: the sum is then one
    Gaussian to within a fraction of each component's width): neighbouring components that the data have
    pulled onto the same point stay apart in weight forever and would keep the track a mixture."""
    keep = pruned(weights)
    weights, means, covs = weights[keep] / weights[keep].sum(), means[keep], covs[keep]
    if weights.size > 1:
        mean, cov = moments(weights, means, covs)
        offsets = means - mean
        distances = np.einsum("ci,ci->c", offsets, np.linalg.solve(covs, offsets[..., None])[..., 0])
        if distances.max() < MERGE_DISTANCE ** 2:
            return np.ones(1), mean[None], cov[None]
    return weights, means, covs


def _line_of_sight_mixture(report: Report, azimuth: int, elevation: int, config: NetworkConfig):
    """Gaussian sum ``(C,)``, ``(C, 6)``, ``(C, 6, 6)`` along the line of sight of one bearing: each component
    centred at its middle range on the measured direction, covering its sub-interval along the line of sight
    and the bearing's noise across it, velocity zero +- ``velocity_prior_sigma_mps``."""
    az = float(report.values[azimuth])
    sigma_az = float(report.sigmas[azimuth])
    if elevation >= 0:
        el, sigma_el = float(report.values[elevation]), float(report.sigmas[elevation])
    else:
        el, sigma_el = 0.0, config.azimuth_only_elevation_sigma_rad
    along = np.array([math.cos(el) * math.sin(az), math.cos(el) * math.cos(az), math.sin(el)])
    across_az = np.array([math.cos(az), -math.sin(az), 0.0])
    across_el = np.array([-math.sin(el) * math.sin(az), -math.sin(el) * math.cos(az), math.cos(el)])
    to_common = report.rotations[azimuth].T
    station = report.stations_enu_m[azimuth]
    middles, sigmas = component_ranges(config)
    count = middles.size
    means = np.zeros((count, STATE_SIZE))
    covs = np.zeros((count, STATE_SIZE, STATE_SIZE))
    for c, (r, sigma_r) in enumerate(zip(middles.tolist(), sigmas.tolist())):
        local = (sigma_r ** 2 * np.outer(along, along) + (r * sigma_az * math.cos(el)) ** 2 * np.outer(across_az, across_az)
                 + (r * sigma_el) ** 2 * np.outer(across_el, across_el))
        means[c, :3] = station + to_common @ (r * along)
        covs[c, :3, :3] = to_common @ local @ to_common.T
        covs[c, 3:, 3:] = velocity_prior(config)
    return np.full(count, 1.0 / count), means, 0.5 * (covs + np.swapaxes(covs, 1, 2))


def _fix_start(report: Report, rows: ReportRows, config: NetworkConfig):
    """A Gaussian, or a Gaussian sum over altitude, from the static fixes of a report without bearings.

    The free fix (:func:`core.estimators.solve`) with its CRLB when that places the emitter within
    :attr:`NetworkConfig.start_altitude_step_m` vertically. Otherwise (four TOAs from stations on the
    ground fix a point exactly, twice, and their hyperboloids meet at a shallow angle in height) the fixes at
    known altitudes over ``start_altitudes_m`` (step ``start_altitude_step_m``): each a component with its
    horizontal CRLB and half a step of height, weighted by the Laplace approximation of its likelihood
    (``exp(-chi2 / 2)`` times the square root of its CRLB's determinant). None when nothing fits.
    """
    from core.estimators import solve, solve_batch
    from core.problem import LocalPoint, Range, TimeOfArrival, build_problem

    used = [int(i) for i in rows.rows] + ([rows.toa_reference] if rows.toa_reference >= 0 else [])
    if not used:
        return None
    stations = [(f"s{i}", LocalPoint(*report.stations_enu_m[i].tolist())) for i in used]
    measurements = []
    for i in used:
        if report.kinds[i] == RANGE:
            measurements.append(Range(f"s{i}", float(report.values[i]), float(report.sigmas[i])))
        else:
            measurements.append(TimeOfArrival(f"s{i}", float(report.values[i] - report.values[rows.toa_reference]),
                                              float(report.sigmas[i])))
    step = config.start_altitude_step_m
    try:
        fix = solve(build_problem(stations, measurements))
        if np.all(np.isfinite(fix.crlb_enu_m2)) and math.sqrt(fix.crlb_enu_m2[2, 2]) <= step:
            means = np.zeros((1, STATE_SIZE))
            covs = np.zeros((1, STATE_SIZE, STATE_SIZE))
            means[0, :3] = fix.position_enu_m
            covs[0, :3, :3] = fix.crlb_enu_m2
            covs[0, 3:, 3:] = velocity_prior(config)
            return np.ones(1), means, covs
    except LocalizationError:
        pass
    low, high = config.start_altitudes_m
    altitudes = np.arange(low, high + 0.5 * step, step)
    fixes = solve_batch([build_problem(stations, measurements, altitude_m=float(h)) for h in altitudes])
    kept = [(h, f) for h, f in zip(altitudes.tolist(), fixes)
            if not isinstance(f, LocalizationError) and np.all(np.isfinite(f.crlb_enu_m2[:2, :2]))
            and np.linalg.det(f.crlb_enu_m2[:2, :2]) > 0.0]
    if not kept:
        return None
    log_w = np.array([-0.5 * f.chi2 + 0.5 * math.log(np.linalg.det(f.crlb_enu_m2[:2, :2])) for _, f in kept])
    weights = np.exp(log_w - log_w.max())
    weights /= weights.sum()
    means = np.zeros((len(kept), STATE_SIZE))
    covs = np.zeros((len(kept), STATE_SIZE, STATE_SIZE))
    for c, (h, f) in enumerate(kept):
        means[c, :3] = f.position_enu_m[0], f.position_enu_m[1], h
        covs[c, :2, :2] = f.crlb_enu_m2[:2, :2]
        covs[c, 2, 2] = (0.5 * step) ** 2
        covs[c, 3:, 3:] = velocity_prior(config)
    keep = pruned(weights)
    return weights[keep] / weights[keep].sum(), means[keep], covs[keep]


def _predicted(track: Track, time_s: float, config: NetworkConfig) -> Track:
    """The track's filter predicted to ``time_s`` (no report): each component with its own process noise,
    the IMM mixed first."""
    dt = time_s - track.time_s
    weights, means, covs = track.weights, np.array(track.means), np.array(track.covariances)
    if track.stage == "imm":
        weights, means, covs = imm.mixed(weights, means, covs,
                                         imm.switching_matrix(weights.size, dt, config.imm_mean_sojourn_s))
        levels = config.imm_accel_sigmas_mps2
    else:
        levels = (config.accel_sigma_mps2,) * weights.size
    phi, noises = motion_model(config, dt, levels)
    means, covs = np.ascontiguousarray(means), np.ascontiguousarray(covs)
    predict_kernel(means, covs, phi, noises)
    mean, cov = (means[0], covs[0]) if weights.size == 1 else moments(weights, means, covs)
    return replace(track, time_s=float(time_s), mean_enu=frozen_array(mean), covariance_enu=frozen_array(cov),
                   weights=frozen_array(weights), means=frozen_array(means), covariances=frozen_array(covs),
                   warnings=())


@functools.lru_cache(maxsize=64)
def _chi2_point(probability: float, dof: int) -> float:
    return float(chi2.ppf(probability, dof))


def _gather(gathered: dict, code: str, message: str, count: int) -> None:
    entry = gathered.setdefault(code, [message, 0])
    entry[1] += count


def _gathered(gathered: dict) -> tuple:
    return tuple((code, message if count == 1 or code == "late_report" else f"{message} (and {count - 1} more)")
                 for code, (message, count) in gathered.items())


def _check_real(name: str, value, loc=None) -> None:
    if isinstance(value, bool) or not isinstance(value, numbers.Real) or not math.isfinite(value):
        raise InvalidInput(f"{name} must be a finite number, got {value!r}", loc or (name,))


def _check_positive(name: str, value, loc=None) -> None:
    _check_real(name, value, loc)
    if not value > 0.0:
        raise InvalidInput(f"{name} must be > 0, got {value!r}", loc or (name,))


__all__ = ["NETWORK_WARNING_CODES", "ApplyOutcome", "HistoryEntry", "Kind", "NetworkConfig", "NetworkState",
           "Report", "ReportRows", "Track", "advance_track", "apply_reports", "new_network_state",
           "predict_tracks", "report_rows", "validate_report", "with_status"]
