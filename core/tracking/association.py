"""Many emitters from unlabelled bearings: association, track start across stations, track management.

A direction-finding network reports every bearing it measures, with no emitter label, missed detections and
false bearings. This module turns those bearings into one track per emitter, each track the network tracker's
filter (:mod:`core.tracking.network`: the same constant-velocity state, measurement model and update).

Public API (pure functions; the state is an immutable value)::

    config = AssociationConfig(network=NetworkConfig(accel_sigma_mps2=0.2, velocity_prior_sigma_mps=30.0))
    state = new_association_state()
    outcome = apply_observations(state, observations, config)   # Observation: one bearing + frequency
    tracks = current_tracks(outcome.state, time_s, config)     # netcore Tracks, status set by the rules below

**Scans.** Observations are processed in time order, grouped into scans: the bearings one station measured
at one time. Within a scan a track takes at most one bearing and a bearing feeds at most one track.

**Gating** on the predicted measurement and its innovation covariance, computed by the network tracker's own
update kernel (:func:`core.tracking.network_kernel.network_ukf_kernel`, one pass: the unscented transform of
the track's predicted position through :func:`core.measurements.measure_point`), so the gate and the update
share one measurement model. A pair passes when its NIS is inside the chi-square ``gate_probability`` point
and, when both carry a frequency, the frequencies differ by at most ``frequency_tolerance_hz``.

**Assignment: JPDA (chosen by measurement), or global nearest neighbour.** Each gated pair's likelihood ratio
against a false bearing is ``P_D N(z; z_hat, S) / lambda`` (``lambda`` the false-bearing density per
rad^dims). With ``method="jpda"`` (the default), the association probabilities of each cluster of tracks that
share gated bearings come from enumerating its feasible joint events (each track one bearing or none, a bearing
to one track at most; a missed track weighs ``1 - P_D``), and each track is updated with every gated bearing
(:func:`core.tracking.network.advance_track`) and left as predicted, the hypotheses merged by their
probabilities into one Gaussian (:func:`_scan_jpda`). With ``method="gnn"``, :func:`scipy.optimize.
linear_sum_assignment` maximises the scan's summed log likelihood ratios (unassigned: 0; only ratios above 1
kept) and assigned bearings update their track, unless another track could have taken the bearing at a cost
less than ``ambiguity_margin`` above (such a bearing counts as a hit but moves neither track). On the eight
variants of :func:`core.simulation.multi_emitter.multi_emitter_scene` (seeds 10-13) JPDA's mean GOSPA was
175-183 m on seven of them (354 m on the eighth, where a ghost started) against GNN's 203-593 m, with 0.06
identity switches a run against GNN's 0.44: where
two emitters on one frequency pass close by, GNN's hard decisions pull the two tracks onto a wrong pairing of
the bearings that it does not revisit, while JPDA weighs the pairings and follows both.

**Starting tracks, ghosts rejected.** Bearings no track took stay in a pool for ``init_window_s`` (the
latest scan of each station); starts are sought from ``init_window_s`` after the first scan on, once every
station's scan can be in the pool (three stations can place a ghost as well as an emitter where two
emitters line up; the others tell them apart). Candidates are built the way S-D assignment builds its
tuples: every pair of bearings of two stations (frequencies compatible) is crossed; a third station's
bearing must lie near the crossing's predicted bearing (every pair of a triple is tried: a near-collinear pair
crosses far from the emitter); each triple is fitted (Gauss-Newton maximum likelihood on the position,
:func:`core.measurements.predict`) and kept when its chi-square is inside the ``init_gate_probability`` point;
it is then extended with the best-fitting bearing of every further station whose NIS at the fit (the fit's
covariance propagated) is inside the gate, and refitted. Each candidate's score is the log likelihood ratio of
"one emitter made these bearings, the other stations missed it" against "these bearings are false" (Laplace
approximation over a uniform prior on ``surveillance_volume_m3``). The accepted candidates are those that
share no bearing with the largest total score (the S-D assignment problem as a set packing, solved exactly
by :func:`select_candidates`). Of the up to ``N^S`` crossings of ``N`` emitters seen by ``S`` stations, a
ghost needs three stations' bearings to agree on one point within the noise, and is chosen only when it
explains the bearings better than the real emitters that share them. A bearing without
elevation is taken, for the fit, as elevation 0 with ``network.azimuth_only_elevation_sigma_rad``, as the
network tracker's start does.

**Track management** (statuses are those of the network sessions):

- a track starts ``tentative`` from an accepted candidate: position the fit (covariance its inverse Fisher
  information), velocity zero with the network tracker's prior (:func:`core.tracking.network.velocity_prior`);
  its starting bearings count as hits;
- each later scan of any station is a hit (a bearing assigned) or a miss. A tentative track is ``confirmed``
  once ``confirm_hits`` of its last ``confirm_window`` scans are hits (M of N), and deleted as soon as it can no
  longer reach that (more than ``confirm_window - confirm_hits`` misses among them): a ghost or clutter-born
  track gets the bearings of at most the stations whose lines made it and dies within a few scans;
- a confirmed track without a hit for ``coast_after_s`` is ``coasting`` (it still gates and may take
  bearings again, which makes it ``confirmed``), and ends after ``end_after_s`` without one;
- ids are ``"t1"``, ``"t2"``, ... in start order, never reused.
"""

from __future__ import annotations

import copy
import itertools
import math
from collections.abc import Sequence
from dataclasses import dataclass, field, replace
from typing import NamedTuple

import numpy as np
from scipy.optimize import linear_sum_assignment
from scipy.stats import chi2

from core.angles import line_of_sight_enu, station_to_common, wrap_to_pi
from core.errors import InvalidInput
from core.measurements import AZIMUTH, ELEVATION, predict
from core.tracking.network import (
    NetworkConfig,
    NetworkState,
    Report,
    Track,
    advance_track,
    predict_tracks,
    report_rows,
)
from core.tracking.network_kernel import STATE_SIZE, UPDATED, network_ukf_kernel
from core.tracking.network_update import velocity_prior
from core.tracking.state import frozen_array

#: Version of the :meth:`AssociationState.to_dict` layout.
ASSOCIATION_STATE_FORMAT = 1
#: A pair of bearings whose lines of sight are closer to parallel than this (rad) is not crossed.
MIN_CROSSING_ANGLE_RAD = math.radians(2.0)
#: Gauss-Newton iterations of a candidate's fit (each from the pair crossing, which is within a few
#: standard deviations of the optimum).
FIT_ITERATIONS = 6
#: Half-width of the coarse third-station window around a crossing's predicted azimuth, in units of the
#: pair's combined azimuth sigma (the exact test is the fit's chi-square).
COARSE_SIGMAS = 6.0
#: With this many tracks or more, a scan's pairs are screened (:func:`_coarse_gate`) before the exact gate;
#: with fewer, the screen costs more than the exact gate it saves.
COARSE_FROM_TRACKS = 8


