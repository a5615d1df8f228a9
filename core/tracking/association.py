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
update kernel (:func:`core.tracking.network_kernel.network_ukf_kernel`: the unscented transform of the track's
predicted position through :func:`core.measurements.measure_point`; the NIS is its first pass's), so the gate
and the update share one measurement model, and the update the kernel makes of a gated pair is the one the
track takes if it gets that bearing (each track is predicted once per scan, each pair updated once). A pair
passes when its NIS is inside the chi-square ``gate_probability`` point and, when both carry a frequency, the
frequencies differ by at most ``frequency_tolerance_hz``.

**Assignment: JPDA (chosen by measurement), or global nearest neighbour.** Each gated pair's likelihood ratio
against a false bearing is ``P_D N(z; z_hat, S) / lambda`` (``lambda`` the false-bearing density per
rad^dims). With ``method="jpda"`` (the default), the association probabilities of each cluster of tracks that
share gated bearings come from enumerating its feasible joint events (each track one bearing or none, a bearing
to one track at most; a missed track weighs ``1 - P_D``), and each track is updated with every gated bearing
(:func:`core.tracking.network_update.advance_track`) and left as predicted, the hypotheses merged by their
probabilities into one Gaussian (:mod:`core.tracking.scan_assignment`). With ``method="gnn"``, :func:`scipy.optimize.
linear_sum_assignment` maximises the scan's summed log likelihood ratios (unassigned: 0; only ratios above 1
kept) and assigned bearings update their track, unless another track could have taken the bearing at a cost
less than ``ambiguity_margin`` above (such a bearing counts as a hit but moves neither track). On the eight
variants of :func:`core.simulation.multi_emitter.multi_emitter_scene` (seeds 10-13) JPDA's mean GOSPA was
167-183 m against GNN's 203-593 m, with no identity switch against GNN's 0.38 a run: where
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
by :func:`core.tracking.track_start.select_candidates`). Of the up to ``N^S`` crossings of ``N`` emitters
seen by ``S`` stations, a ghost needs three stations' bearings to agree on one point within the noise, and is
chosen only when it explains the bearings better than the real emitters that share them. A bearing without
elevation is taken, for the fit, as elevation 0 with ``network.azimuth_only_elevation_sigma_rad``, as the
network tracker's start does.

**Rival starts: the decision deferred to the next scans.** One scan can leave the packing ambiguous: where
each of two emitters on one frequency lies near the line between two opposite stations, the swapped pairing
is a pair of ghosts that all four stations fit, and a missed detection can make it score as well as the
emitters. So when the best packing without one of the accepted candidates scores less than
``init_ambiguity_margin`` below the best (:func:`core.tracking.track_start.rival_candidates`), that packing's
candidates start too, as tentative tracks that are each other's *rivals* where they share starting bearings,
unless a candidate's position agrees with that of an accepted one it shares a bearing with (within the
``gate_probability`` chi-square point: the same emitter from other bearings, which the next scans refine
anyway). While a tentative track has a live rival it is a hypothesis about bearings, not an emitter beside the others:
it stays out of the joint assignment, takes each scan its best gated bearing of those the other tracks left,
and adds that bearing's log likelihood ratio (``log(1 - P_D)`` when none gates) to its score, its candidate's
score to begin with (the track score of Blackman and Popoli, 1999). Two rivals that take one bearing
add to their *conflict* what the one that fits it less would lose by missing it; the bearings they shared at
the start begin it. After each scan the rivals' joint hypotheses (the subsets of a group of rivals) are scored
as their tracks' scores less their pairs' conflicts; a rival is confirmed once it has the M of N hits below,
is in the best subset, ``init_window_s`` after its start, and the best subset without it scores
``init_ambiguity_margin`` less, or ``init_decision_s`` after its start; its rivals outside the best subset
end (:func:`core.tracking.rival_starts.decide_rivals`). Ghosts that fit one scan fit the next ones worse
as the emitters move and the stations miss them, and the emitters' lead
grows scan by scan. This is track-oriented MHT confined to where it is needed: hypotheses over every track
and scan would grow with both, while the ambiguity here is one of starts (a confirmed track is followed by
JPDA, which weighs its pairings anyway); withholding an ambiguous start instead would look again at a
single scan's pool each time and, where the ambiguity persists, leave the emitters unstarted with nothing
learnt; and confirming every track on its score rather than M of N would change every unambiguous start too.

