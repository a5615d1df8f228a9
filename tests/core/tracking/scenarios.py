"""Shared Monte Carlo helpers for the session-filter tests (and ``report_figures``)."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from core.simulation.emitter import EmitterScenario, paper_001_scenario, simulate_emitter
from core.tracking import TrackerConfig, new_state, step

#: Period error of the initial estimate when the period is "unknown" (20 ns on 1 ms, 0.2 sigma of the default prior).
UNKNOWN_PERIOD_OFFSET_S = 20e-9
#: Filter acceleration noise for the constant-velocity paper scenario (m/s^2).
PAPER_ACCEL_SIGMA_MPS2 = 0.05


#: The paper emitter's first range (m): 156.4 km.
PAPER_FIRST_RANGE_M = float(np.linalg.norm(paper_001_scenario().initial_position_enu_m))


def paper_config(model: str, period_known: bool, **changes) -> TrackerConfig:
    """The paper-001 filter settings (sigmas of the scenario; period exact when known, 20 ns off when not)."""
    scenario = paper_001_scenario()
    fields = dict(
        model=model,
        period_s=scenario.period_s + (0.0 if period_known else UNKNOWN_PERIOD_OFFSET_S),
        period_known=period_known,
        pulses_per_observation=scenario.pulses_per_observation,
        sigma_azimuth_rad=scenario.sigma_azimuth_rad,
        sigma_elevation_rad=scenario.sigma_elevation_rad,
        sigma_azimuth_rate_rad_s=scenario.sigma_azimuth_rate_rad_s,
        sigma_toa_s=scenario.sigma_toa_s,
        accel_sigma_mps2=PAPER_ACCEL_SIGMA_MPS2,
    )
    fields.update(changes)
    return TrackerConfig(**fields)


@dataclass
class MonteCarlo:
    """Errors of one filter over runs and epochs (NaN before initialisation).

    Attributes
    ----------
    times_s : ndarray, shape (K,)
    ranges_m : ndarray, shape (R, K)
    position_errors_m : ndarray, shape (R, K)
        Norm of the position error.
    errors : ndarray, shape (R, K, 6)
        Estimate minus truth, ``[p, v]``.
    nees : ndarray, shape (R, K)
        ``e^T P^-1 e`` with the 6 x 6 covariance.
    min_eigenvalues : ndarray, shape (R, K)
        Smallest eigenvalue of the unit-diagonal (correlation) 6 x 6 covariance.
    sigmas : ndarray, shape (R, K, 6)
        Square roots of the covariance diagonal.
    """

    times_s: np.ndarray
    ranges_m: np.ndarray
    position_errors_m: np.ndarray
    errors: np.ndarray
    nees: np.ndarray
    min_eigenvalues: np.ndarray
    sigmas: np.ndarray

    def rmse_percent(self) -> np.ndarray:
        """Position RMSE over runs as a percentage of the mean true range, per epoch ``(K,)``; inf while any
        run is not initialised."""
        squared = np.where(np.isnan(self.position_errors_m), np.inf, self.position_errors_m**2)
        return 100.0 * np.sqrt(squared.mean(axis=0)) / self.ranges_m.mean(axis=0)

    def convergence_time_s(self, threshold_percent: float) -> float:
        """First time after which the RMSE stays at or below ``threshold_percent`` of the range (inf if never)."""
        above = np.flatnonzero(~(self.rmse_percent() <= threshold_percent))
        if above.size == 0:
            return float(self.times_s[0])
        if above[-1] == self.times_s.size - 1:
            return float("inf")
        return float(self.times_s[above[-1] + 1])


def run_monte_carlo(config: TrackerConfig, scenario: EmitterScenario, runs: int, seed: int) -> MonteCarlo:
    """Run ``config`` on ``runs`` independent draws of ``scenario`` (seeds ``seed + r``).

    The per-epoch figures (NEES, sigmas, smallest correlation eigenvalue) are computed after the runs, in
    batches: the filter steps dominate the time, not the bookkeeping."""
    k = scenario.epochs - len(scenario.missed_epochs)
    estimates = np.full((runs, k, 6), np.nan)
    covariances = np.tile(np.eye(6), (runs, k, 1, 1))
    truths = np.empty((runs, k, 6))
    ranges = np.empty((runs, k))
    times = None
    for r in range(runs):
        track = simulate_emitter(scenario, np.random.default_rng(seed + r))
        times = track.emission_times_s
        ranges[r] = track.ranges_m
        truths[r] = track.states_enu
        state = new_state(config)
        for i, epoch in enumerate(track.epochs):
            state = step(state, epoch, config)
            if state.initialized:
                estimates[r, i] = state.mean[:6]
                covariances[r, i] = state.covariance[:6, :6]
    errors = estimates - truths
    ready = ~np.isnan(errors[..., 0])
    nees = np.full((runs, k), np.nan)
    min_eigenvalues = np.full((runs, k), np.nan)
    sigmas = np.full((runs, k, 6), np.nan)
    cov = covariances[ready]
    d = np.sqrt(np.diagonal(cov, axis1=-2, axis2=-1))
    sigmas[ready] = d
    e = errors[ready]
    nees[ready] = np.einsum("ni,ni->n", e, np.linalg.solve(cov, e[..., None])[..., 0])
    min_eigenvalues[ready] = np.linalg.eigvalsh(cov / (d[:, :, None] * d[:, None, :]))[:, 0]
    return MonteCarlo(times, ranges, np.linalg.norm(errors[..., :3], axis=-1), errors, nees, min_eigenvalues, sigmas)


@dataclass
class AgainstBound:
    """A filter's position errors over runs next to the PCRB of the truth's model.

    Attributes
    ----------
    squared_errors_m2 : ndarray, shape (R, K)
        ``|p_hat - p|^2``; NaN before initialisation.
    nees : ndarray, shape (R, K)
        Position NEES (3 degrees of freedom).
    bound_m2 : ndarray, shape (K,)
        Trace of the PCRB's position block.
    """

    squared_errors_m2: np.ndarray
    nees: np.ndarray
    bound_m2: np.ndarray

    def ratio(self, window: slice) -> float:
        """RMSE over runs and the epochs of ``window`` over the PCRB's RMS there."""
        return float(np.sqrt(np.mean(self.squared_errors_m2[:, window]) / np.mean(self.bound_m2[window])))

    def mean_nees(self, window: slice) -> np.ndarray:
        """Per epoch of ``window``, the mean position NEES over runs."""
        return self.nees[:, window].mean(axis=0)