@dataclass(frozen=True)
class AssociationConfig:
    """Settings of the association and track management (module docstring).

    Attributes
    ----------
    network : NetworkConfig
        The filter of each track (motion model, velocity prior, update passes).
    detection_probability : float
        Probability that a station measures a bearing of an emitter in one scan.
    false_density_per_rad2 : float
        False bearings per scan per unit of (azimuth, elevation) area (per rad for azimuth-only bearings).
    surveillance_volume_m3 : float
        The volume emitters are sought in (the uniform prior of a candidate's position).
    gate_probability : float
        Chi-square probability of the track gate.
    init_gate_probability : float
        Chi-square probability a candidate's fit and each added bearing must pass.
    frequency_tolerance_hz : float
        Largest frequency difference of one emitter's bearings (either frequency NaN: no frequency gate).
    init_window_s : float
        Unassigned bearings stay this long in the start pool (the latest scan of each station is used).
    init_min_stations : int
        Stations a candidate needs (at least 3: two bearings always cross).
    init_ambiguity_margin : float
        A candidate starts a track only when every packing without it is this much less likely (log
        likelihood ratio; :func:`select_candidates`); 0: off.
    ambiguity_margin : float
        A bearing updates its track only when no other track could take it at a cost (log likelihood
        ratio) less than this above the assignment's (:func:`_ambiguous`); 0: every assigned bearing updates.
    method : str
        ``"gnn"`` (global nearest neighbour) or ``"jpda"`` (joint probabilistic data association,
        :func:`_scan_jpda`); compared on the scenes in the module docstring.
    range_min_m, range_max_m : float
        A crossing nearer to or farther from either station than these is not a candidate.
    confirm_hits, confirm_window : int
        M of N: hits among the last scans needed to confirm (and whose impossibility deletes a tentative track).
    coast_after_s, end_after_s : float
        A confirmed track without a hit for longer is ``coasting``, then ended.
    """

    network: NetworkConfig = field(default_factory=NetworkConfig)
    detection_probability: float = 0.9
    false_density_per_rad2: float = 0.2
    surveillance_volume_m3: float = 1e13
    gate_probability: float = 0.999
    init_gate_probability: float = 0.99
    frequency_tolerance_hz: float = 10e3
    init_window_s: float = 1.0
    init_min_stations: int = 3
    init_ambiguity_margin: float = 0.0
    ambiguity_margin: float = 2.0
    method: str = "jpda"
    range_min_m: float = 200.0
    range_max_m: float = 100e3
    confirm_hits: int = 6
    confirm_window: int = 8
    coast_after_s: float = 5.0
    end_after_s: float = 30.0

    def __post_init__(self):
        if not isinstance(self.network, NetworkConfig):
            raise InvalidInput("network must be a NetworkConfig", ("network",))
        for name in ("false_density_per_rad2", "surveillance_volume_m3", "frequency_tolerance_hz",
                     "init_window_s", "range_min_m", "range_max_m", "coast_after_s", "end_after_s"):
            value = getattr(self, name)
            if not (isinstance(value, (int, float)) and math.isfinite(value) and value > 0.0):
                raise InvalidInput(f"{name} must be a finite number > 0", (name,))
        for name in ("detection_probability", "gate_probability", "init_gate_probability"):
            value = getattr(self, name)
            if not 0.0 < value < 1.0:
                raise InvalidInput(f"{name} must be inside (0, 1)", (name,))
        if not 3 <= self.init_min_stations:
            raise InvalidInput("init_min_stations must be >= 3", ("init_min_stations",))
        if self.method not in ("gnn", "jpda"):
            raise InvalidInput("method must be \"gnn\" or \"jpda\"", ("method",))
        if not 1 <= self.confirm_hits <= self.confirm_window:
            raise InvalidInput("confirm_hits must be from 1 to confirm_window", ("confirm_hits",))
        if not self.end_after_s > self.coast_after_s:
            raise InvalidInput("end_after_s must be above coast_after_s", ("end_after_s",))
        if not self.end_after_s < self.network.end_after_s:
            raise InvalidInput("end_after_s must be below network.end_after_s (the filter restarts after that)",
                               ("end_after_s",))


@dataclass(frozen=True, eq=False)
class Observation:
    """One unlabelled bearing: a station's azimuth (and elevation) of one signal at one time.

    Attributes
    ----------
    report : Report
        The network tracker's report of that bearing: one station's azimuth row and, optionally, its
        elevation row (``emitter_id`` is not read).
    frequency_hz : float
        The signal's frequency; NaN when not known.
    """

    report: Report
    frequency_hz: float = math.nan

    def __post_init__(self):
        kinds = self.report.kinds
        azimuth = np.flatnonzero(kinds == AZIMUTH)
        elevation = np.flatnonzero(kinds == ELEVATION)
        if azimuth.size != 1 or elevation.size > 1 or kinds.size != azimuth.size + elevation.size or len(
                set(self.report.station_ids)) != 1:
            raise InvalidInput("an unlabelled bearing is one station's azimuth and at most one elevation",
                               ("measurements",))

    @property
    def time_s(self) -> float:
        return self.report.time_s

    @property
    def station_id(self) -> str:
        return self.report.station_ids[0]


def observations_from_report(report: Report, frequency_hz: float = math.nan) -> list[Observation]:
    """Split a report into its bearings, one :class:`Observation` per station (its azimuth and elevation rows).

    Raises
    ------
    InvalidInput
        When the report holds a measurement that is not an azimuth or an elevation, or a station's rows are
        not one azimuth and at most one elevation (``loc`` names the measurement).
    """
    out = []
    for station in dict.fromkeys(report.station_ids):
        rows = [i for i, s in enumerate(report.station_ids) if s == station]
        for i in rows:
            if report.kinds[i] not in (AZIMUTH, ELEVATION):
                raise InvalidInput("association \"auto\" takes bearings only", ("measurements", i, "kind"))
        try:
            out.append(Observation(Report(report.seq, report.time_s, "", tuple(report.station_ids[i] for i in rows),
                                          report.stations_enu_m[rows], report.rotations[rows], report.kinds[rows],
                                          report.values[rows], report.sigmas[rows]), float(frequency_hz)))
        except InvalidInput:
            raise InvalidInput("a station's bearing is one azimuth and at most one elevation",
                               ("measurements", rows[0])) from None
    return out


@dataclass(frozen=True, eq=False)
class MultiTrack:
    """A track of the association state.

    Attributes
    ----------
    track : Track
        The network tracker's track (its filter; ``id`` is this track's id).
    frequency_hz : float
        Mean frequency of its bearings (NaN when none carried one).
    frequency_count : int
        Bearings the mean is over.
    hits : tuple of bool
        The last ``confirm_window`` scans: a bearing assigned (True) or not.
    last_hit_s : float
    confirmed : bool
    started_s : float
    confirmed_s : float
        When it was confirmed (NaN while tentative).
    """

    track: Track
    frequency_hz: float
    frequency_count: int
    hits: tuple[bool, ...]
    last_hit_s: float
    confirmed: bool
    started_s: float
    confirmed_s: float = math.nan

    @property
    def id(self) -> str:
        return self.track.id


