"""Moving-emitter session filters (paper 001): pure ``(state, epoch) -> state`` functions.

Public API::

    config = TrackerConfig(model="velocity_kinematic", period_s=1e-3, period_known=False,
                           pulses_per_observation=1000, sigma_azimuth_rad=5e-3,
                           sigma_elevation_rad=5e-3, sigma_azimuth_rate_rad_s=2e-4,
                           sigma_toa_s=1e-8, accel_sigma_mps2=0.05)
    state = new_state(config)
    state = step(state, Epoch(time_s, azimuth_rad, elevation_rad, azimuth_rate_rad_s, toa_s), config)
    stored = state.to_dict()                      # JSON-able, exact
    state = TrackState.from_dict(stored)
"""

from core.tracking.config import JOINT_INITIAL_RANGES, MODELS, Epoch, TimeNotIncreasing, TrackerConfig
from core.tracking.session import new_state, step, step_many
from core.tracking.state import WARNING_CODES, TrackState

__all__ = [
    "JOINT_INITIAL_RANGES",
    "MODELS",
    "WARNING_CODES",
    "Epoch",
    "TimeNotIncreasing",
    "TrackState",
    "TrackerConfig",
    "new_state",
    "step",
    "step_many",
]
