"""Many emitters, unlabelled bearings: the multi-emitter scene, its simulation and its evaluation.

The scene (:func:`multi_emitter_scene`): four direction finders over about 40 km (geodetic positions, so the
common frame is exercised as in :mod:`core.simulation.network`), four ground emitters on straight paths, two of
them on one frequency passing within 2 km of each other, one starting halfway, one stopping before the
end. Every second each station reports every bearing it measured (azimuth and elevation) with no emitter label:
each emitter is detected with probability ``detection_probability``; false bearings (multipath, noise) make up
``false_fraction`` of the bearings, uniform in azimuth, on the frequency of one of the emitters on the air (the
station listens on those channels, so the frequency does not give a false bearing away).

:func:`evaluate_multi` runs seeded trials through :func:`core.tracking.association.apply_observations` and,
on the same bearings, through the pairwise-intersection + DBSCAN baseline (:func:`baseline_estimates`: the
KrakenSDR df-aggregator's method), and scores both with GOSPA (:mod:`core.tracking.gospa`) on the horizontal
position (the baseline is two-dimensional).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field, replace
from typing import NamedTuple

import numpy as np

from core.angles import line_of_sight_enu, station_to_common
from core.measurements import AZIMUTH, ELEVATION, predict
from core.parallel import Stopped
from core.simulation.network import (
    START_TIME_S,
    NetworkStation,
    _geodetic_stations,
    station_frame,
)
from core.tracking.association import (
    AssociationConfig,
    Observation,
    apply_observations,
    current_tracks,
    new_association_state,
)
from core.tracking.gospa import gospa
from core.tracking.network import NetworkConfig, Report

#: The filter of a ground emitter's track: gentle horizontal manoeuvres, next to none vertically.
GROUND_EMITTERS = NetworkConfig(accel_sigma_mps2=0.2, velocity_prior_sigma_mps=30.0, vertical_accel_sigma_mps2=0.02,
                                vertical_velocity_prior_sigma_mps=1.0, coast_after_s=10.0, end_after_s=60.0)


@dataclass(frozen=True)
class EmitterPath:
    """One emitter: a straight path at constant velocity while it transmits.

    Attributes
    ----------
    id : str
    frequency_hz : float
    start_enu_m : tuple of 3 floats
        Position at the scene's start (common frame; extrapolated backwards when it starts later).
    velocity_enu_mps : tuple of 3 floats
    on_s, off_s : float
        Transmitting from ``on_s`` to ``off_s`` after the scene's start.
    """

    id: str
    frequency_hz: float
    start_enu_m: tuple[float, float, float]
    velocity_enu_mps: tuple[float, float, float]
    on_s: float
    off_s: float

    def state_at(self, elapsed_s):
        """States ``(..., 6)`` at ``elapsed_s`` after the start."""
        elapsed = np.asarray(elapsed_s, dtype=float)[..., None]
        position = np.asarray(self.start_enu_m) + elapsed * np.asarray(self.velocity_enu_mps)
        return np.concatenate([position, np.broadcast_to(self.velocity_enu_mps, position.shape)], axis=-1)

    def active(self, elapsed_s) -> np.ndarray:
        elapsed = np.asarray(elapsed_s, dtype=float)
        return (elapsed >= self.on_s) & (elapsed <= self.off_s)


@dataclass(frozen=True)
class MultiEmitterScenario:
    """A multi-emitter scene (module docstring).

    Attributes
    ----------
    name : str
    origin_lat_deg, origin_lon_deg, origin_alt_m : float
    stations : tuple of NetworkStation
        Bearing stations, each scanning every ``scan_interval_s`` from its ``report_offset_s``.
    emitters : tuple of EmitterPath
    duration_s, scan_interval_s : float
    detection_probability : float
    false_fraction : float
        Expected share of false bearings among all bearings.
    false_elevation_rad : tuple of 2 floats
        False bearings' elevations are uniform in this interval.
    config : AssociationConfig
        The tracker's settings for the scene.
    gospa_cutoff_m : float
        GOSPA's ``c``: a position error beyond it counts as a missed emitter and a false track.
    baseline_window_s, baseline_eps_m : float
        The baseline's bearing window and DBSCAN neighbourhood radius.
    baseline_min_samples : int
        DBSCAN's core-point count. The three defaults are the baseline at its best: the lowest mean GOSPA of
        a grid (window 1-8 s, eps 150-700 m, min_samples 2-45) on two runs of variant 0 (seeds 100 and 101,
        apart from the seeds the tests use).
    """

    name: str
    origin_lat_deg: float
    origin_lon_deg: float
    origin_alt_m: float
    stations: tuple[NetworkStation, ...]
    emitters: tuple[EmitterPath, ...]
    duration_s: float = 300.0
    scan_interval_s: float = 1.0
    detection_probability: float = 0.9
    false_fraction: float = 0.05
    false_elevation_rad: tuple[float, float] = (math.radians(-5.0), math.radians(5.0))
    config: AssociationConfig = field(default_factory=AssociationConfig)
    gospa_cutoff_m: float = 1000.0
    baseline_window_s: float = 5.0
    baseline_eps_m: float = 400.0
    baseline_min_samples: int = 30

    @property
    def origin_rad(self) -> tuple[float, float, float]:
        return math.radians(self.origin_lat_deg), math.radians(self.origin_lon_deg), self.origin_alt_m


class MultiRun(NamedTuple):
    """One simulated run.

    Attributes
    ----------
    observations : tuple of Observation
        Every bearing, in time order (a station's scan in random order, as a receiver lists its peaks).
    sources : tuple of str
        The emitter of each observation (``""``: false), for scoring only.
    first_detection_s : dict of str to float
        Each emitter's first true bearing time.
    """

    observations: tuple
    sources: tuple
    first_detection_s: dict


def scan_times(scenario: MultiEmitterScenario) -> list[tuple[float, int]]:
    """``(time_s, station index)`` of every scan, in time order."""
    end = START_TIME_S + scenario.duration_s
    out = []
    for i, station in enumerate(scenario.stations):
        t = START_TIME_S + station.report_offset_s
        while t <= end + 1e-9:
            out.append((t, i))
            t += scenario.scan_interval_s
    out.sort()
    return out


def truth_at(scenario: MultiEmitterScenario, time_s: float) -> tuple[tuple[str, ...], np.ndarray]:
    """Ids and states ``(K, 6)`` of the emitters transmitting at ``time_s``."""
    elapsed = time_s - START_TIME_S
    live = [e for e in scenario.emitters if e.active(elapsed)]
    return tuple(e.id for e in live), np.array([e.state_at(elapsed) for e in live]).reshape(len(live), 6)


def expected_bearings(scenario: MultiEmitterScenario) -> float:
    """Bearings a run of the scene holds on average: per scan, each emitter on the air detected with
    ``detection_probability``, and the false share on top (:func:`simulate_multi`)."""
    per_true = scenario.detection_probability / (1.0 - scenario.false_fraction)
    return sum(len(truth_at(scenario, time_s)[0]) for time_s, _ in scan_times(scenario)) * per_true


def simulate_multi(scenario: MultiEmitterScenario, rng: np.random.Generator, scans=None) -> MultiRun:
    """One run's bearings (module docstring); ``scans`` (``(time_s, station index)`` pairs, default every
    :func:`scan_times`) draws only those, so that a long run can be drawn a part at a time with one ``rng``."""
    positions, rotations = station_frame(scenario)
    kinds = np.array([AZIMUTH, ELEVATION])
    observations, sources, first = [], [], {}
    seq = 0
    low, high = scenario.false_elevation_rad
    pd = scenario.detection_probability
    false_per_true = scenario.false_fraction / (1.0 - scenario.false_fraction)
    for time_s, i in scan_times(scenario) if scans is None else scans:
        station = scenario.stations[i]
        sigmas = np.array([station.sigma_azimuth_rad, station.sigma_elevation_rad])
        ids, states = truth_at(scenario, time_s)
        frequencies = [e.frequency_hz for e in scenario.emitters if e.id in ids]
        scan = []
        for emitter_id, state, frequency in zip(ids, states, frequencies):
            if rng.uniform() >= pd:
                continue
            exact, _ = predict(state[:3], 0.0, positions[i][None].repeat(2, 0), rotations[i][None].repeat(2, 0), kinds)
            scan.append((exact + rng.normal(0.0, sigmas), frequency, emitter_id))
            first.setdefault(emitter_id, time_s)
        if ids:
            for _ in range(rng.poisson(false_per_true * pd * len(ids))):
                values = np.array([rng.uniform(-math.pi, math.pi), rng.uniform(low, high)])
                scan.append((values, frequencies[rng.integers(len(frequencies))], ""))
        for k in rng.permutation(len(scan)):
            values, frequency, source = scan[k]
            report = Report(seq, time_s, "", (station.id, station.id), positions[i][None].repeat(2, 0),
                            rotations[i][None].repeat(2, 0), kinds, values, sigmas)
            observations.append(Observation(report, frequency))
            sources.append(source)
            seq += 1
    return MultiRun(tuple(observations), tuple(sources), first)


# ---------------------------------------------------------------------------------------------------------------
# The pairwise-intersection + DBSCAN baseline


def baseline_estimates(scenario: MultiEmitterScenario, observations, time_s: float) -> np.ndarray:
    """Emitter positions ``(K, 2)`` (east, north) from the bearings of ``(time_s - baseline_window_s, time_s]``
    the way the KrakenSDR df-aggregator finds them: every pair of bearings of two stations on one frequency is
    intersected in the horizontal plane (in front of both stations), the crossings are clustered with DBSCAN,
    and each cluster's centroid is an emitter."""
    from sklearn.cluster import DBSCAN

    window = [o for o in observations if time_s - scenario.baseline_window_s < o.time_s <= time_s]
    if len(window) < 2:
        return np.zeros((0, 2))
    station_of = np.array([hash(o.station_id) for o in window])
    origins = np.array([o.report.stations_enu_m[0, :2] for o in window])
    azimuths = np.array([o.report.values[o.report.kinds == AZIMUTH][0] for o in window])
    rotations = np.array([o.report.rotations[0] for o in window])
    directions = station_to_common(line_of_sight_enu(azimuths, np.zeros_like(azimuths)), rotations)[:, :2]
    directions /= np.linalg.norm(directions, axis=1, keepdims=True)
    frequency = np.array([o.frequency_hz for o in window])
    a, b = np.triu_indices(len(window), 1)
    same = (station_of[a] != station_of[b]) & ~(np.abs(frequency[a] - frequency[b])
                                               > scenario.config.frequency_tolerance_hz)
    a, b = a[same], b[same]
    ua, ub, d = directions[a], directions[b], origins[b] - origins[a]
    cross = ua[:, 0] * ub[:, 1] - ua[:, 1] * ub[:, 0]
    with np.errstate(divide="ignore", invalid="ignore"):
        ra = (d[:, 0] * ub[:, 1] - d[:, 1] * ub[:, 0]) / cross
        rb = (d[:, 0] * ua[:, 1] - d[:, 1] * ua[:, 0]) / cross
    limit = scenario.config.range_max_m
    good = (np.abs(cross) > math.sin(math.radians(2.0))) & (ra > 0) & (rb > 0) & (ra < limit) & (rb < limit)
    points = origins[a[good]] + ra[good, None] * ua[good]
    if points.shape[0] < scenario.baseline_min_samples:
        return np.zeros((0, 2))
    labels = DBSCAN(eps=scenario.baseline_eps_m, min_samples=scenario.baseline_min_samples).fit(points).labels_
    return np.array([points[labels == k].mean(axis=0) for k in range(labels.max() + 1)]).reshape(-1, 2)