@dataclass(frozen=True, eq=False)
class AssociationState:
    """Everything an unlabelled session carries between posts.

    Attributes
    ----------
    tracks : tuple of MultiTrack
    pool : tuple of Observation
        Unassigned bearings of the last ``init_window_s``.
    next_id : int
        The number of the next track id.
    last_time_s : float or None
        Time of the newest processed scan.
    first_time_s : float or None
        Time of the first scan.
    """

    tracks: tuple[MultiTrack, ...] = ()
    pool: tuple[Observation, ...] = ()
    next_id: int = 1
    last_time_s: float | None = None
    first_time_s: float | None = None

    def to_dict(self) -> dict:
        """Plain JSON-able data; exact inverse of :meth:`from_dict` (a service stores it)."""
        return {"format": ASSOCIATION_STATE_FORMAT, "next_id": self.next_id, "last_time_s": self.last_time_s,
                "first_time_s": self.first_time_s,
                "tracks": [{"track": t.track.to_dict(), "frequency_hz": _float_or_none(t.frequency_hz),
                            "frequency_count": t.frequency_count, "hits": list(t.hits), "last_hit_s": t.last_hit_s,
                            "confirmed": t.confirmed, "started_s": t.started_s,
                            "confirmed_s": _float_or_none(t.confirmed_s)} for t in self.tracks],
                "pool": [{"report": o.report.to_dict(), "frequency_hz": _float_or_none(o.frequency_hz)}
                         for o in self.pool]}

    @classmethod
    def from_dict(cls, data: dict) -> AssociationState:
        """Rebuild a state from :meth:`to_dict` output (after a JSON round trip).

        Raises
        ------
        InvalidInput
            When the data is not an association state of a known format.
        """
        if not isinstance(data, dict) or data.get("format") != ASSOCIATION_STATE_FORMAT:
            raise InvalidInput(f"association state must be a mapping with format {ASSOCIATION_STATE_FORMAT}")
        try:
            tracks = tuple(MultiTrack(Track.from_dict(t["track"]), _nan_if_none(t["frequency_hz"]),
                                      int(t["frequency_count"]), tuple(bool(h) for h in t["hits"]),
                                      float(t["last_hit_s"]), bool(t["confirmed"]), float(t["started_s"]),
                                      _nan_if_none(t["confirmed_s"])) for t in data["tracks"])
            pool = tuple(Observation(Report.from_dict(o["report"]), _nan_if_none(o["frequency_hz"]))
                         for o in data["pool"])
            last, first = data["last_time_s"], data["first_time_s"]
            return cls(tracks, pool, int(data["next_id"]), None if last is None else float(last),
                       None if first is None else float(first))
        except (KeyError, TypeError, ValueError) as error:
            raise InvalidInput(f"association state is malformed: {error}") from None

    def __eq__(self, other):
        if not isinstance(other, AssociationState):
            return NotImplemented
        return self.to_dict() == other.to_dict()

    __hash__ = None


def _float_or_none(value: float) -> float | None:
    return None if math.isnan(value) else value


def _nan_if_none(value) -> float:
    return math.nan if value is None else float(value)


class AssociationOutcome(NamedTuple):
    """What :func:`apply_observations` did.

    Attributes
    ----------
    state : AssociationState
    applied : int
        Observations processed.
    late : int
        Observations older than the newest processed scan: counted, not applied.
    started, ended : tuple of str
        Ids of the tracks started and ended.
    """

    state: AssociationState
    applied: int
    late: int
    started: tuple[str, ...]
    ended: tuple[str, ...]


def new_association_state() -> AssociationState:
    """The state before any bearing."""
    return AssociationState()


def status_of(track: MultiTrack, now_s: float, config: AssociationConfig) -> str:
    """``tentative``, ``confirmed`` or ``coasting`` as of ``now_s`` (module docstring)."""
    if not track.confirmed:
        return "tentative"
    return "coasting" if now_s - track.last_hit_s > config.coast_after_s else "confirmed"


def current_tracks(state: AssociationState, time_s: float, config: AssociationConfig) -> tuple[Track, ...]:
    """Every live track predicted to ``time_s`` (one newer is returned as it is), its status by the rules of
    the module docstring, in id order."""
    if not state.tracks:
        return ()
    now = time_s if state.last_time_s is None else max(time_s, state.last_time_s)
    predicted = predict_tracks(NetworkState(tracks=tuple(t.track for t in state.tracks)), time_s, config.network)
    return tuple(replace(p, status=status_of(t, now, config)) for t, p in zip(state.tracks, predicted))


def apply_observations(state: AssociationState, observations: Sequence[Observation],
                       config: AssociationConfig) -> AssociationOutcome:
    """Process bearings: scan by scan in time order, gate, assign, update, start and end tracks.

    Parameters
    ----------
    state : AssociationState
    observations : sequence of Observation
        Any order; one older than the newest processed scan is counted ``late`` and not applied.
    config : AssociationConfig

    Returns
    -------
    AssociationOutcome
    """
    late = 0
    accepted = []
    for obs in observations:
        if not isinstance(obs, Observation):
            raise InvalidInput("observations must be Observation")
        if state.last_time_s is not None and obs.time_s < state.last_time_s:
            late += 1
        else:
            accepted.append(obs)
    accepted.sort(key=lambda o: (o.time_s, o.station_id, o.report.seq))
    tracks = list(state.tracks)
    pool = list(state.pool)
    next_id = state.next_id
    last, first = state.last_time_s, state.first_time_s
    started, ended = [], []
    for (time_s, _), scan in itertools.groupby(accepted, key=lambda o: (o.time_s, o.station_id)):
        scan = list(scan)
        first = time_s if first is None else first
        tracks, gone = _drop_ended(tracks, time_s, config)
        ended.extend(gone)
        tracks, unassigned = _scan(tracks, scan, config)
        pool = [o for o in pool if o.time_s > time_s - config.init_window_s] + unassigned
        if unassigned and time_s - first >= config.init_window_s:
            tracks, pool, next_id, new = _start_tracks(tracks, pool, next_id, time_s, config)
            started.extend(new)
        last = time_s
    return AssociationOutcome(AssociationState(tuple(tracks), tuple(pool), next_id, last, first), len(accepted), late,
                              tuple(started), tuple(ended))


def apply_reports_auto(state: AssociationState, reports: Sequence[Report], frequencies_hz: Sequence[float],
                       config: AssociationConfig) -> AssociationOutcome:
    """A network session's post under ``"association": "auto"``: each report split into its stations' bearings
    (:func:`observations_from_report`, the report's ``frequency_hz`` on each, NaN when absent) and applied.

    Raises
    ------
    InvalidInput
        For the first report that is not bearings; ``loc`` starts with its index.
    """
    observations = []
    for k, (report, frequency) in enumerate(zip(reports, frequencies_hz, strict=True)):
        try:
            observations.extend(observations_from_report(report, frequency))
        except InvalidInput as error:
            raise InvalidInput(error.message, (k,) + (error.loc or ())) from None
    return apply_observations(state, observations, config)


def _drop_ended(tracks, now_s, config):
    kept, gone = [], []
    for t in tracks:
        (gone if now_s - t.last_hit_s > config.end_after_s else kept).append(t)
    return kept, [t.id for t in gone]


