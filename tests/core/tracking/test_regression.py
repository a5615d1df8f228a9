"""The session filters give the numbers of the frozen reference implementation (``reference/``) to 1e-12.

The hot path of ``core.tracking`` was rewritten for speed (scalar arithmetic, fewer numpy calls); the
filter itself was not meant to change. Both implementations run here, in the same test run, on fixed
scenarios that visit every branch of a step (start, bootstrap, tracking, range unobservable, missed
epochs, a TOA off by half a period, a turn to near-radial flight, a covariance repair), and every state
must agree:

- stage, update count and warning codes exactly;
- each mean component to ``TOLERANCE * (|x_i| + sigma_i)``, each covariance entry to
  ``TOLERANCE * sigma_i sigma_j`` (i.e. the correlation matrix to ``TOLERANCE`` absolute), the period
  and the range pseudo-measurement to ``TOLERANCE`` relative.

The tolerance is set by rounding alone: a different but equivalent order of floating-point operations
moves the results by ~1e-15 relative per step, and a Kalman filter does not amplify that.
"""

from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest

from core.simulation.emitter import paper_001_scenario, simulate_emitter
from core.tracking import TrackState, step
from core.tracking import new_state as new_state_now
from tests.core.tracking.reference.session import new_state as new_state_then
from tests.core.tracking.reference.session import step as step_then
from tests.core.tracking.scenarios import paper_config

TOLERANCE = 1e-12


def deviation(now: TrackState, then: TrackState) -> float:
    """Largest normalised difference between two states of the same layout (see the module docstring)."""
    assert (now.model, now.stage, now.updates, now.time_s, now.toa_s) == (
        then.model, then.stage, then.updates, then.time_s, then.toa_s)
    assert [code for code, _ in now.warnings] == [code for code, _ in then.warnings]
    assert now.mean.shape == then.mean.shape and now.covariance.shape == then.covariance.shape
    assert (now.last_range_measurement_m is None) == (then.last_range_measurement_m is None)
    sigma = np.sqrt(np.diag(then.covariance))
    worst = [
        float(np.max(np.abs(now.mean - then.mean) / (np.abs(then.mean) + sigma))),
        float(np.max(np.abs(now.covariance - then.covariance) / np.outer(sigma, sigma))),
        abs(now.pulse_period_s - then.pulse_period_s) / then.pulse_period_s,
    ]
    if then.last_range_measurement_m is not None:
        worst.append(abs(now.last_range_measurement_m / then.last_range_measurement_m - 1.0))
    return max(worst)


def run_both(config, epochs, tamper=None) -> tuple[float, set]:
    """Step both implementations through ``epochs``; the largest deviation and the warning codes seen.

    ``tamper(i, state)`` may replace the state before epoch ``i`` (applied to both, from the reference's
    state, so that both continue from one input)."""
    now, then = new_state_now(config), new_state_then(config)
    assert deviation(now, then) == 0.0
    worst = 0.0
    codes = set()
    for i, epoch in enumerate(epochs):
        if tamper is not None:
            changed = tamper(i, then)
            if changed is not None:
                now = then = changed
        now, then = step(now, epoch, config), step_then(then, epoch, config)
        worst = max(worst, deviation(now, then))
        codes |= {code for code, _ in then.warnings}
    return worst, codes


CONFIGS = [
    ("velocity_kinematic", True, {}),
    ("velocity_kinematic", False, {}),
    ("velocity_kinematic", True, {"pseudo_range_errors": "independent"}),
    ("velocity_kinematic", False, {"pseudo_range_errors": "independent"}),
    ("joint_ukf", True, {}),
    ("joint_ukf", False, {}),
]


def config_id(case) -> str:
    model, known, extra = case
    return f"{model}-{'known' if known else 'unknown'}" + "".join(f"-{v}" for v in extra.values())


@pytest.mark.parametrize("case", CONFIGS, ids=config_id)
@pytest.mark.parametrize("seed", [1000, 1001, 1002])
def test_paper_scenario_equals_the_reference(case, seed):
    model, known, extra = case
    config = paper_config(model, known, **extra)
    epochs = simulate_emitter(paper_001_scenario(), np.random.default_rng(seed)).epochs
    worst, codes = run_both(config, epochs)
    assert worst <= TOLERANCE


@pytest.mark.parametrize("case", CONFIGS, ids=config_id)
def test_gaps_bad_toa_and_a_turn_to_near_radial_equal_the_reference(case):
    """Missed epochs (a 13 s gap), TOAs off by half a period before and after initialisation, then a turn
    onto a line 1 degree off the line of sight (range unobservable)."""
    model, known, extra = case
    config = paper_config(model, known, **extra)
    p = np.array(paper_001_scenario().initial_position_enu_m) + 119.0 * np.array((-300.0, 100.0, 2.0))
    inward = -p / np.linalg.norm(p)
    off = np.cross(inward, (0.0, 0.0, 1.0))
    velocity = 300.0 * (np.cos(np.radians(1.0)) * inward + np.sin(np.radians(1.0)) * off / np.linalg.norm(off))
    scenario = paper_001_scenario(epochs=181, turn_epoch=120, velocity_after_turn_enu_mps=tuple(velocity),
                                  missed_epochs=tuple(range(70, 82)) + (100, 101))
    epochs = list(simulate_emitter(scenario, np.random.default_rng(77)).epochs)
    for i in (8, 90):
        epochs[i] = replace(epochs[i], toa_s=epochs[i].toa_s + 0.5 * config.period_s)
    worst, codes = run_both(config, epochs)
    assert worst <= TOLERANCE
    assert {"pulse_count_ambiguous", "range_unobservable"} <= codes


@pytest.mark.parametrize("case", CONFIGS, ids=config_id)
def test_a_covariance_repair_equals_the_reference(case):
    """A velocity correlation beyond 1 is planted in the state at epoch 50; both repair it alike."""
    model, known, extra = case
    config = paper_config(model, known, **extra)
    epochs = simulate_emitter(paper_001_scenario(epochs=90), np.random.default_rng(7)).epochs

    def tamper(i, state):
        if i != 50:
            return None
        assert state.initialized
        broken = state.covariance.copy()
        broken[3, 4] = broken[4, 3] = 2.0 * np.sqrt(broken[3, 3] * broken[4, 4])
        return replace(state, covariance=broken)

    worst, codes = run_both(config, epochs, tamper)
    assert worst <= TOLERANCE
    assert "covariance_repaired" in codes