# ---------------------------------------------------------------------------------------------------------------
# Evaluation


@dataclass(frozen=True)
class MultiEvaluation:
    """Seeded Monte Carlo of the association tracker and the baseline on one scene.

    Attributes
    ----------
    scenario : str
    trials : int
    gospa_m, baseline_gospa_m : float
        Mean over epochs and trials of the GOSPA distance (confirmed tracks; baseline centroids).
    localisation_m2, missed_m2, false_m2 : float
        Mean of the parts of the tracker's GOSPA^2 (m^2); ``baseline_parts_m2`` the baseline's, same order.
    baseline_parts_m2 : tuple of 3 floats
    confirm_delay_s : ndarray, shape (trials, emitters)
        Time from each emitter's first detection to the first epoch a confirmed track is assigned to it
        (inf when never).
    false_tracks : ndarray of int, shape (trials,)
        Confirmed tracks assigned to no emitter at most of the epochs they were reported.
    identity_switches : ndarray of int, shape (trials,)
        Changes of the track that corresponds to an emitter (:func:`correspondences`) from one epoch it has
        one to the next.
    gospa_per_trial, baseline_gospa_per_trial : ndarray, shape (trials,)
    """

    scenario: str
    trials: int
    gospa_m: float
    baseline_gospa_m: float
    localisation_m2: float
    missed_m2: float
    false_m2: float
    baseline_parts_m2: tuple
    confirm_delay_s: np.ndarray
    false_tracks: np.ndarray
    identity_switches: np.ndarray
    gospa_per_trial: np.ndarray
    baseline_gospa_per_trial: np.ndarray

    def summary(self) -> dict:
        return {"scenario": self.scenario, "trials": self.trials, "gospa_m": self.gospa_m,
                "baseline_gospa_m": self.baseline_gospa_m, "gospa_over_baseline": self.gospa_m / self.baseline_gospa_m,
                "localisation_m2": self.localisation_m2, "missed_m2": self.missed_m2, "false_m2": self.false_m2,
                "baseline_localisation_missed_false_m2": list(self.baseline_parts_m2),
                "max_confirm_delay_s": float(np.max(self.confirm_delay_s)),
                "mean_false_tracks": float(np.mean(self.false_tracks)),
                "mean_identity_switches": float(np.mean(self.identity_switches))}


