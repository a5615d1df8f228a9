"""Moving emitter seen by one fixed observer: the paper-001 scenario and variants.

The observer is at the origin of its ENU frame. The emitter sends pulses
every ``period_s``; the observer reports every ``pulses_per_observation``-th
pulse: the azimuth (``atan2(x, y)``), elevation, azimuth rate and time of
arrival of that pulse, each with Gaussian noise. The truth of a report is the
emitter state when it emitted the reported pulse.

Motion is constant velocity, optionally with continuous white acceleration
noise of power spectral density ``accel_sigma_mps2**2 * 1 s`` per axis
(sampled exactly over each report interval), the model the session filters
assume.
"""

from __future__ import annotations

from dataclasses import dataclass, replace

import numpy as np

from core.angles import wrap_to_pi
from core.tracking.config import SPEED_OF_LIGHT_MPS, Epoch


@dataclass(frozen=True)
class EmitterScenario:
    """A single-observer moving-emitter scenario.

    Attributes
    ----------
    initial_position_enu_m : tuple of 3 floats
        Emitter position at the first report's emission (m, observer ENU).
    velocity_enu_mps : tuple of 3 floats
        Initial velocity (m/s).
    period_s : float
        True pulse period (s).
    pulses_per_observation : int
        Pulses between reports.
    epochs : int
        Number of scheduled reports (the first at emission time 0).
    sigma_azimuth_rad, sigma_elevation_rad, sigma_azimuth_rate_rad_s, sigma_toa_s : float
        Measurement noise standard deviations.
    accel_sigma_mps2 : float
        Acceleration noise intensity (0: exactly constant velocity).
    accel_sigma_by_interval_mps2 : tuple of float or None
        Per report interval (``epochs - 1`` values), the intensity over that
        interval instead of ``accel_sigma_mps2``: a target that switches
        between quiet and manoeuvring legs.
    toa_offset_s : float
        TOA clock reading at emission time 0 (TOAs are large numbers, as in practice).
    time_offset_s : float
        Observer ``time_s`` at emission time 0.
    missed_epochs : tuple of int
        Indices of scheduled reports the observer misses (absent from the output).
    turn_epoch : int or None
        Index of the scheduled report from which the emitter flies with
        ``velocity_after_turn_enu_mps`` (an instant turn just before that
        report's emission, position continuous); None for no turn.
    velocity_after_turn_enu_mps : tuple of 3 floats or None
    """

    initial_position_enu_m: tuple[float, float, float] = (120e3, 100e3, 8e3)
    velocity_enu_mps: tuple[float, float, float] = (-300.0, 100.0, 2.0)
    period_s: float = 1e-3
    pulses_per_observation: int = 1000
    epochs: int = 201
    sigma_azimuth_rad: float = 5e-3
    sigma_elevation_rad: float = 5e-3
    sigma_azimuth_rate_rad_s: float = 2e-4
    sigma_toa_s: float = 10e-9
    accel_sigma_mps2: float = 0.0
    accel_sigma_by_interval_mps2: tuple[float, ...] | None = None
    toa_offset_s: float = 500.0
    time_offset_s: float = 0.0
    missed_epochs: tuple[int, ...] = ()
    turn_epoch: int | None = None
    velocity_after_turn_enu_mps: tuple[float, float, float] | None = None

    @property
    def interval_s(self) -> float:
        """Nominal report interval ``T = N Tr`` (s)."""
        return self.pulses_per_observation * self.period_s


@dataclass(frozen=True)
class EmitterTrack:
    """One simulated run, restricted to the reports the observer made.

    Attributes
    ----------
    emission_times_s : ndarray, shape (K,)
        Emission time of each reported pulse since the first report (s).
    states_enu : ndarray, shape (K, 6)
        True ``[x, y, z (m), vx, vy, vz (m/s)]`` at those times.
    epochs : tuple of Epoch, length K
        The noisy reports.
    schedule_index : ndarray, shape (K,)
        Index of each report in the full schedule.
    """

    emission_times_s: np.ndarray
    states_enu: np.ndarray
    epochs: tuple[Epoch, ...]
    schedule_index: np.ndarray

    @property
    def ranges_m(self) -> np.ndarray:
        """True ranges ``(K,)`` (m)."""
        return np.linalg.norm(self.states_enu[:, :3], axis=1)