# ---------------------------------------------------------------------------------------------------------------
# One scan: gate, assign, update


def _frequency_ok(a: float, b: float, config: AssociationConfig) -> bool:
    return not (abs(a - b) > config.frequency_tolerance_hz)  # NaN on either side: True


def gate_costs(tracks: Sequence[MultiTrack], scan: Sequence[Observation], config: AssociationConfig):
    """The association costs of one scan's bearings against the tracks (JPDA and GNN).

    Returns
    -------
    cost : ndarray, shape (T, B)
        ``-log`` likelihood ratio of each pair (track's bearing against a false one); ``inf`` outside the gate.
    nis : ndarray, shape (T, B)
    """
    count, size = len(tracks), len(scan)
    cost = np.full((count, size), np.inf)
    nis_out = np.full((count, size), np.inf)
    if not count or not size:
        return cost, nis_out
    time_s = scan[0].time_s
    if count >= COARSE_FROM_TRACKS:
        near = _coarse_gate(tracks, scan, config)
    else:
        near = np.array([[_frequency_ok(t.frequency_hz, o.frequency_hz, config) for o in scan] for t in tracks])
    needed = np.flatnonzero(near.any(axis=1))
    if not needed.size:
        return cost, nis_out
    predicted = predict_tracks(NetworkState(tracks=tuple(tracks[i].track for i in needed)), time_s, config.network)
    all_means = np.array([p.mean_enu for p in predicted])
    all_covs = np.array([p.covariance_enu for p in predicted])
    eye = np.eye(STATE_SIZE)
    log_pd_over_lambda = math.log(config.detection_probability / config.false_density_per_rad2)
    for j, obs in enumerate(scan):
        local = np.flatnonzero(near[needed, j])
        if not local.size:
            continue
        report = obs.report
        rows = report_rows(report)
        dof = rows.rows.size
        means, covs = np.ascontiguousarray(all_means[local]), np.ascontiguousarray(all_covs[local])
        noises = np.zeros_like(covs)
        new_means, new_covs = np.empty_like(means), np.empty_like(covs)
        nis, log_det, status = np.empty(local.size), np.empty(local.size), np.empty(local.size, dtype=np.int64)
        network_ukf_kernel(means, covs, eye, noises, False, report.stations_enu_m, report.rotations, report.kinds,
                           rows.values, rows.variances, rows.rows, rows.toa_reference, 1, new_means, new_covs, nis,
                           log_det, status)
        gate = _chi2_point(config.gate_probability, dof)
        for k, i in enumerate(needed[local].tolist()):
            if status[k] != UPDATED or not nis[k] <= gate:
                continue
            nis_out[i, j] = nis[k]
            cost[i, j] = 0.5 * (nis[k] + log_det[k] + dof * math.log(2.0 * math.pi)) - log_pd_over_lambda
    return cost, nis_out


def _coarse_gate(tracks: Sequence[MultiTrack], scan: Sequence[Observation], config: AssociationConfig) -> np.ndarray:
    """Pairs ``(T, B)`` that may pass the gate: frequencies compatible and the bearing's azimuth within
    :data:`COARSE_SIGMAS` of the track's azimuth from the scan's station, with an upper bound of its standard
    deviation (the root of the position covariance's trace, grown by the velocity's over the interval, over
    the range, with the bearing's own). The exact test on the pairs left is the gate itself."""
    station, rotation = scan[0].report.stations_enu_m[0], scan[0].report.rotations[0]
    means = np.array([t.track.mean_enu for t in tracks])
    covs = np.array([t.track.covariance_enu for t in tracks])
    dt = np.abs(scan[0].time_s - np.array([t.track.time_s for t in tracks]))
    positions = means[:, :3] + means[:, 3:] * dt[:, None]
    spread_m = (np.sqrt(np.trace(covs[:, :3, :3], axis1=1, axis2=2))
                + dt * np.sqrt(np.trace(covs[:, 3:, 3:], axis1=1, axis2=2))
                + 3.0 * config.network.accel_sigma_mps2 * dt ** 1.5)
    seen, _ = predict(positions, 0.0, station[None], rotation[None], np.array([AZIMUTH]))
    distances = np.linalg.norm(positions - station, axis=1)
    azimuths = np.array([o.report.values[o.report.kinds == AZIMUTH][0] for o in scan])
    sigmas = np.array([o.report.sigmas[o.report.kinds == AZIMUTH][0] for o in scan])
    with np.errstate(divide="ignore", invalid="ignore"):
        angular = np.where(distances > spread_m, spread_m / distances, np.inf)
    window = COARSE_SIGMAS * np.hypot(angular[:, None], sigmas[None, :])
    near = np.abs(wrap_to_pi(azimuths[None, :] - seen[:, 0][:, None])) < window
    frequencies = np.array([t.frequency_hz for t in tracks])
    near &= ~(np.abs(frequencies[:, None] - np.array([o.frequency_hz for o in scan])[None, :])
              > config.frequency_tolerance_hz)
    return near


def _scan(tracks, scan, config):
    """Associate one scan's bearings (JPDA or GNN, ``config.method``), update the tracks; returns the tracks and
    the bearings left for starts."""
    time_s = scan[0].time_s
    pairs = {}
    if tracks:
        cost, _ = gate_costs(tracks, scan, config)
        if config.method == "jpda":
            return _scan_jpda(tracks, scan, cost, config)
        usable = np.minimum(np.where(np.isfinite(cost), cost, 0.0), 0.0)
        if usable.any():
            rows, cols = linear_sum_assignment(usable)
            pairs = {int(i): int(j) for i, j in zip(rows, cols) if cost[i, j] < 0.0}
    unsure = _ambiguous(pairs, cost, config.ambiguity_margin) if pairs and config.ambiguity_margin > 0.0 else set()
    out = [_after_scan(t, None if pairs.get(i) is None else scan[pairs[i]], time_s, config, i in unsure)
           for i, t in enumerate(tracks)]
    taken = set(pairs.values())
    return [t for t in out if t is not None], [o for j, o in enumerate(scan) if j not in taken]


#: Largest number of tracks in one JPDA cluster whose joint events are enumerated; larger ones fall back to
#: the GNN assignment.
JPDA_MAX_CLUSTER = 6
#: A JPDA hypothesis (a bearing, or none) less probable than this is dropped.
JPDA_NEGLIGIBLE = 1e-3