def run_multi_trial(scenario: MultiEmitterScenario, run: MultiRun, config: AssociationConfig | None = None,
                    tracker=None):
    """Feed one run's bearings scan by scan and score every epoch (once a second, after the bearings up to it).

    Parameters
    ----------
    tracker : callable, optional
        ``tracker(observations, time_s)``: takes the bearings that arrived since its last call (possibly none)
        and returns the confirmed tracks at ``time_s`` (each with an ``id`` and a ``mean_enu`` whose first two
        entries are east and north). Default: :func:`core.tracking.association.apply_observations` with
        ``config``, the tracks :func:`core.tracking.association.current_tracks` calls ``confirmed``. A
        yardstick tracker is scored through the same epochs and measures.

    Returns
    -------
    dict
        ``gospa``, ``parts`` (E, 3), ``baseline_gospa``, ``baseline_parts`` (E, 3), ``confirm_delay_s`` (emitters,),
        ``false_tracks``, ``identity_switches``.
    """
    config = config or scenario.config
    count = int(scenario.duration_s / scenario.scan_interval_s)
    epochs = START_TIME_S + scenario.scan_interval_s * np.arange(1, count + 1)
    tracker = tracker or _association_tracker(config)
    observations = run.observations
    cursor = 0
    cutoff = scenario.gospa_cutoff_m
    distances, parts, base_distances, base_parts = [], [], [], []
    first_assigned: dict[str, float] = {}
    last_id: dict[str, str] = {}
    switches = 0
    track_epochs: dict[str, list[bool]] = {}
    for t in epochs.tolist():
        start = cursor
        while cursor < len(observations) and observations[cursor].time_s <= t:
            cursor += 1
        tracks = tracker(observations[start:cursor], t)
        ids, truths = truth_at(scenario, t)
        estimates = np.array([tr.mean_enu[:2] for tr in tracks]).reshape(-1, 2)
        score = gospa(estimates, truths[:, :2], cutoff)
        distances.append(score.distance)
        parts.append((score.localisation, score.missed, score.false))
        for k, emitter in enumerate(ids):
            if score.assignment[k] >= 0:
                first_assigned.setdefault(emitter, t)
        for emitter, track_id in correspondences(ids, truths[:, :2], tracks, estimates, last_id, cutoff).items():
            if emitter in last_id and last_id[emitter] != track_id:
                switches += 1
            last_id[emitter] = track_id
        assigned = {int(j) for j in score.assignment if j >= 0}
        for j, tr in enumerate(tracks):
            track_epochs.setdefault(tr.id, []).append(j in assigned)
        base = gospa(baseline_estimates(scenario, observations[:cursor], t), truths[:, :2], cutoff)
        base_distances.append(base.distance)
        base_parts.append((base.localisation, base.missed, base.false))
    delays = np.array([first_assigned.get(e.id, math.inf) - run.first_detection_s.get(e.id, math.inf)
                       if e.id in run.first_detection_s else 0.0 for e in scenario.emitters])
    false_tracks = sum(1 for flags in track_epochs.values() if sum(flags) <= 0.5 * len(flags))
    return {"gospa": np.array(distances), "parts": np.array(parts), "baseline_gospa": np.array(base_distances),
            "baseline_parts": np.array(base_parts), "confirm_delay_s": delays, "false_tracks": false_tracks,
            "identity_switches": switches}


