"""Network tracking scenes and their Monte Carlo evaluation against the posterior CRLB.

Three scenes (:func:`df_network_scene`, :func:`toa_network_scene`, :func:`airborne_df_scene`), each a
:class:`NetworkScenario`: stations at geodetic positions (so the common frame is exercised over 20-50 km:
every measurement is simulated and filtered with its station's own position and rotation, the frame built
with :mod:`core.geodesy` as a fix builds it), an emitter drawn from the tracker's own model (constant
velocity with white acceleration, exactly discretised, in the common frame), reports as the stations would
post them (each station at its own times, a fraction of the reports posted late).

:func:`simulate_network` gives one run (truth, reports in posting order, and what the HTTP API needs to post
them); :func:`evaluate_network` runs seeded trials through :func:`core.tracking.network.apply_reports` as
reports arrive and gives per-epoch RMSE and NEES against :func:`core.tracking.network_bound.network_pcrb`.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field, replace
from typing import NamedTuple

import numpy as np
from scipy.stats import chi2

from core import geodesy
from core.measurements import AZIMUTH, ELEVATION, SPEED_OF_LIGHT_MPS, TOA, predict
from core.parallel import Stopped
from core.tracking.motion import transition
from core.tracking.network import NetworkConfig, Report, apply_reports, new_network_state, predict_tracks
from core.tracking.network_bound import network_pcrb

#: What a station measures.
STATION_KINDS = ("bearing", "toa")
#: Session clock at a scene's start (s): small enough that float64 TOAs keep sub-picosecond digits.
START_TIME_S = 1000.0


@dataclass(frozen=True)
class NetworkStation:
    """One station of a scene.

    Attributes
    ----------
    id : str
    lat_deg, lon_deg, alt_m : float
        WGS84 position (a moving station's is given per report by the scene's ``platform``).
    measures : str
        ``"bearing"`` (azimuth and elevation) or ``"toa"``.
    sigma_azimuth_rad, sigma_elevation_rad, sigma_toa_s : float
    report_offset_s : float
        A bearing station reports every ``report_interval_s`` from this offset after the start.
    """

    id: str
    lat_deg: float
    lon_deg: float
    alt_m: float
    measures: str = "bearing"
    sigma_azimuth_rad: float = math.radians(1.0)
    sigma_elevation_rad: float = math.radians(1.0)
    sigma_toa_s: float = 30e-9
    report_offset_s: float = 0.0


@dataclass(frozen=True)
class AirbornePath:
    """A platform flying straight, then turning at a constant rate, then straight again, at a constant height.

    Attributes
    ----------
    start_enu_m : tuple of 3 floats
        Common frame, at the scene's start.
    speed_mps : float
    heading_deg : float
        Clockwise from the common frame's north.
    straight_s : float
        Time before the turn.
    turn_rate_deg_s : float
        Positive: to the right.
    turn_s : float
    """

    start_enu_m: tuple[float, float, float]
    speed_mps: float
    heading_deg: float
    straight_s: float
    turn_rate_deg_s: float
    turn_s: float

    def position_enu_m(self, elapsed_s: float) -> np.ndarray:
        """Platform position ``(3,)`` at ``elapsed_s`` after the start."""
        heading = math.radians(self.heading_deg)
        p = np.array(self.start_enu_m, dtype=float)
        leg = min(elapsed_s, self.straight_s)
        p[:2] += self.speed_mps * leg * np.array([math.sin(heading), math.cos(heading)])
        if elapsed_s <= self.straight_s:
            return p
        rate = math.radians(self.turn_rate_deg_s)
        turning = min(elapsed_s - self.straight_s, self.turn_s)
        radius = self.speed_mps / rate
        end_heading = heading + rate * turning
        p[0] += radius * (math.cos(heading) - math.cos(end_heading))
        p[1] += radius * (math.sin(end_heading) - math.sin(heading))
        rest = elapsed_s - self.straight_s - turning
        p[:2] += self.speed_mps * rest * np.array([math.sin(end_heading), math.cos(end_heading)])
        return p


@dataclass(frozen=True)
class NetworkScenario:
    """A network tracking scene: stations, the emitter's prior and motion, the reporting, the tracker.

    Attributes
    ----------
    name : str
    origin_lat_deg, origin_lon_deg, origin_alt_m : float
        The common frame's tangent point.
    stations : tuple of NetworkStation
    duration_s : float
    report_interval_s : float
        Each bearing station's report interval; the pulse interval of a TOA scene (one report per pulse
        with every TOA station's TOA).
    emitter_start_enu_m : tuple of 3 floats
        Mean start position, common frame.
    emitter_start_spread_m : float
        Standard deviation of the start position about it, horizontally.
    emitter_speed_mps, emitter_heading_deg : float
        Start velocity (horizontal; heading clockwise from the common frame's north). Every trial starts
        from this nominal state (plus the spread): the PCRB averages the measurement information over the
        trials' truths, which is attainable only while their geometries differ by less than the noise
        (:func:`core.tracking.network_bound.network_pcrb`); a scene's variants (``variant=`` of the scene
        functions) draw other nominal states.
    truth_accel_sigma_mps2 : float
        White-acceleration intensity the truth is drawn with.
    truth_vertical_accel_sigma_mps2 : float or None
        Its intensity on the up axis (None: the same).
    late_fraction : float
        Fraction of reports posted late, each by a delay uniform in ``(0, max_delay_s)``.
    max_delay_s : float
    platform : AirbornePath or None
        The path of the scene's moving station (the first station), None when every station is fixed.
    config : NetworkConfig
        The tracker's settings for the scene.
    epoch_interval_s : float
        Evaluation epochs: every this many seconds after the start.
    converged_after_s : float
        Epochs from this long after the start are judged against the bound.
    """

    name: str
    origin_lat_deg: float
    origin_lon_deg: float
    origin_alt_m: float
    stations: tuple[NetworkStation, ...]
    duration_s: float
    report_interval_s: float
    emitter_start_enu_m: tuple[float, float, float]
    emitter_start_spread_m: float
    emitter_speed_mps: float
    emitter_heading_deg: float
    truth_accel_sigma_mps2: float
    truth_vertical_accel_sigma_mps2: float | None = None
    late_fraction: float = 0.0
    max_delay_s: float = 0.0
    platform: AirbornePath | None = None
    config: NetworkConfig = field(default_factory=NetworkConfig)
    epoch_interval_s: float = 1.0
    converged_after_s: float = 60.0

    @property
    def origin_rad(self) -> tuple[float, float, float]:
        return math.radians(self.origin_lat_deg), math.radians(self.origin_lon_deg), self.origin_alt_m


class PostedReport(NamedTuple):
    """A report as a client posts it.

    Attributes
    ----------
    report : Report
        Core's report (common frame); ``seq`` in posting order.
    arrival_s : float
        When it is posted (session clock).
    moving_stations : tuple of (str, float, float, float)
        ``(station_id, lat_deg, lon_deg, alt_m)`` of each moving station at ``report.time_s`` (the API's
        per-report ``stations``).
    """

    report: Report
    arrival_s: float
    moving_stations: tuple


class NetworkRun(NamedTuple):
    """One simulated run.

    Attributes
    ----------
    times_s : ndarray, shape (T,)
        Every report time and epoch, sorted.
    states_enu : ndarray, shape (T, 6)
        The truth at those times.
    posted : tuple of PostedReport
        In posting order.
    """

    times_s: np.ndarray
    states_enu: np.ndarray
    posted: tuple

    def truth_at(self, time_s) -> np.ndarray:
        """True states ``(..., 6)`` at times that are in :attr:`times_s`."""
        index = np.searchsorted(self.times_s, time_s)
        return self.states_enu[index]


def station_frame(scenario: NetworkScenario):
    """Fixed stations in the common frame: positions ``(N, 3)`` and rotations ``(N, 3, 3)`` (station ENU <-
    common ENU), exact (:mod:`core.geodesy`)."""
    lat0, lon0, alt0 = scenario.origin_rad
    lat = np.radians([s.lat_deg for s in scenario.stations])
    lon = np.radians([s.lon_deg for s in scenario.stations])
    alt = np.array([s.alt_m for s in scenario.stations])
    positions = geodesy.geodetic_to_enu(lat, lon, alt, lat0, lon0, alt0)
    return positions, geodesy.enu_to_enu_rotation(lat0, lon0, lat, lon)


def _platform_at(scenario: NetworkScenario, time_s: float):
    """The moving station's common-frame position, rotation and geodetic position at ``time_s``."""
    lat0, lon0, alt0 = scenario.origin_rad
    position = scenario.platform.position_enu_m(time_s - START_TIME_S)
    lat, lon, alt = geodesy.enu_to_geodetic(position, lat0, lon0, alt0)
    return position, geodesy.enu_to_enu_rotation(lat0, lon0, lat, lon), (math.degrees(lat), math.degrees(lon),
                                                                          float(alt))


