"""The values the association passes between its parts: its settings, an unlabelled bearing, a track.

:mod:`core.tracking.association` (the public API and the state), :mod:`core.tracking.scan_assignment` (one
scan: gate, assign, update) and :mod:`core.tracking.track_start` (tracks started from bearings of three or
more stations) all build on these; this module imports none of them. The rules the settings tune are in
:mod:`core.tracking.association`.
"""

from __future__ import annotations

import math
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field

import numpy as np

from core.errors import InvalidInput
from core.measurements import AZIMUTH, ELEVATION
from core.tracking.network_types import NetworkConfig, Report, Track

#: Half-width of the coarse azimuth windows, in units of the combined azimuth sigma: a scan's screen of
#: track-bearing pairs (:mod:`core.tracking.scan_assignment`, the exact test is the gate) and the
#: third-station window around a crossing's predicted azimuth (:mod:`core.tracking.track_start`, the exact
#: test is the fit's chi-square).
COARSE_SIGMAS = 6.0


@dataclass(frozen=True)
class AssociationConfig:
    """Settings of the association and track management (:mod:`core.tracking.association`).

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
        A start is decided when every other packing of the start's candidates is this much less likely (log
        likelihood ratio); when one is closer, its candidates that place an emitter elsewhere start too, as
        rival tentative tracks confirmed on their cumulative scores
        (:func:`core.tracking.rival_starts.decide_rivals`); 0: the best packing starts alone.
    init_decision_s : float
        Rival tracks whose scores have not told them apart this long after their start are decided for the
        best joint hypothesis of their scores.
    ambiguity_margin : float
        A bearing updates its track only when no other track could take it at a cost (log likelihood
        ratio) less than this above the assignment's (:func:`core.tracking.scan_assignment.ambiguous_tracks`); 0:
        every assigned bearing updates.
    method : str
        ``"gnn"`` (global nearest neighbour) or ``"jpda"`` (joint probabilistic data association,
        :mod:`core.tracking.scan_assignment`); compared on the scenes in :mod:`core.tracking.association`.
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
    init_ambiguity_margin: float = 4.0
    init_decision_s: float = 10.0
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
                     "init_window_s", "init_decision_s", "range_min_m", "range_max_m", "coast_after_s", "end_after_s"):
            value = getattr(self, name)
            if not (isinstance(value, (int, float)) and math.isfinite(value) and value > 0.0):
                raise InvalidInput(f"{name} must be a finite number > 0", (name,))
        for name in ("detection_probability", "gate_probability", "init_gate_probability"):
            value = getattr(self, name)
            if not 0.0 < value < 1.0:
                raise InvalidInput(f"{name} must be inside (0, 1)", (name,))
        if not 3 <= self.init_min_stations:
            raise InvalidInput("init_min_stations must be >= 3", ("init_min_stations",))
        if not (math.isfinite(self.init_ambiguity_margin) and self.init_ambiguity_margin >= 0.0):
            raise InvalidInput("init_ambiguity_margin must be a finite number >= 0", ("init_ambiguity_margin",))
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
    score : float
        Log likelihood ratio of "an emitter" against "false bearings": its start candidate's score plus, for
        each later scan while it has live rivals, its bearing's log likelihood ratio or ``log(1 - P_D)``
        (NaN for a track started before scores were kept).
    rivals : mapping of str to float
        The tracks started beside it that share a starting bearing with it, each with the log likelihood
        ratio both would lose to be emitters side by side (one of them missing each bearing they share: at the
        start and in every scan since; :func:`core.tracking.rival_starts.decide_rivals`).
    """

    track: Track
    frequency_hz: float
    frequency_count: int
    hits: tuple[bool, ...]
    last_hit_s: float
    confirmed: bool
    started_s: float
    confirmed_s: float = math.nan
    score: float = math.nan
    rivals: Mapping[str, float] = field(default_factory=dict)

    @property
    def id(self) -> str:
        return self.track.id


def frequency_ok(a: float, b: float, config: AssociationConfig) -> bool:
    """Whether two frequencies (Hz) may be one emitter's: within ``config.frequency_tolerance_hz``, or either
    unknown (NaN)."""
    return not (abs(a - b) > config.frequency_tolerance_hz)  # NaN on either side: True


def under_test(tracks: Sequence[MultiTrack]) -> list[int]:
    """Indices of the tentative tracks with a live tentative rival (:attr:`MultiTrack.rivals`): each is still
    one of several explanations of its bearings (:func:`core.tracking.rival_starts.decide_rivals`)."""
    tentative = {t.id for t in tracks if not t.confirmed}
    return [k for k, t in enumerate(tracks) if not t.confirmed and tentative.intersection(t.rivals)]


__all__ = ["COARSE_SIGMAS", "AssociationConfig", "MultiTrack", "Observation", "frequency_ok", "under_test"]