def _association_tracker(config: AssociationConfig):
    """:func:`run_multi_trial`'s default tracker: the association's confirmed tracks."""
    state = new_association_state()

    def step(observations, time_s: float):
        nonlocal state
        if observations:
            state = apply_observations(state, observations, config).state
        return [tr for tr in current_tracks(state, time_s, config) if tr.status == "confirmed"]

    return step


def correspondences(ids, truths, tracks, estimates, previous: dict, cutoff: float) -> dict:
    """Which track stands for each emitter at one epoch, the CLEAR MOT way (Bernardin and Stiefelhagen 2008):
    an emitter keeps its previous track while that track is still within ``cutoff`` of it; the others are
    matched by the optimal assignment of the distances (pairs within ``cutoff``). An identity switch is a
    change of an emitter's track. (GOSPA's own per-epoch assignment would swap two tracks that pass close by
    whenever their errors trade places, and count switches the tracks never made.)

    Parameters
    ----------
    ids : sequence of str, length N
    truths : ndarray, shape (N, D)
    tracks : sequence of Track, length M
    estimates : ndarray, shape (M, D)
    previous : dict of str to str
        Each emitter's track at the last epoch it had one.
    cutoff : float

    Returns
    -------
    dict of str to str
        Emitter id to track id, for the emitters that have one.
    """
    from scipy.optimize import linear_sum_assignment

    index = {tr.id: j for j, tr in enumerate(tracks)}
    out, used = {}, set()
    for k, emitter in enumerate(ids):
        j = index.get(previous.get(emitter))
        if j is not None and np.linalg.norm(estimates[j] - truths[k]) < cutoff:
            out[emitter] = tracks[j].id
            used.add(j)
    rest = [k for k, emitter in enumerate(ids) if emitter not in out]
    free = [j for j in range(len(tracks)) if j not in used]
    if rest and free:
        distances = np.linalg.norm(truths[rest][:, None, :] - estimates[free][None, :, :], axis=-1)
        for a, b in zip(*linear_sum_assignment(np.minimum(distances, cutoff))):
            if distances[a, b] < cutoff:
                out[ids[rest[a]]] = tracks[free[b]].id
    return out