def report_schedule(scenario: NetworkScenario) -> list[tuple[float, tuple[int, ...]]]:
    """``(time_s, station indices)`` of every report in time order (the same in every run)."""
    end = START_TIME_S + scenario.duration_s
    toa = [i for i, s in enumerate(scenario.stations) if s.measures == "toa"]
    schedule = []
    for i, station in enumerate(scenario.stations):
        if station.measures != "bearing":
            continue
        t = START_TIME_S + station.report_offset_s
        while t <= end + 1e-9:
            schedule.append((t, (i,)))
            t += scenario.report_interval_s
    if toa:
        count = int(math.floor(scenario.duration_s / scenario.report_interval_s + 1e-9)) + 1
        schedule.extend((START_TIME_S + k * scenario.report_interval_s, tuple(toa)) for k in range(count))
    schedule.sort(key=lambda item: (item[0], item[1]))
    return schedule


def epoch_times(scenario: NetworkScenario) -> np.ndarray:
    """Evaluation epochs ``(E,)``: every ``epoch_interval_s`` after the start, to the end."""
    count = int(math.floor(scenario.duration_s / scenario.epoch_interval_s + 1e-9))
    return START_TIME_S + scenario.epoch_interval_s * np.arange(1, count + 1)


def simulate_truth(scenario: NetworkScenario, times_s, rng: np.random.Generator) -> np.ndarray:
    """True states ``(T, 6)`` at sorted times: a start drawn from the scene's prior, then constant velocity with
    white acceleration of ``truth_accel_sigma_mps2``, exactly discretised (:func:`core.tracking.motion.transition`)."""
    times = np.asarray(times_s, dtype=float)
    state = np.zeros(6)
    state[:2] = np.asarray(scenario.emitter_start_enu_m[:2]) + rng.normal(0.0, scenario.emitter_start_spread_m, 2)
    state[2] = scenario.emitter_start_enu_m[2]
    speed = scenario.emitter_speed_mps
    heading = math.radians(scenario.emitter_heading_deg)
    state[3:5] = speed * math.sin(heading), speed * math.cos(heading)
    q = scenario.truth_accel_sigma_mps2 ** 2
    scale = np.ones(6)
    if scenario.truth_vertical_accel_sigma_mps2 is not None:
        scale[[2, 5]] = scenario.truth_vertical_accel_sigma_mps2 / scenario.truth_accel_sigma_mps2
    out = np.empty((times.size, 6))
    last = START_TIME_S
    for k, t in enumerate(times.tolist()):
        if t > last:
            phi, noise = transition(6, (3,), True, t - last, q)
            kick = scale * (np.linalg.cholesky(noise) @ rng.standard_normal(6)) if q > 0.0 else 0.0
            state = phi @ state + kick
            last = t
        out[k] = state
    return out