def _jpda_weights(likelihood: np.ndarray, missed: float) -> tuple[np.ndarray, np.ndarray]:
    """Association probabilities of one scan: ``beta (T, B)`` and ``beta_0 (T,)`` (no bearing), by enumerating
    the feasible joint events of each cluster of tracks that share gated bearings. ``likelihood`` is each
    pair's ``P_D N / lambda`` (0 outside the gate); a track left without a bearing weighs ``missed``."""
    from scipy.sparse import coo_matrix
    from scipy.sparse.csgraph import connected_components

    count, size = likelihood.shape
    beta, beta0 = np.zeros((count, size)), np.ones(count)
    gated = likelihood > 0.0
    rows, cols = np.nonzero(gated)
    if not rows.size:
        return beta, beta0
    # Clusters: the connected parts of the graph of tracks and bearings joined by their gates.
    graph = coo_matrix((np.ones(rows.size), (rows, count + cols)), shape=(count + size, count + size))
    labels = connected_components(graph, directed=False)[1][:count]
    for label in np.unique(labels[np.unique(rows)]).tolist():
        order = np.flatnonzero(labels == label).tolist()
        if len(order) == 1:
            # One track: its bearings or none, in closed form.
            i = order[0]
            total = missed + likelihood[i].sum()
            beta[i], beta0[i] = likelihood[i] / total, missed / total
            continue
        if len(order) > JPDA_MAX_CLUSTER:
            picked_tracks, picked = linear_sum_assignment(-np.log(np.where(gated[order], likelihood[order], 1e-300)))
            for r, c in zip(picked_tracks, picked):
                if gated[order[r], c]:
                    beta[order[r], c], beta0[order[r]] = 1.0, 0.0
            continue
        acc, acc0, total = _joint_events(order, gated, likelihood, missed)
        beta[order] = acc[order] / total
        beta0[order] = acc0[order] / total
    return beta, beta0


def _joint_events(order: list, gated: np.ndarray, likelihood: np.ndarray, missed: float):
    """Sum over the feasible joint events of the tracks ``order`` (each takes one gated bearing no other
    takes, or none) of their weights, per track and bearing: ``(T, B)``, per track for no bearing ``(T,)``,
    and in all."""
    count, size = likelihood.shape
    acc, acc0, total = np.zeros((count, size)), np.zeros(count), 0.0
    stack = [(0, frozenset(), 1.0, ())]
    while stack:
        position, used, weight, picks = stack.pop()
        if position == len(order):
            total += weight
            for i, j in picks:
                if j < 0:
                    acc0[i] += weight
                else:
                    acc[i, j] += weight
            continue
        i = order[position]
        stack.append((position + 1, used, weight * missed, picks + ((i, -1),)))
        for j in np.flatnonzero(gated[i]).tolist():
            if j not in used:
                stack.append((position + 1, used | {j}, weight * likelihood[i, j], picks + ((i, j),)))
    return acc, acc0, total


def _scan_jpda(tracks, scan, cost, config):
    """JPDA in place of GNN: each track updated with every gated bearing of the scan and left as predicted,
    the hypotheses merged by their association probabilities (the Gaussian sum's moments; for a linear model
    this is the PDA update); a hit when the track's bearing probability is above one half; a bearing whose
    probability of belonging to any track is below one half goes to the start pool."""
    time_s = scan[0].time_s
    likelihood = np.where(np.isfinite(cost), np.exp(-np.where(np.isfinite(cost), cost, 0.0)), 0.0)
    beta, beta0 = _jpda_weights(likelihood, 1.0 - config.detection_probability)
    out = []
    for i, t in enumerate(tracks):
        # Hypotheses below JPDA_NEGLIGIBLE are dropped (the rest renormalised): an isolated track with one
        # bearing deep in its gate is then updated as GNN would, at GNN's cost.
        options = np.flatnonzero(beta[i] > JPDA_NEGLIGIBLE).tolist()
        keep_missed = beta0[i] > JPDA_NEGLIGIBLE
        if not options or t.track.stage == "imm" or (len(options) == 1 and not keep_missed):
            best = int(np.argmax(beta[i])) if options else -1
            hit = bool(options) and beta[i, best] > 0.5
            out.append(_after_scan(t, scan[best] if hit else None, time_s, config))
            continue
        weights, means, covs, updated = [], [], [], []
        if keep_missed:
            predicted = predict_tracks(NetworkState(tracks=(t.track,)), time_s, config.network)[0]
            weights, means, covs = [beta0[i]], [predicted.mean_enu], [predicted.covariance_enu]
        for j in options:
            track, _ = advance_track(t.track, _labelled(scan[j].report, t.id), config.network)
            weights.append(beta[i, j])
            means.append(track.mean_enu)
            covs.append(track.covariance_enu)
            updated.append(track)
        weights = np.array(weights) / np.sum(weights)
        mean = np.einsum("k,ki->i", weights, np.array(means))
        spread = np.array(means) - mean
        cov = np.einsum("k,kij->ij", weights, np.array(covs)) + np.einsum("k,ki,kj->ij", weights, spread, spread)
        cov = 0.5 * (cov + cov.T)
        best = int(np.argmax(weights[1:] if keep_missed else weights))
        merged = replace(updated[best], mean_enu=frozen_array(mean), covariance_enu=frozen_array(cov),
                         weights=frozen_array([1.0]), means=frozen_array(mean[None]),
                         covariances=frozen_array(cov[None]))
        hit = 1.0 - beta0[i] > 0.5
        hits = (t.hits + (bool(hit),))[-config.confirm_window:]
        if not hit and not t.confirmed and hits.count(False) > config.confirm_window - config.confirm_hits:
            continue
        confirmed = t.confirmed or hits.count(True) >= config.confirm_hits
        out.append(MultiTrack(merged, t.frequency_hz, t.frequency_count, hits, time_s if hit else t.last_hit_s,
                              confirmed, t.started_s, time_s if confirmed and not t.confirmed else t.confirmed_s))
    claimed = beta.sum(axis=0)
    return [t for t in out if t is not None], [o for j, o in enumerate(scan) if claimed[j] < 0.5]


def _ambiguous(pairs: dict, cost: np.ndarray, margin: float) -> set:
    """Tracks whose assigned bearing is not decisively theirs: another track could take it (swapping bearings
    with it, or taking it while left without one) at a cost less than ``margin`` above the assignment's."""
    out = set()
    for i, j in pairs.items():
        for k in np.flatnonzero(np.isfinite(cost[:, j])).tolist():
            if k == i:
                continue
            other = pairs.get(k)
            if other is None:
                worse = cost[k, j] - cost[i, j]
            elif np.isfinite(cost[i, other]):
                worse = cost[k, j] + cost[i, other] - cost[i, j] - cost[k, other]
            else:
                continue
            if worse < margin:
                out.update((i, k))
    return out


def _after_scan(track: MultiTrack, obs: Observation | None, time_s: float, config: AssociationConfig,
                unsure: bool = False):
    """A track after one scan (None: deleted as a tentative track that can no longer confirm). With ``unsure``
    the bearing counts as a hit but does not update the track (:func:`_ambiguous`)."""
    hits = (track.hits + (obs is not None,))[-config.confirm_window:]
    if obs is None:
        if not track.confirmed and hits.count(False) > config.confirm_window - config.confirm_hits:
            return None
        return MultiTrack(track.track, track.frequency_hz, track.frequency_count, hits, track.last_hit_s,
                          track.confirmed, track.started_s, track.confirmed_s)
    confirmed = track.confirmed or hits.count(True) >= config.confirm_hits
    confirmed_s = time_s if confirmed and not track.confirmed else track.confirmed_s
    if unsure:
        return MultiTrack(track.track, track.frequency_hz, track.frequency_count, hits, time_s, confirmed,
                          track.started_s, confirmed_s)
    updated, _ = advance_track(track.track, _labelled(obs.report, track.id), config.network)
    frequency, count = track.frequency_hz, track.frequency_count
    if math.isfinite(obs.frequency_hz):
        count += 1
        frequency = obs.frequency_hz if not math.isfinite(frequency) else (
            frequency + (obs.frequency_hz - frequency) / count)
    return MultiTrack(updated, frequency, count, hits, time_s, confirmed, track.started_s, confirmed_s)