def evaluate_multi(scenario: MultiEmitterScenario, trials: int, seed: int = 0,
                   config: AssociationConfig | None = None, should_stop=None) -> MultiEvaluation:
    """Seeded Monte Carlo (trial ``r`` draws from ``seed + r``) of the tracker and the baseline on the same
    bearings (module docstring).

    Parameters
    ----------
    should_stop : callable returning bool, optional
        Asked before each trial (a request's deadline or cancellation); True raises
        :class:`core.parallel.Stopped`.
    """
    results = []
    for r in range(trials):
        if should_stop is not None and should_stop():
            raise Stopped(f"stopped after {r} of {trials} trials")
        results.append(run_multi_trial(scenario, simulate_multi(scenario, np.random.default_rng(seed + r)), config))
    parts = np.mean([r["parts"].mean(axis=0) for r in results], axis=0)
    base_parts = np.mean([r["baseline_parts"].mean(axis=0) for r in results], axis=0)
    per_trial = np.array([r["gospa"].mean() for r in results])
    base_per_trial = np.array([r["baseline_gospa"].mean() for r in results])
    return MultiEvaluation(scenario.name, trials, float(per_trial.mean()), float(base_per_trial.mean()),
                           float(parts[0]), float(parts[1]), float(parts[2]), tuple(float(v) for v in base_parts),
                           np.array([r["confirm_delay_s"] for r in results]),
                           np.array([r["false_tracks"] for r in results]),
                           np.array([r["identity_switches"] for r in results]), per_trial, base_per_trial)


# ---------------------------------------------------------------------------------------------------------------
# The scene


def _path_through(point_enu_m, at_s: float, speed_mps: float, heading_deg: float, on_s: float, off_s: float,
                  emitter_id: str, frequency_hz: float, up_m: float) -> EmitterPath:
    """A straight path at ``speed_mps`` on ``heading_deg`` passing ``point_enu_m`` (east, north) at ``at_s``."""
    heading = math.radians(heading_deg)
    velocity = (speed_mps * math.sin(heading), speed_mps * math.cos(heading), 0.0)
    start = (point_enu_m[0] - velocity[0] * at_s, point_enu_m[1] - velocity[1] * at_s, up_m)
    return EmitterPath(emitter_id, frequency_hz, start, velocity, on_s, off_s)