def simulate_network(scenario: NetworkScenario, rng: np.random.Generator) -> NetworkRun:
    """One run: the truth and every report, noisy, in posting order (module docstring)."""
    schedule = report_schedule(scenario)
    epochs = epoch_times(scenario)
    times = np.unique(np.concatenate([[t for t, _ in schedule], epochs]))
    states = simulate_truth(scenario, times, rng)
    positions, rotations = station_frame(scenario)
    drafts = []
    for time_s, members in schedule:
        truth = states[np.searchsorted(times, time_s)]
        stations, turns, kinds, sigmas, ids, moving = [], [], [], [], [], ()
        for i in members:
            station = scenario.stations[i]
            position, rotation = positions[i], rotations[i]
            if scenario.platform is not None and i == 0:
                position, rotation, geodetic = _platform_at(scenario, time_s)
                moving = ((station.id,) + geodetic,)
            if station.measures == "bearing":
                pairs = ((AZIMUTH, station.sigma_azimuth_rad), (ELEVATION, station.sigma_elevation_rad))
            else:
                pairs = ((TOA, station.sigma_toa_s),)
            for kind, sigma in pairs:
                stations.append(position)
                turns.append(rotation)
                kinds.append(kind)
                sigmas.append(sigma)
                ids.append(station.id)
        stations, turns, kinds, sigmas = np.array(stations), np.array(turns), np.array(kinds), np.array(sigmas)
        exact, _ = predict(truth[:3], 0.0, stations, turns, kinds)
        values = np.where(kinds == TOA, time_s + exact / SPEED_OF_LIGHT_MPS, exact) + rng.normal(0.0, sigmas)
        late = rng.uniform() < scenario.late_fraction
        arrival = time_s + (rng.uniform(0.0, scenario.max_delay_s) if late else 0.0)
        drafts.append((arrival, time_s, tuple(ids), stations, turns, kinds, values, sigmas, moving))
    drafts.sort(key=lambda d: (d[0], d[1]))
    posted = tuple(PostedReport(Report(seq, time_s, "e1", ids, stations, turns, kinds, values, sigmas), arrival, moving)
                   for seq, (arrival, time_s, ids, stations, turns, kinds, values, sigmas, moving) in enumerate(drafts))
    return NetworkRun(times, states, posted)


