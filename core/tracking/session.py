"""The session filter's public functions: ``new_state``, ``step``, ``step_many``.

They are pure: a state and an epoch in, a new state out; nothing is kept
between calls, so the service can store the state (``to_dict``), load it and
continue, with bit-identical results.
"""

from __future__ import annotations

from dataclasses import replace
from typing import Iterable

from core.errors import InvalidInput
from core.measurements import toa_spacing_s
from core.tracking import joint_ukf, velocity_kinematic
from core.tracking.config import Epoch, TimeNotIncreasing, TrackerConfig, validate_epoch
from core.tracking.kinematic import C, kinematic_prior
from core.tracking.state import TrackState, frozen_array

_ADVANCE = {
    "velocity_kinematic": velocity_kinematic.advance,
    "joint_ukf": joint_ukf.advance,
}


def new_state(config: TrackerConfig) -> TrackState:
    """The state of a session before any epoch.

    Parameters
    ----------
    config : TrackerConfig

    Returns
    -------
    TrackState
        Not initialised; holds the step-1 prior (velocity and, for an unknown
        period, the period error).
    """
    if not isinstance(config, TrackerConfig):
        raise InvalidInput("config must be a TrackerConfig")
    mean, cov = kinematic_prior(config)
    return TrackState(config.model, "velocity", 0, None, None, config.period_s, frozen_array(mean),
                      frozen_array(cov))


def step(state: TrackState, epoch: Epoch, config: TrackerConfig) -> TrackState:
    """Apply one epoch.

    Parameters
    ----------
    state : TrackState
        From :func:`new_state`, a previous :func:`step` or ``TrackState.from_dict``.
    epoch : Epoch
        Its ``time_s`` must be after ``state.time_s``; any number of missed
        epochs may lie between (the interval and the pulse count are measured).
    config : TrackerConfig
        The session's configuration (the one the state was made with).

    Returns
    -------
    TrackState
        ``warnings`` holds what this epoch raised.

    Raises
    ------
    InvalidInput
        On a non-finite or out-of-domain epoch value, or a state that does not
        belong to ``config``.
    TimeNotIncreasing
        When ``epoch.time_s`` is not after ``state.time_s`` (an ``InvalidInput``).
    """
    values = validate_epoch(epoch)
    _check_state(state, config)
    if state.time_s is not None and not values[0] > state.time_s:
        raise TimeNotIncreasing(f"epoch time_s {values[0]!r} is not after the last applied {state.time_s!r}",
                                ("time_s",))
    advanced = _ADVANCE[config.model](state, values, config)
    spacing_s = float(toa_spacing_s(values[4]))
    if spacing_s > config.sigma_toa_s:
        advanced = replace(advanced, warnings=advanced.warnings + ((
            "toa_resolution",
            f"toa_s {values[4]:.3g} s: float64 carries it to {spacing_s:.1e} s ({spacing_s * C:.2g} m), coarser than "
            f"sigma_toa_s {config.sigma_toa_s:.1e} s, so the TOA differences are no better than that; send toa_s "
            "relative to a recent reference (say, seconds since the session began)"),))
    return advanced


def step_many(state: TrackState, epochs: Iterable[Epoch], config: TrackerConfig) -> TrackState:
    """Apply epochs in order; the result's ``warnings`` gather the batch's (first message per code).

    Raises
    ------
    InvalidInput
        As :func:`step`, for the first bad epoch; nothing of the batch is
        applied then (the caller still holds the input state).
    """
    gathered: dict[str, tuple[str, int]] = {}
    for epoch in epochs:
        state = step(state, epoch, config)
        for code, message in state.warnings:
            first, count = gathered.get(code, (message, 0))
            gathered[code] = (first, count + 1)
    warnings = tuple((code, message if count == 1 else f"{message} (and {count - 1} more epochs)")
                     for code, (message, count) in gathered.items())
    return replace(state, warnings=warnings)


def _check_state(state: TrackState, config: TrackerConfig) -> None:
    if not isinstance(state, TrackState):
        raise InvalidInput("state must be a TrackState")
    if state.model != config.model:
        raise InvalidInput(f"state of model {state.model!r} cannot be stepped as {config.model!r}", ("model",))
    k = 4 if config.period_known else 5
    if state.stage == "velocity":
        expected = k
    elif config.model == "velocity_kinematic":
        expected = 6 + k
    else:
        expected = 3 + k
    if state.mean.shape != (expected,):
        raise InvalidInput("state does not match the config (period_known or model)", ("period_known",))
    if (state.time_s is None) != (state.toa_s is None):
        raise InvalidInput("state time_s and toa_s must both be set or both be null", ("time_s",))