def _labelled(report: Report, track_id: str) -> Report:
    """The report as its track's (``emitter_id`` set): a shallow copy, its arrays read-only and shared."""
    out = copy.copy(report)
    object.__setattr__(out, "emitter_id", track_id)
    return out


# ---------------------------------------------------------------------------------------------------------------
# Starting tracks from bearings of three or more stations


class Candidate(NamedTuple):
    """A possible emitter: the pool bearings it explains, its fitted position and score.

    Attributes
    ----------
    members : tuple of int
        Pool indices, one per station.
    position_enu_m : ndarray, shape (3,)
    covariance_enu_m2 : ndarray, shape (3, 3)
        Inverse Fisher information of the fit.
    chi2 : float
    score : float
        Log likelihood ratio against "all false" (module docstring).
    """

    members: tuple[int, ...]
    position_enu_m: np.ndarray
    covariance_enu_m2: np.ndarray
    chi2: float
    score: float


class _Pool(NamedTuple):
    """The pool's bearings as arrays ``(P, ...)``: two rows (azimuth, elevation) each."""

    station: np.ndarray       # (P,) int, station index
    positions: np.ndarray     # (P, 3)
    rotations: np.ndarray     # (P, 3, 3)
    values: np.ndarray        # (P, 2) azimuth, elevation (0 when not measured)
    sigmas: np.ndarray        # (P, 2)
    directions: np.ndarray    # (P, 3) line of sight, common frame
    frequency: np.ndarray     # (P,)
    has_elevation: np.ndarray  # (P,) bool


def _pool_arrays(pool: Sequence[Observation], config: AssociationConfig) -> _Pool:
    names = {}
    station = np.empty(len(pool), dtype=np.int64)
    positions = np.empty((len(pool), 3))
    rotations = np.empty((len(pool), 3, 3))
    values = np.zeros((len(pool), 2))
    sigmas = np.full((len(pool), 2), config.network.azimuth_only_elevation_sigma_rad)
    has_elevation = np.zeros(len(pool), dtype=bool)
    for k, obs in enumerate(pool):
        report = obs.report
        station[k] = names.setdefault(obs.station_id, len(names))
        positions[k] = report.stations_enu_m[0]
        rotations[k] = report.rotations[0]
        for kind, value, sigma in zip(report.kinds.tolist(), report.values.tolist(), report.sigmas.tolist()):
            column = 0 if kind == AZIMUTH else 1
            values[k, column], sigmas[k, column] = value, sigma
            has_elevation[k] |= kind == ELEVATION
    directions = station_to_common(line_of_sight_enu(values[:, 0], values[:, 1]), rotations)
    frequency = np.array([obs.frequency_hz for obs in pool], dtype=float)
    return _Pool(station, positions, rotations, values, sigmas, directions, frequency, has_elevation)


def _start_tracks(tracks, pool, next_id, time_s, config):
    """Start tracks from the pool (module docstring); returns tracks, pool, next id and the new ids."""
    latest = {}
    for obs in pool:
        latest[obs.station_id] = max(latest.get(obs.station_id, -math.inf), obs.time_s)
    usable = [o for o in pool if o.time_s == latest[o.station_id]]
    if len(latest) < config.init_min_stations:
        return tracks, pool, next_id, []
    candidates = find_candidates(usable, config)
    used: set[int] = set()
    new_ids = []
    for cand in select_candidates(candidates, len(usable), config.init_ambiguity_margin):
        used.update(cand.members)
        members = [usable[k] for k in cand.members]
        track_id = f"t{next_id}"
        next_id += 1
        new_ids.append(track_id)
        tracks.append(_new_track(track_id, cand, members, config))
    consumed = {id(usable[k]) for k in used}
    return tracks, [o for o in pool if id(o) not in consumed], next_id, new_ids


def select_candidates(candidates: Sequence[Candidate], size: int, margin: float = 0.0) -> list[Candidate]:
    """The candidates that share no bearing with the largest total score: the S-D assignment problem as a
    set packing, ``max sum score_k x_k`` over binary ``x`` with every bearing in at most one chosen candidate,
    solved exactly (:func:`scipy.optimize.milp`). A greedy pick by score is not enough: where stations see two
    emitters nearly in line, a ghost that borrows one bearing of each can out-score either real emitter and
    would block both.

    Parameters
    ----------
    candidates : sequence of Candidate
        Scores positive.
    size : int
        Number of bearings (pool indices ``0 .. size-1``).
    margin : float
        Above 0: a chosen candidate is returned only when the best packing without it scores at least this
        much (log likelihood ratio) less; where another explanation of its bearings is about as likely (a
        missed detection can make a ghost and an emitter equally good), the next scans decide.

    Returns
    -------
    list of Candidate
        In descending score.
    """
    if len(candidates) <= 1:
        return list(candidates)
    from scipy.optimize import Bounds, LinearConstraint, milp
    from scipy.sparse import coo_matrix

    rows = [m for c in candidates for m in c.members]
    cols = [k for k, c in enumerate(candidates) for _ in c.members]
    usage = LinearConstraint(coo_matrix((np.ones(len(rows)), (rows, cols)), shape=(size, len(candidates))), -np.inf,
                             1.0)
    scores = np.array([c.score for c in candidates])
    integral = np.ones(len(candidates))
    result = milp(-scores, constraints=usage, integrality=integral, bounds=Bounds(0.0, 1.0))
    if result.x is None:  # no solution within HiGHS's limits: the greedy pick
        chosen, used = [], set()
        for cand in sorted(candidates, key=lambda c: -c.score):
            if not used.intersection(cand.members):
                used.update(cand.members)
                chosen.append(cand)
        return chosen
    chosen = np.flatnonzero(result.x > 0.5)
    if margin > 0.0:
        decided = []
        for k in chosen.tolist():
            upper = np.ones(len(candidates))
            upper[k] = 0.0
            other = milp(-scores, constraints=usage, integrality=integral, bounds=Bounds(0.0, upper))
            if other.x is None or other.fun - result.fun >= margin:
                decided.append(k)
        chosen = np.array(decided, dtype=np.int64)
    return sorted((candidates[k] for k in chosen.tolist()), key=lambda c: -c.score)