@dataclass(frozen=True)
class NetworkEvaluation:
    """Monte Carlo accuracy of the network tracker on a scene, per epoch, against the PCRB.

    Attributes
    ----------
    scenario : str
    trials : int
    times_s : ndarray, shape (E,)
    rmse_position_m, rmse_velocity_mps : ndarray, shape (E,)
        Over the trials with a track at the epoch (NaN where none has one).
    pcrb_position_m, pcrb_velocity_mps : ndarray, shape (E,)
        ``sqrt(trace)`` of the bound's blocks (inf while the position is not determined).
    nees_position, nees_state : ndarray, shape (E,)
        Mean over the trials of the position (3 degrees of freedom) and state (6) NEES.
    nees_interval_99 : tuple of 2 floats
        The chi-square 99 % interval of a per-epoch mean of the position NEES over ``trials``.
    tracked_fraction, confirmed_fraction : ndarray, shape (E,)
        Trials with a track, and with a confirmed one, at each epoch.
    converged_after_s : float
    rmse_over_pcrb : float
        Position RMSE over the epochs from ``converged_after_s`` (root of the mean squared error) over the
        bound's (root of the mean squared bound) there.
    nees_after : float
        Mean position NEES over those epochs and trials.
    late_reports : int
        Reports counted late (over all trials).
    estimates_enu, covariances_enu : ndarray, shape (R, E, 6) and (R, E, 6, 6)
        Every trial's estimate (NaN without a track), for further comparisons.
    truths_enu : ndarray, shape (R, E, 6)
    own_bound_position_m : ndarray, shape (E,)
        RMS over the trials of each truth's own bound (``network_pcrb(..., each_truth=True)``): what a filter
        approaches where the truths' geometries differ (not itself a bound).
    rmse_over_own_bound : float
        As ``rmse_over_pcrb``, against ``own_bound_position_m``.
    """

    scenario: str
    trials: int
    times_s: np.ndarray
    rmse_position_m: np.ndarray
    rmse_velocity_mps: np.ndarray
    pcrb_position_m: np.ndarray
    pcrb_velocity_mps: np.ndarray
    nees_position: np.ndarray
    nees_state: np.ndarray
    nees_interval_99: tuple[float, float]
    tracked_fraction: np.ndarray
    confirmed_fraction: np.ndarray
    converged_after_s: float
    rmse_over_pcrb: float
    nees_after: float
    late_reports: int
    estimates_enu: np.ndarray
    covariances_enu: np.ndarray
    truths_enu: np.ndarray
    own_bound_position_m: np.ndarray
    rmse_over_own_bound: float

    def summary(self) -> dict:
        """The headline figures as plain numbers."""
        return {"scenario": self.scenario, "trials": self.trials, "converged_after_s": self.converged_after_s,
                "rmse_over_pcrb": self.rmse_over_pcrb,
                "rmse_over_own_bound": self.rmse_over_own_bound, "nees_after": self.nees_after,
                "nees_interval_99": list(self.nees_interval_99), "late_reports": self.late_reports}