**Track management** (statuses are those of the network sessions):

- a track starts ``tentative`` from an accepted candidate: position the fit (covariance its inverse Fisher
  information), velocity zero with the network tracker's prior (:func:`core.tracking.network_update.velocity_prior`);
  its starting bearings count as hits;
- each later scan of any station is a hit (a bearing assigned) or a miss. A tentative track is ``confirmed``
  once ``confirm_hits`` of its last ``confirm_window`` scans are hits (M of N; a rival also as above), and
  deleted as soon as it can no
  longer reach that (more than ``confirm_window - confirm_hits`` misses among them): a ghost or clutter-born
  track gets the bearings of at most the stations whose lines made it and dies within a few scans;
- a confirmed track without a hit for ``coast_after_s`` is ``coasting`` (it still gates and may take
  bearings again, which makes it ``confirmed``), and ends after ``end_after_s`` without one;
- ids are ``"t1"``, ``"t2"``, ... in start order, never reused.

Layout: this module holds the state and its API; one scan's gating and assignment is
:mod:`core.tracking.scan_assignment`, the track starts are :mod:`core.tracking.track_start`, the decision
between rival starts is :mod:`core.tracking.rival_starts`, and the values all four share (settings, bearing,
track) are :mod:`core.tracking.association_types`. Imports run one way,
from here down.
"""

from __future__ import annotations

import itertools
import math
from collections.abc import Sequence
from dataclasses import dataclass, replace
from typing import NamedTuple

from core.errors import InvalidInput
from core.measurements import AZIMUTH, ELEVATION
from core.tracking.association_types import AssociationConfig, MultiTrack, Observation
from core.tracking.network import NetworkState, predict_tracks
from core.tracking.network_types import Report, Track
from core.tracking.rival_starts import decide_rivals
from core.tracking.scan_assignment import assign_scan, gate_costs
from core.tracking.track_start import (
    Candidate,
    find_candidates,
    select_candidates,
    start_tracks,
)

#: Version of the :meth:`AssociationState.to_dict` layout. Format 1 (tracks without ``score`` and ``rivals``)
#: still loads: its tracks have no rivals, so they are managed as they were.
ASSOCIATION_STATE_FORMAT = 2
_READABLE_FORMATS = (1, 2)


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
                            "confirmed_s": _float_or_none(t.confirmed_s), "score": _float_or_none(t.score),
                            "rivals": dict(t.rivals)} for t in self.tracks],
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
        if not isinstance(data, dict) or data.get("format") not in _READABLE_FORMATS:
            raise InvalidInput(f"association state must be a mapping with format {ASSOCIATION_STATE_FORMAT}")
        try:
            tracks = tuple(MultiTrack(Track.from_dict(t["track"]), _nan_if_none(t["frequency_hz"]),
                                      int(t["frequency_count"]), tuple(bool(h) for h in t["hits"]),
                                      float(t["last_hit_s"]), bool(t["confirmed"]), float(t["started_s"]),
                                      _nan_if_none(t["confirmed_s"]), _nan_if_none(t.get("score")),
                                      {str(r): float(c) for r, c in t.get("rivals", {}).items()})
                           for t in data["tracks"])
            pool = tuple(Observation(Report.from_dict(o["report"]), _nan_if_none(o["frequency_hz"]))
                         for o in data["pool"])
            last, first = data["last_time_s"], data["first_time_s"]
            return cls(tracks, pool, int(data["next_id"]), None if last is None else float(last),
                       None if first is None else float(first))
        except (AttributeError, KeyError, TypeError, ValueError) as error:
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
        tracks, unassigned = assign_scan(tracks, scan, config)
        tracks = decide_rivals(tracks, time_s, config)
        pool = [o for o in pool if o.time_s > time_s - config.init_window_s] + unassigned
        if unassigned and time_s - first >= config.init_window_s:
            tracks, pool, next_id, new = start_tracks(tracks, pool, next_id, time_s, config)
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
    "select_candidates",
    "status_of",
]