def against_bound(config: TrackerConfig, scenario: EmitterScenario, runs: int, seed: int) -> AgainstBound:
    """Run ``config`` on ``runs`` draws of ``scenario`` (seeds ``seed + r``) next to the PCRB of the
    scenario's own model (its acceleration noise, per interval when it has a schedule)."""
    from core.tracking.bound import session_pcrb

    tracks = [simulate_emitter(scenario, np.random.default_rng(seed + r)) for r in range(runs)]
    states = np.array([t.states_enu for t in tracks])
    sigmas = scenario.accel_sigma_by_interval_mps2
    if sigmas is None:
        sigmas = (scenario.accel_sigma_mps2,) * (scenario.epochs - 1)
    bound = session_pcrb(states, tracks[0].emission_times_s, config, np.array(sigmas))
    squared = np.full(states.shape[:2], np.nan)
    nees = np.full(states.shape[:2], np.nan)
    for r, track in enumerate(tracks):
        state = new_state(config)
        for i, epoch in enumerate(track.epochs):
            state = step(state, epoch, config)
            if state.initialized:
                error = state.mean[:3] - track.states_enu[i, :3]
                squared[r, i] = error @ error
                nees[r, i] = error @ np.linalg.solve(state.covariance[:3, :3], error)
    return AgainstBound(squared, nees, bound.position_rmse_m**2)