def run_trial(scenario: NetworkScenario, run: NetworkRun, config: NetworkConfig | None = None):
    """Post one run's reports as they arrive and read the track at every epoch.

    Returns
    -------
    estimates : ndarray, shape (E, 6)
        NaN where there is no track.
    covariances : ndarray, shape (E, 6, 6)
    statuses : list of str or None, length E
    late : int
    """
    config = config or scenario.config
    epochs = epoch_times(scenario)
    estimates = np.full((epochs.size, 6), np.nan)
    covariances = np.full((epochs.size, 6, 6), np.nan)
    statuses: list = [None] * epochs.size
    state = new_network_state(config)
    late = 0
    posted = run.posted
    next_report = 0
    for j, t in enumerate(epochs.tolist()):
        batch = []
        while next_report < len(posted) and posted[next_report].arrival_s <= t:
            batch.append(posted[next_report].report)
            next_report += 1
        for report in batch:
            outcome = apply_reports(state, [report], config)
            state, late = outcome.state, late + outcome.late
        tracks = predict_tracks(state, t, config)
        if tracks:
            estimates[j] = tracks[0].mean_enu
            covariances[j] = tracks[0].covariance_enu
            statuses[j] = tracks[0].status
    return estimates, covariances, statuses, late


def nees(errors, covariances) -> np.ndarray:
    """``e^T P^-1 e`` over the last axes (NaN where ``e`` is)."""
    out = np.full(errors.shape[:-1], np.nan)
    ok = np.all(np.isfinite(errors), axis=-1)
    out[ok] = np.einsum("ni,ni->n", errors[ok], np.linalg.solve(covariances[ok], errors[ok][..., None])[..., 0])
    return out


def evaluate_network(scenario: NetworkScenario, trials: int, seed: int = 0, config: NetworkConfig | None = None,
                     should_stop=None) -> NetworkEvaluation:
    """Seeded Monte Carlo of the network tracker on a scene (trial ``r`` draws from ``seed + r``).

    Each trial posts its reports one at a time as they arrive and reads the track, predicted, at every
    epoch; the bound is :func:`core.tracking.network_bound.network_pcrb` over the trials' truths. ``should_stop``
    (optional, a request's deadline or cancellation) is asked before each trial: True raises ``Stopped``.
    """
    config = config or scenario.config
    epochs = epoch_times(scenario)
    schedule_runs = []
    estimates = np.full((trials, epochs.size, 6), np.nan)
    covariances = np.full((trials, epochs.size, 6, 6), np.nan)
    truths = np.empty((trials, epochs.size, 6))
    confirmed = np.zeros((trials, epochs.size), dtype=bool)
    late = 0
    report_truths = []
    for r in range(trials):
        if should_stop is not None and should_stop():
            raise Stopped(f"stopped after {r} of {trials} trials")
        run = simulate_network(scenario, np.random.default_rng(seed + r))
        estimates[r], covariances[r], statuses, trial_late = run_trial(scenario, run, config)
        late += trial_late
        truths[r] = run.truth_at(epochs)
        confirmed[r] = [s == "confirmed" for s in statuses]
        in_time = sorted((p.report for p in run.posted), key=lambda rep: rep.order_key)
        report_truths.append(run.truth_at([rep.time_s for rep in in_time]))
        if r == 0:
            schedule_runs = in_time
    model = dict(times_s=epochs, vertical_accel_sigma_mps2=scenario.truth_vertical_accel_sigma_mps2,
                 vertical_velocity_prior_sigma_mps=config.vertical_velocity_prior_sigma_mps)
    bound = network_pcrb(np.array(report_truths), schedule_runs, scenario.truth_accel_sigma_mps2,
                         config.velocity_prior_sigma_mps, **model)
    own = network_pcrb(np.array(report_truths), schedule_runs, scenario.truth_accel_sigma_mps2,
                       config.velocity_prior_sigma_mps, each_truth=True, **model)
    with np.errstate(invalid="ignore"):
        own_position = np.sqrt(np.mean(own.position_rmse_m ** 2, axis=0))
    errors = estimates - truths
    tracked = np.all(np.isfinite(estimates), axis=-1)
    with np.errstate(invalid="ignore"):
        mse_position = np.nanmean(np.sum(errors[..., :3] ** 2, axis=-1), axis=0)
        mse_velocity = np.nanmean(np.sum(errors[..., 3:] ** 2, axis=-1), axis=0)
        nees_position = np.nanmean(nees(errors[..., :3], covariances[..., :3, :3]), axis=0)
        nees_state = np.nanmean(nees(errors, covariances), axis=0)
    after = epochs >= START_TIME_S + scenario.converged_after_s
    ratio = math.sqrt(float(np.mean(mse_position[after])) / float(np.mean(bound.position_rmse_m[after] ** 2)))
    own_ratio = math.sqrt(float(np.mean(mse_position[after])) / float(np.mean(own_position[after] ** 2)))
    interval = (float(chi2.ppf(0.005, 3 * trials) / trials), float(chi2.ppf(0.995, 3 * trials) / trials))
    return NetworkEvaluation(scenario.name, trials, epochs, np.sqrt(mse_position), np.sqrt(mse_velocity),
                             bound.position_rmse_m, bound.velocity_rmse_mps, nees_position, nees_state, interval,
                             tracked.mean(axis=0), confirmed.mean(axis=0), scenario.converged_after_s, ratio,
                             float(np.mean(nees_position[after])), late, estimates, covariances, truths,
                             own_position, own_ratio)