def _new_track(track_id, cand: Candidate, members, config) -> MultiTrack:
    time_s = max(o.time_s for o in members)
    mean = np.zeros(STATE_SIZE)
    mean[:3] = cand.position_enu_m
    cov = np.zeros((STATE_SIZE, STATE_SIZE))
    cov[:3, :3] = cand.covariance_enu_m2
    cov[3:, 3:] = velocity_prior(config.network)
    nearest = float(min(np.linalg.norm(o.report.stations_enu_m[0] - cand.position_enu_m) for o in members))
    track = Track(track_id, "tentative", time_s, frozen_array(mean), frozen_array(cov), len(members), (), "single",
                  frozen_array([1.0]), frozen_array(mean[None]), frozen_array(cov[None]), 0, False, nearest)
    frequencies = [o.frequency_hz for o in members if math.isfinite(o.frequency_hz)]
    frequency = float(np.mean(frequencies)) if frequencies else math.nan
    return MultiTrack(track, frequency, len(frequencies), (True,) * min(len(members), config.confirm_window),
                      time_s, False, time_s)


def find_candidates(pool: Sequence[Observation], config: AssociationConfig) -> list[Candidate]:
    """Candidate emitters from bearings of at least ``init_min_stations`` stations (module docstring).

    Parameters
    ----------
    pool : sequence of Observation
        At most one scan per station.

    Returns
    -------
    list of Candidate
        Each passing its chi-square test with a positive score; candidates may share bearings.
    """
    if len(pool) < 3:
        return []
    arrays = _pool_arrays(pool, config)
    triples = _triples(arrays, config)
    if not triples.size:
        return []
    positions, covariances, chi2_values, ok = _fit(arrays, triples, _best_crossings(arrays, triples))
    gate = _chi2_point(config.init_gate_probability, 3)
    keep = ok & (chi2_values <= gate)
    out: dict[frozenset, Candidate] = {}
    stations = np.unique(arrays.station)
    grown: list[frozenset] = []
    for t in np.flatnonzero(keep):
        triple = [int(m) for m in triples[t]]
        position, cov = positions[t], covariances[t]
        _add_candidate(out, arrays, triple, position, cov, float(chi2_values[t]), len(stations), config)
        # The triple extended with every further station's best-fitting bearing, kept beside the triple: the
        # set packing decides (a bearing of another emitter may pass the gate of a triple on its own). A triple
        # inside a set already extended (an emitter seen by S stations has S-choose-3 triples) extends to it.
        if any(extended.issuperset(triple) for extended in grown):
            continue
        members = list(triple)
        known = arrays.frequency[members][np.isfinite(arrays.frequency[members])]
        frequency = float(known.mean()) if known.size else math.nan
        for s in stations:
            if s in arrays.station[members]:
                continue
            best = _best_addition(arrays, s, position, cov, frequency, config)
            if best >= 0:
                members.append(best)
        if len(members) > 3:
            p, c, x2, good = _fit(arrays, np.array([members]), position[None])
            if good[0] and x2[0] <= _chi2_point(config.init_gate_probability, 2 * len(members) - 3):
                _add_candidate(out, arrays, members, p[0], c[0], float(x2[0]), len(stations), config)
                grown.append(frozenset(members))
    return list(out.values())


def _add_candidate(out: dict, arrays: _Pool, members, position, cov, chi2_value: float, stations: int,
                   config) -> None:
    key = frozenset(members)
    if key in out:
        return
    score = _score(arrays, members, cov, chi2_value, stations, config)
    if score > 0.0 and _in_range(arrays, members, position, config):
        out[key] = Candidate(tuple(int(m) for m in members), position, cov, chi2_value, score)


def _frequency_compatible(arrays: _Pool, a, b, config) -> np.ndarray:
    difference = np.abs(arrays.frequency[a] - arrays.frequency[b])
    return ~(difference > config.frequency_tolerance_hz)


def _crossings(arrays: _Pool, a: np.ndarray, b: np.ndarray):
    """Midpoints ``(K, 3)`` of the closest approach of the lines of sight of bearings ``a`` and ``b``, and
    the ranges ``(K,)`` along each (least squares on ``p_a + r_a u_a = p_b + r_b u_b``)."""
    ua, ub = arrays.directions[a], arrays.directions[b]
    pa, pb = arrays.positions[a], arrays.positions[b]
    d = pb - pa
    uu = np.einsum("ki,ki->k", ua, ub)
    da, db = np.einsum("ki,ki->k", d, ua), np.einsum("ki,ki->k", d, ub)
    det = 1.0 - uu * uu
    with np.errstate(divide="ignore", invalid="ignore"):
        ra = (da - uu * db) / det
        rb = (uu * da - db) / det
    return 0.5 * (pa + ra[:, None] * ua + pb + rb[:, None] * ub), ra, rb


def _best_crossings(arrays: _Pool, triples: np.ndarray) -> np.ndarray:
    """Each triple's starting point ``(K, 3)``: the crossing of its pair of lines of sight closest to
    perpendicular."""
    pairs = ((0, 1), (0, 2), (1, 2))
    sines = np.stack([np.linalg.norm(np.cross(arrays.directions[triples[:, i]], arrays.directions[triples[:, j]]),
                                     axis=1) for i, j in pairs], axis=1)
    best = np.argmax(sines, axis=1)
    first = np.array([pairs[b][0] for b in best])
    second = np.array([pairs[b][1] for b in best])
    rows = np.arange(triples.shape[0])
    return _crossings(arrays, triples[rows, first], triples[rows, second])[0]


def _triples(arrays: _Pool, config) -> np.ndarray:
    """Triples ``(K, 3)`` of pool indices of three stations whose third bearing lies near the first two's
    crossing (coarse azimuth window, frequencies compatible), each set once."""
    stations = np.unique(arrays.station)
    by_station = {int(s): np.flatnonzero(arrays.station == s) for s in stations}
    out = []
    for sa, sb in itertools.combinations(stations.tolist(), 2):
        a, b = np.meshgrid(by_station[sa], by_station[sb], indexing="ij")
        a, b = a.ravel(), b.ravel()
        a, b = a[_frequency_compatible(arrays, a, b, config)], b[_frequency_compatible(arrays, a, b, config)]
        if not a.size:
            continue
        crossing_angle = np.arccos(np.clip(np.abs(np.einsum("ki,ki->k", arrays.directions[a], arrays.directions[b])),
                                           0.0, 1.0))
        points, ra, rb = _crossings(arrays, a, b)
        good = ((crossing_angle > MIN_CROSSING_ANGLE_RAD) & (ra > config.range_min_m) & (rb > config.range_min_m)
                & (ra < config.range_max_m) & (rb < config.range_max_m))
        a, b, points, ra, rb = a[good], b[good], points[good], ra[good], rb[good]
        if not a.size:
            continue
        # Angular uncertainty of the crossing as seen from a third station: both bearings' sigmas at their
        # ranges, over the sine of the crossing angle (a loose bound; the fit's chi-square decides).
        spread_m = np.hypot(ra * arrays.sigmas[a, 0], rb * arrays.sigmas[b, 0]) / np.sin(crossing_angle[good])
        for sc in stations.tolist():
            if sc in (sa, sb):
                continue
            c = by_station[sc]
            station = arrays.positions[c[0]]
            rotation = arrays.rotations[c[0]]
            seen, _ = predict(points, 0.0, station[None], rotation[None], np.array([AZIMUTH]))
            distance = np.linalg.norm(points - station, axis=1)
            window = COARSE_SIGMAS * np.hypot(arrays.sigmas[c, 0][None, :], (spread_m / distance)[:, None])
            near = np.abs(wrap_to_pi(arrays.values[c, 0][None, :] - seen[:, 0][:, None])) < window
            near &= _frequency_compatible(arrays, a[:, None], c[None, :], config)
            near &= _frequency_compatible(arrays, b[:, None], c[None, :], config)
            k, l = np.nonzero(near)
            if k.size:
                out.append(np.stack([a[k], b[k], c[l]], axis=1))
    if not out:
        return np.zeros((0, 3), dtype=np.int64)
    # Each triple is reached from each of its pairs (a near-collinear pair crosses far from the emitter, so
    # the well-conditioned pairs must be tried too): one copy each.
    triples = np.concatenate(out)
    _, first = np.unique(np.sort(triples, axis=1), axis=0, return_index=True)
    return triples[np.sort(first)]


