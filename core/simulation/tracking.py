"""Monte Carlo evaluation of the session filters (paper 001), against the posterior CRLB.

Each run is one simulated track with its own seed (``seed + r``), so the
runs can be cut into chunks that run here or on a Dask cluster
(:func:`core.parallel.run_chunks`) with the same result. A filter steps
through one track epoch by epoch (its state is sequential), so a chunk
loops over its runs; the bookkeeping afterwards is batched.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any, Callable

import numpy as np

from core.parallel import chunk_slices, run_chunks
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


def run_tracks(config: TrackerConfig, scenario: EmitterScenario, seeds) -> dict:
    """Run ``config`` on one simulated track per seed (one chunk of a Monte Carlo).

    Parameters
    ----------
    config : TrackerConfig
    scenario : EmitterScenario
    seeds : sequence of int
        One track per seed (``numpy.random.default_rng(seed)``).

    Returns
    -------
    dict
        ``times_s`` (K,), ``ranges_m`` (R, K), ``truths`` (R, K, 6), ``estimates`` (R, K, 6) (NaN before
        initialisation), ``covariances`` (R, K, 6, 6) (identity before initialisation).
    """
    seeds = list(seeds)
    k = scenario.epochs - len(scenario.missed_epochs)
    estimates = np.full((len(seeds), k, 6), np.nan)
    covariances = np.tile(np.eye(6), (len(seeds), k, 1, 1))
    truths = np.empty((len(seeds), k, 6))
    ranges = np.empty((len(seeds), k))
    times = np.zeros(k)
    for r, seed in enumerate(seeds):
        track = simulate_emitter(scenario, np.random.default_rng(seed))
        times = track.emission_times_s
        ranges[r] = track.ranges_m
        truths[r] = track.states_enu
        state = new_state(config)
        for i, epoch in enumerate(track.epochs):
            state = step(state, epoch, config)
            if state.initialized:
                estimates[r, i] = state.mean[:6]
                covariances[r, i] = state.covariance[:6, :6]
    return {"times_s": times, "ranges_m": ranges, "truths": truths, "estimates": estimates,
            "covariances": covariances}


def monte_carlo_tracks(config: TrackerConfig, scenario: EmitterScenario, runs: int, seed: int, *,
                       chunk_runs: int = 4, scheduler: Any = None,
                       progress: Callable[[int, int], None] | None = None) -> dict:
    """:func:`run_tracks` over runs ``seed + r``, ``r < runs``, in chunks (here or on a Dask cluster).

    The result is that of one call with every seed: it depends on neither ``chunk_runs`` nor the workers.
    """
    chunks = [(config, scenario, [seed + r for r in range(part.start, part.stop)])
              for part in chunk_slices(runs, chunk_runs)]
    parts = run_chunks(run_tracks, chunks, scheduler=scheduler, progress=progress)
    out = {key: np.concatenate([part[key] for part in parts]) for key in ("ranges_m", "truths", "estimates",
                                                                          "covariances")}
    out["times_s"] = parts[0]["times_s"]
    return out


def run_monte_carlo(config: TrackerConfig, scenario: EmitterScenario, runs: int, seed: int, *,
                    scheduler: Any = None, progress: Callable[[int, int], None] | None = None) -> MonteCarlo:
    """Run ``config`` on ``runs`` independent draws of ``scenario`` (seeds ``seed + r``).

    The per-epoch figures (NEES, sigmas, smallest correlation eigenvalue) are computed after the runs, in
    batches: the filter steps dominate the time, not the bookkeeping."""
    tracks = monte_carlo_tracks(config, scenario, runs, seed, scheduler=scheduler, progress=progress)
    covariances = tracks["covariances"]
    errors = tracks["estimates"] - tracks["truths"]
    k = errors.shape[1]
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
    return MonteCarlo(tracks["times_s"], tracks["ranges_m"], np.linalg.norm(errors[..., :3], axis=-1), errors, nees,
                      min_eigenvalues, sigmas)


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
    times_s : ndarray, shape (K,)
    ranges_m : ndarray, shape (R, K)
    own_bound_m2 : ndarray, shape (R, K)
        The same trace for the bound of each run's truth on its own (``session_pcrb(..., each_truth=True)``):
        what an efficient estimator reaches where the PCRB, which averages the information over the truths,
        is not attainable.
    """

    squared_errors_m2: np.ndarray
    nees: np.ndarray
    bound_m2: np.ndarray
    times_s: np.ndarray | None = None
    ranges_m: np.ndarray | None = None
    own_bound_m2: np.ndarray | None = None

    def rmse_m(self) -> np.ndarray:
        """Per epoch ``(K,)``, the position RMSE over runs (NaN while a run is not initialised)."""
        return np.sqrt(np.mean(self.squared_errors_m2, axis=0))

    def ratio(self, window: slice) -> float:
        """RMSE over runs and the epochs of ``window`` over the PCRB's RMS there."""
        return float(np.sqrt(np.mean(self.squared_errors_m2[:, window]) / np.mean(self.bound_m2[window])))

    def own_ratio(self, window: slice) -> float:
        """RMSE over runs and the epochs of ``window`` over the RMS there of each run's own bound."""
        return float(np.sqrt(np.mean(self.squared_errors_m2[:, window]) / np.mean(self.own_bound_m2[:, window])))

    def mean_nees(self, window: slice) -> np.ndarray:
        """Per epoch of ``window``, the mean position NEES over runs."""
        return self.nees[:, window].mean(axis=0)


def against_bound(config: TrackerConfig, scenario: EmitterScenario, runs: int, seed: int, *,
                  scheduler: Any = None, progress: Callable[[int, int], None] | None = None) -> AgainstBound:
    """Run ``config`` on ``runs`` draws of ``scenario`` (seeds ``seed + r``) next to the PCRB of the
    scenario's own model (its acceleration noise, per interval when it has a schedule).

    The session-filter evaluation of ``passive-locator evaluate`` (a tracking scenario): RMSE per epoch
    against the bound. Chunks of runs run here or on a Dask cluster (``scheduler``)."""
    from core.tracking.bound import session_pcrb

    tracks = monte_carlo_tracks(config, scenario, runs, seed, scheduler=scheduler, progress=progress)
    states = tracks["truths"]
    sigmas = scenario.accel_sigma_by_interval_mps2
    if sigmas is None:
        sigmas = (scenario.accel_sigma_mps2,) * (scenario.epochs - 1)
    bound = session_pcrb(states, tracks["times_s"], config, np.array(sigmas))
    own = session_pcrb(states, tracks["times_s"], config, np.array(sigmas), each_truth=True)
    error = tracks["estimates"][..., :3] - states[..., :3]
    squared = np.einsum("rki,rki->rk", error, error)
    position_cov = tracks["covariances"][..., :3, :3]
    ready = ~np.isnan(error[..., 0])
    nees = np.full(squared.shape, np.nan)
    nees[ready] = np.einsum("ni,ni->n", error[ready], np.linalg.solve(position_cov[ready], error[ready][..., None])[..., 0])
    return AgainstBound(squared, nees, bound.position_rmse_m**2, tracks["times_s"], tracks["ranges_m"],
                        own.position_rmse_m**2)