# The scenes ----------------------------------------------------------------------------------------------------


def _geodetic_stations(origin, offsets_enu_m, **fields) -> tuple[NetworkStation, ...]:
    """Stations at common-frame offsets ``(id, east_m, north_m, up_m, extra fields)`` from ``origin`` (deg, m)."""
    lat0, lon0, alt0 = math.radians(origin[0]), math.radians(origin[1]), origin[2]
    out = []
    for station_id, east, north, up, extra in offsets_enu_m:
        lat, lon, alt = geodesy.enu_to_geodetic(np.array([east, north, up]), lat0, lon0, alt0)
        out.append(NetworkStation(station_id, math.degrees(lat), math.degrees(lon), float(alt), **{**fields, **extra}))
    return tuple(out)


def _variant(variant: int, stream: int) -> np.random.Generator:
    """The generator of a scene's nominal draws: variant 0 is the scene as documented."""
    return np.random.default_rng((variant, stream))


def df_network_scene(variant: int = 0, **changes) -> NetworkScenario:
    """Four direction finders 25-35 km apart (azimuth and elevation, 1 deg), each reporting once a second at
    its own times; a ground vehicle at 15-25 m/s (variant 0: 20 m/s heading 60 deg from the network's
    middle; other variants draw speed, heading and start); a tenth of the reports posted up to 1.5 s late."""
    origin = (47.0, 8.0, 0.0)
    stations = _geodetic_stations(origin, (
        ("df-west", -15e3, -12e3, 600.0, {"report_offset_s": 0.0}),
        ("df-east", 17e3, -10e3, 450.0, {"report_offset_s": 0.27}),
        ("df-north", 12e3, 16e3, 800.0, {"report_offset_s": 0.55}),
        ("df-northwest", -14e3, 13e3, 500.0, {"report_offset_s": 0.81}),
    ), measures="bearing")
    speed, heading, start = 20.0, 60.0, (0.0, 0.0, 0.0)
    if variant:
        rng = _variant(variant, 1)
        speed, heading = rng.uniform(15.0, 25.0), rng.uniform(0.0, 360.0)
        start = tuple(rng.uniform(-8e3, 8e3, 2).tolist()) + (0.0,)
    scene = NetworkScenario("df_network", *origin, stations, duration_s=180.0, report_interval_s=1.0,
                            emitter_start_enu_m=start, emitter_start_spread_m=0.0, emitter_speed_mps=speed,
                            emitter_heading_deg=heading, truth_accel_sigma_mps2=0.2, late_fraction=0.1,
                            max_delay_s=1.5,
                            config=NetworkConfig(accel_sigma_mps2=0.2, velocity_prior_sigma_mps=30.0,
                                                 reorder_window_s=2.0),
                            converged_after_s=60.0)
    return replace(scene, **changes)