def paper_001_scenario(**changes) -> EmitterScenario:
    """The paper-001 scenario (Tr = 1 ms, N = 1000, 200 s), with any field changed."""
    return replace(EmitterScenario(), **changes)


def true_states(scenario: EmitterScenario, rng: np.random.Generator) -> np.ndarray:
    """True states ``(epochs, 6)`` at every scheduled report (m, m/s)."""
    k = scenario.epochs
    t = np.arange(k) * scenario.interval_s
    p0 = np.asarray(scenario.initial_position_enu_m, dtype=float)
    v0 = np.asarray(scenario.velocity_enu_mps, dtype=float)
    states = np.empty((k, 6))
    states[:, :3] = p0 + t[:, None] * v0
    states[:, 3:] = v0
    turn = scenario.turn_epoch
    if turn is not None and 0 < turn < k:
        v1 = np.asarray(scenario.velocity_after_turn_enu_mps, dtype=float)
        states[turn:, :3] = states[turn - 1, :3] + (t[turn:, None] - t[turn - 1]) * v1
        states[turn:, 3:] = v1
    sigmas = scenario.accel_sigma_by_interval_mps2
    if sigmas is None:
        sigmas = (scenario.accel_sigma_mps2,) * max(k - 1, 0)
    if len(sigmas) != max(k - 1, 0):
        raise ValueError("accel_sigma_by_interval_mps2 needs one value per report interval (epochs - 1)")
    if max(sigmas, default=0.0) > 0.0 and k > 1:
        dt = scenario.interval_s
        unit = np.linalg.cholesky(np.array([[dt**3 / 3.0, dt**2 / 2.0], [dt**2 / 2.0, dt]]))
        kicks = np.einsum("ij,kaj->kai", unit, rng.standard_normal((k - 1, 3, 2))) * np.asarray(sigmas)[:, None, None]
        for i in range(1, k):
            velocity = states[i - 1, 3:] if i != turn else states[i, 3:]
            states[i, :3] = states[i - 1, :3] + dt * velocity + kicks[i - 1, :, 0]
            states[i, 3:] = velocity + kicks[i - 1, :, 1]
    return states


def simulate_emitter(scenario: EmitterScenario, rng: np.random.Generator) -> EmitterTrack:
    """Simulate one run: true states and the observer's noisy reports.

    Parameters
    ----------
    scenario : EmitterScenario
    rng : numpy.random.Generator
        The only source of randomness.

    Returns
    -------
    EmitterTrack
    """
    states = true_states(scenario, rng)
    k = scenario.epochs
    t = np.arange(k) * scenario.interval_s
    x, y, z, vx, vy, vz = states.T
    rho2 = x * x + y * y
    ranges = np.sqrt(rho2 + z * z)
    noise = rng.standard_normal((k, 4))
    azimuth = wrap_to_pi(np.arctan2(x, y) + scenario.sigma_azimuth_rad * noise[:, 0])
    elevation = np.arctan2(z, np.sqrt(rho2)) + scenario.sigma_elevation_rad * noise[:, 1]
    rate = (y * vx - x * vy) / rho2 + scenario.sigma_azimuth_rate_rad_s * noise[:, 2]
    arrival = t + ranges / SPEED_OF_LIGHT_MPS
    toa = scenario.toa_offset_s + arrival + scenario.sigma_toa_s * noise[:, 3]
    time_s = scenario.time_offset_s + arrival

    missed = set(int(i) for i in scenario.missed_epochs)
    kept = np.array([i for i in range(k) if i not in missed], dtype=int)
    epochs = tuple(Epoch(float(time_s[i]), float(azimuth[i]), float(elevation[i]), float(rate[i]), float(toa[i]))
                   for i in kept)
    return EmitterTrack(t[kept], states[kept], epochs, kept)