def _fit(arrays: _Pool, members: np.ndarray, start: np.ndarray):
    """Gauss-Newton maximum-likelihood positions of ``K`` candidates of ``n`` bearings each.

    Parameters
    ----------
    members : ndarray of int, shape (K, n)
    start : ndarray, shape (K, 3)

    Returns
    -------
    positions : ndarray, shape (K, 3)
    covariances : ndarray, shape (K, 3, 3)
        Inverse Fisher information at the fit.
    chi2 : ndarray, shape (K,)
    ok : ndarray of bool, shape (K,)
    """
    count, n = members.shape
    stations = np.repeat(arrays.positions[members], 2, axis=1)              # (K, 2n, 3)
    rotations = np.repeat(arrays.rotations[members], 2, axis=1)             # (K, 2n, 3, 3)
    kinds = np.tile(np.array([AZIMUTH, ELEVATION]), (count, n))             # (K, 2n)
    measured = arrays.values[members].reshape(count, 2 * n)
    weights = 1.0 / arrays.sigmas[members].reshape(count, 2 * n) ** 2
    is_azimuth = kinds == AZIMUTH
    position = np.array(start, dtype=float)
    ok = np.all(np.isfinite(position), axis=1)
    position[~ok] = 0.0
    info = np.tile(np.eye(3), (count, 1, 1))
    for _ in range(FIT_ITERATIONS + 1):
        value, jacobian = predict(position, 0.0, stations, rotations, kinds)
        residual = measured - value
        residual = np.where(is_azimuth, wrap_to_pi(residual), residual)
        h = jacobian[..., :3]
        info = np.einsum("kmi,km,kmj->kij", h, weights, h)
        gradient = np.einsum("kmi,km,km->ki", h, weights, residual)
        step = np.einsum("kij,kj->ki", _inverses(info), gradient)
        ok &= np.all(np.isfinite(step), axis=1)
        position = position + np.where(ok[:, None], step, 0.0)
    chi2_values = np.einsum("km,km,km->k", residual, weights, residual)
    covariances = _inverses(info)
    ok &= np.all(np.isfinite(position), axis=1) & np.all(np.isfinite(covariances), axis=(1, 2))
    ok &= np.linalg.eigvalsh(np.where(ok[:, None, None], covariances, np.eye(3)))[:, 0] > 0.0
    return position, covariances, chi2_values, ok


def _inverses(matrices: np.ndarray) -> np.ndarray:
    """Inverses ``(K, 3, 3)`` of symmetric matrices, NaN where one is singular (lines of sight that are
    parallel or meet at a station)."""
    try:
        return np.linalg.inv(matrices)
    except np.linalg.LinAlgError:
        out = np.full(matrices.shape, np.nan)
        for k, matrix in enumerate(matrices):
            try:
                out[k] = np.linalg.inv(matrix)
            except np.linalg.LinAlgError:
                pass
        return out


def _best_addition(arrays: _Pool, station: int, position, cov, frequency: float, config) -> int:
    """The pool index of ``station``'s bearing that best fits a candidate (NIS at the fit, the fit's
    covariance propagated), -1 when none passes the gate."""
    index = np.flatnonzero(arrays.station == station)
    kinds = np.array([AZIMUTH, ELEVATION])
    value, jacobian = predict(position, 0.0, arrays.positions[index[0]][None].repeat(2, 0),
                              arrays.rotations[index[0]][None].repeat(2, 0), kinds)
    h = jacobian[:, :3]
    base = h @ cov @ h.T
    best, best_nis = -1, _chi2_point(config.init_gate_probability, 2)
    for k in index.tolist():
        if not _frequency_ok(arrays.frequency[k], frequency, config):
            continue
        residual = arrays.values[k] - value
        residual[0] = wrap_to_pi(residual[0])
        nis = float(residual @ np.linalg.solve(base + np.diag(arrays.sigmas[k] ** 2), residual))
        if nis < best_nis:
            best, best_nis = k, nis
    return best


def _score(arrays: _Pool, members, cov, chi2_value: float, stations: int, config) -> float:
    """Log likelihood ratio of "one emitter made these bearings, the other stations missed it" against "these
    bearings are false" (Laplace approximation over the uniform prior on the surveillance volume): per
    bearing ``log(P_D / lambda)`` less its Gaussian normaliser, ``-chi2 / 2`` at the fit, ``log(1 - P_D)`` per
    station that saw nothing, ``log det(2 pi P) / 2 - log V`` for the position integrated out."""
    n = len(members)
    sigmas = arrays.sigmas[members]
    normaliser = 0.5 * np.log(2.0 * math.pi * sigmas[:, 0] ** 2) + np.where(
        arrays.has_elevation[members], 0.5 * np.log(2.0 * math.pi * sigmas[:, 1] ** 2), 0.0)
    sign, log_det = np.linalg.slogdet(2.0 * math.pi * np.asarray(cov))
    if sign <= 0:
        return -math.inf
    return float(n * math.log(config.detection_probability / config.false_density_per_rad2) - normaliser.sum()
                 - 0.5 * chi2_value + (stations - n) * math.log1p(-config.detection_probability) + 0.5 * log_det
                 - math.log(config.surveillance_volume_m3))


def _in_range(arrays: _Pool, members, position, config) -> bool:
    distances = np.linalg.norm(arrays.positions[members] - position, axis=1)
    return bool(np.all((distances > config.range_min_m) & (distances < config.range_max_m)))


_CHI2_CACHE: dict = {}


def _chi2_point(probability: float, dof: int) -> float:
    key = (probability, dof)
    if key not in _CHI2_CACHE:
        _CHI2_CACHE[key] = float(chi2.ppf(probability, dof))
    return _CHI2_CACHE[key]


__all__ = [
    "ASSOCIATION_STATE_FORMAT",
    "AssociationConfig",
    "AssociationOutcome",
    "AssociationState",
    "Candidate",
    "MultiTrack",
    "Observation",
    "apply_observations",
    "apply_reports_auto",
    "current_tracks",
    "find_candidates",
    "gate_costs",
    "new_association_state",
    "observations_from_report",
    "status_of",
]