def toa_network_scene(variant: int = 0, station_count: int = 5, **changes) -> NetworkScenario:
    """Five TOA stations 20-50 km apart (sigmas 20-50 ns) timing an aircraft at 5-10 km altitude flying at
    150-250 m/s (variant 0: 7.5 km, 200 m/s, heading 70 deg across the network; other variants draw them),
    manoeuvring at 1 m/s^2 horizontally and 0.1 m/s^2 vertically (the tracker knows both); one report per
    pulse (once a second) with every station's TOA.

    ``station_count=4`` drops the middle station: each pulse then places the height only along a ridge that
    turns by a degree across the truths' spread, and the PCRB (information averaged over truths) is reached
    by no tracker: this class's yardstick is :attr:`NetworkEvaluation.rmse_over_own_bound`."""
    origin = (51.0, 10.0, 0.0)
    stations = _geodetic_stations(origin, (
        ("toa-a", -20e3, -18e3, 150.0, {"sigma_toa_s": 20e-9}),
        ("toa-b", 22e3, -15e3, 300.0, {"sigma_toa_s": 30e-9}),
        ("toa-c", 18e3, 21e3, 250.0, {"sigma_toa_s": 40e-9}),
        ("toa-d", -19e3, 17e3, 400.0, {"sigma_toa_s": 50e-9}),
        ("toa-e", 2e3, 1e3, 200.0, {"sigma_toa_s": 25e-9}),
    ), measures="toa")
    if station_count not in (4, 5):
        raise ValueError(f"station_count must be 4 or 5, got {station_count!r}")
    stations = stations[:station_count]
    speed, heading, start = 200.0, 70.0, (-10e3, -4e3, 7.5e3)
    if variant:
        rng = _variant(variant, 2)
        speed, heading = rng.uniform(150.0, 250.0), rng.uniform(0.0, 360.0)
        direction = np.array([math.sin(math.radians(heading)), math.cos(math.radians(heading))])
        start = tuple((-0.5 * 120.0 * speed * direction + rng.uniform(-5e3, 5e3, 2)).tolist()) + (
            rng.uniform(5e3, 10e3),)
    scene = NetworkScenario("toa_network" if station_count == 5 else "toa_network_4", *origin, stations,
                            duration_s=120.0, report_interval_s=1.0, emitter_start_enu_m=start,
                            emitter_start_spread_m=0.0, emitter_speed_mps=speed, emitter_heading_deg=heading,
                            truth_accel_sigma_mps2=1.0, truth_vertical_accel_sigma_mps2=0.1,
                            config=NetworkConfig(accel_sigma_mps2=1.0, velocity_prior_sigma_mps=300.0,
                                                 vertical_accel_sigma_mps2=0.1,
                                                 vertical_velocity_prior_sigma_mps=20.0),
                            converged_after_s=30.0)
    return replace(scene, **changes)


def airborne_df_scene(variant: int = 0, **changes) -> NetworkScenario:
    """One airborne direction finder (azimuth and elevation, 1 deg, once a second) at 6 km flying east at
    150 m/s for 90 s, turning left by 90 deg at 3 deg/s, then north, past a ground emitter 30 km north of
    its track moving at 3 m/s (other variants draw its start within 25-35 km and its speed, 2-5 m/s, and
    heading): the range is not observable before the turn.

    After the turn the range is still learnt slowly and the velocity prior (10 m/s per axis) still weighs:
    the PCRB is the mean squared error over truths drawn from that prior, and this emitter (3 m/s, level) is
    one the prior's shrinkage favours, so the tracker's RMSE after the turn may sit below the PCRB (0.86x to
    1.01x over the seeds tried, 40 to 100 trials); its NEES stays in its interval."""
    origin = (45.0, 5.0, 0.0)
    stations = _geodetic_stations(origin, (("air-df", -15e3, 0.0, 6000.0, {}),), measures="bearing")
    path = AirbornePath((-15e3, 0.0, 6000.0), 150.0, 90.0, 90.0, -3.0, 30.0)
    speed, heading, start = 3.0, 200.0, (0.0, 30e3, 0.0)
    if variant:
        rng = _variant(variant, 3)
        speed, heading = rng.uniform(2.0, 5.0), rng.uniform(0.0, 360.0)
        start = (rng.uniform(-5e3, 5e3), rng.uniform(25e3, 35e3), 0.0)
    scene = NetworkScenario("airborne_df", *origin, stations, duration_s=240.0, report_interval_s=1.0,
                            emitter_start_enu_m=start, emitter_start_spread_m=0.0, emitter_speed_mps=speed,
                            emitter_heading_deg=heading, truth_accel_sigma_mps2=0.05, platform=path,
                            config=NetworkConfig(accel_sigma_mps2=0.05, velocity_prior_sigma_mps=10.0),
                            converged_after_s=180.0)
    return replace(scene, **changes)


SCENES = {"df_network": df_network_scene, "toa_network": toa_network_scene, "airborne_df": airborne_df_scene}