def multi_emitter_scene(variant: int = 0, **changes) -> MultiEmitterScenario:
    """Four direction finders over about 40 km (azimuth and elevation, 1 deg, one scan a second each at its own
    offset) and four ground emitters (module docstring). Variant 0: e1 (433.92 MHz) at 12 m/s heading 45 deg
    and e2 (same frequency) at 15 m/s heading 300 deg pass 1.5 km apart at 150 s; e3 (446.1 MHz) still,
    transmitting from halfway; e4 (145.5 MHz) at 8 m/s heading 180 deg, silent after 220 s. Other variants draw
    speeds (5-20 m/s), headings, where and when the pair meets (at 90-210 s: e2 then 0.8-2 km across e1's
    path, their closest approach at most that), the others' positions and e4's end (55-85 % of the scene)."""
    origin = (47.0, 8.0, 0.0)
    stations = _geodetic_stations(origin, (
        ("df-west", -15e3, -12e3, 600.0, {"report_offset_s": 0.0}),
        ("df-east", 17e3, -10e3, 450.0, {"report_offset_s": 0.27}),
        ("df-north", 12e3, 16e3, 800.0, {"report_offset_s": 0.55}),
        ("df-northwest", -14e3, 13e3, 500.0, {"report_offset_s": 0.81}),
    ), measures="bearing")
    duration = 300.0
    meet_s, miss_m, meet_at = 150.0, 1.5e3, (-1e3, 0.0)
    speeds, headings = (12.0, 15.0, 0.0, 8.0), (45.0, 300.0, 0.0, 180.0)
    still_at, e4_at, e4_off = (5e3, 6e3), (2e3, 8e3), 220.0
    if variant:
        rng = np.random.default_rng((variant, 33))
        meet_s, miss_m = rng.uniform(90.0, 210.0), rng.uniform(0.8e3, 2e3)
        meet_at = tuple(rng.uniform(-6e3, 6e3, 2).tolist())
        speeds = (rng.uniform(5.0, 20.0), rng.uniform(5.0, 20.0), 0.0, rng.uniform(5.0, 20.0))
        h1 = rng.uniform(0.0, 360.0)
        headings = (h1, h1 + rng.uniform(60.0, 300.0), 0.0, rng.uniform(0.0, 360.0))
        still_at = tuple(rng.uniform(-8e3, 8e3, 2).tolist())
        e4_at = tuple(rng.uniform(-8e3, 8e3, 2).tolist())
        e4_off = rng.uniform(0.55, 0.85) * duration
    # The pair's closest approach: e2 crosses at miss_m across e1's path at meet_s.
    h1 = math.radians(headings[0])
    across = (math.cos(h1) * miss_m, -math.sin(h1) * miss_m)
    emitters = (
        _path_through(meet_at, meet_s, speeds[0], headings[0], 0.0, duration, "e1", 433.92e6, 100.0),
        _path_through((meet_at[0] + across[0], meet_at[1] + across[1]), meet_s, speeds[1], headings[1], 0.0,
                      duration, "e2", 433.92e6, 150.0),
        _path_through(still_at, 0.0, 0.0, 0.0, duration / 2.0, duration, "e3", 446.1e6, 200.0),
        _path_through(e4_at, e4_off / 2.0, speeds[3], headings[3], 0.0, e4_off, "e4", 145.5e6, 50.0),
    )
    network = GROUND_EMITTERS
    scene = MultiEmitterScenario("multi_emitter", *origin, stations, emitters, duration_s=duration,
                                 config=AssociationConfig(network=network))
    return replace(scene, **changes)


def scale_scene(emitters: int = 20, stations: int = 10, duration_s: float = 60.0, seed: int = 0,
                **changes) -> MultiEmitterScenario:
    """``emitters`` ground emitters (5-20 m/s, distinct frequencies) seen by ``stations`` direction finders
    spread over a 60 km square, each scanning once a second: the scale of a large network."""
    rng = np.random.default_rng((seed, 20))
    origin = (47.0, 8.0, 0.0)
    offsets = [(f"df-{k}", *rng.uniform(-30e3, 30e3, 2).tolist(), float(rng.uniform(300.0, 900.0)),
                {"report_offset_s": float(rng.uniform(0.0, 1.0))}) for k in range(stations)]
    paths = tuple(_path_through(tuple(rng.uniform(-20e3, 20e3, 2).tolist()), 0.0, rng.uniform(5.0, 20.0),
                                rng.uniform(0.0, 360.0), 0.0, duration_s, f"e{k + 1}", 400e6 + 25e3 * k, 100.0)
                  for k in range(emitters))
    network = GROUND_EMITTERS
    scene = MultiEmitterScenario("scale", *origin, _geodetic_stations(origin, offsets, measures="bearing"), paths,
                                 duration_s=duration_s, config=AssociationConfig(network=network))
    return replace(scene, **changes)


SCENES = {"multi_emitter": multi_emitter_scene}
