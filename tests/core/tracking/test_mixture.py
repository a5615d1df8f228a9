"""The range-parameterised Gaussian-sum start of the joint UKF: its algebra and its stages."""

from __future__ import annotations

import json
import math

import numpy as np
import pytest

from core.errors import InvalidInput
from core.simulation.emitter import paper_001_scenario, simulate_emitter
from core.tracking import TrackState, new_state, step
from core.tracking.joint_ukf import joint_epoch, joint_epochs, pulse_count
from core.tracking.range_mixture import RANGE_RATIO, component_ranges, moments, relative_sigma
from core.simulation.tracking import paper_config


def test_moments_equal_those_of_samples_from_the_sum():
    rng = np.random.default_rng(1)
    weights = np.array([0.2, 0.5, 0.3])
    means = rng.normal(size=(3, 2)) * 3.0
    covariances = np.array([(a := rng.normal(size=(2, 2))) @ a.T + 0.1 * np.eye(2) for _ in range(3)])
    mean, cov = moments(weights, means, covariances)
    picks = rng.choice(3, size=400_000, p=weights)
    chol = np.linalg.cholesky(covariances)
    samples = means[picks] + np.einsum("nij,nj->ni", chol[picks], rng.standard_normal((picks.size, 2)))
    np.testing.assert_allclose(mean, samples.mean(axis=0), atol=0.02)
    np.testing.assert_allclose(cov, np.cov(samples.T), rtol=0.02, atol=0.02)


def test_component_intervals_tile_the_range_interval():
    config = paper_config("joint_ukf", True)
    middles, sigmas = component_ranges(config)
    ratio = middles[1] / middles[0]
    assert ratio <= RANGE_RATIO
    np.testing.assert_allclose(middles[0] / math.sqrt(ratio), config.range_min_m, rtol=1e-12)
    np.testing.assert_allclose(middles[-1] * math.sqrt(ratio), config.range_max_m, rtol=1e-12)
    np.testing.assert_allclose(middles[1:] / middles[:-1], ratio, rtol=1e-12)
    uniform = np.random.default_rng(2).uniform(middles[3] / math.sqrt(ratio), middles[3] * math.sqrt(ratio), 200_000)
    assert sigmas[3] == pytest.approx(uniform.std(), rel=0.01)
    assert relative_sigma(1.0) == 0.0


def test_one_component_is_the_direct_joint_ukf_with_that_range_prior():
    """A range interval of ratio at most RANGE_RATIO gives one component: the sum collapses at the second epoch and
    the filter is then the direct joint UKF started from the interval's middle and its sigma."""
    middle, ratio = 150e3, 1.4
    mixture = paper_config("joint_ukf", False, range_min_m=middle / math.sqrt(ratio),
                           range_max_m=middle * math.sqrt(ratio))
    direct = paper_config("joint_ukf", False, joint_initial_range="prior", range_prior_m=middle,
                          range_prior_sigma_m=middle * relative_sigma(ratio))
    track = simulate_emitter(paper_001_scenario(epochs=30), np.random.default_rng(3))
    a, b = new_state(mixture), new_state(direct)
    for i, epoch in enumerate(track.epochs):
        a, b = step(a, epoch, mixture), step(b, epoch, direct)
        assert a.stage == ("mixture" if i == 0 else "tracking")
        np.testing.assert_allclose(a.mean, b.mean, rtol=1e-12, atol=1e-9)
        np.testing.assert_allclose(a.covariance, b.covariance, rtol=1e-10, atol=1e-12)
        assert a.pulse_period_s == pytest.approx(b.pulse_period_s, rel=1e-15)


@pytest.mark.parametrize("period_known", [True, False])
def test_the_sum_collapses_to_one_filter_and_round_trips_at_every_epoch(period_known):
    config = paper_config("joint_ukf", period_known, accel_sigma_mps2=0.05)
    track = simulate_emitter(paper_001_scenario(epochs=120, accel_sigma_mps2=0.05), np.random.default_rng(4))
    state = new_state(config)
    counts = []
    for epoch in track.epochs:
        state = step(state, epoch, config)
        again = TrackState.from_dict(json.loads(json.dumps(state.to_dict(), allow_nan=False)))
        assert again == state
        if state.stage == "mixture":
            parts = state.components
            counts.append(parts.weights.size)
            assert parts.weights.sum() == pytest.approx(1.0, abs=1e-12)
            mean, cov = moments(parts.weights, parts.means, parts.covariances)
            np.testing.assert_array_equal(state.mean, mean)
            assert np.all(np.linalg.eigvalsh(parts.covariances) > 0.0)
        else:
            assert state.components is None and "components" not in state.to_dict()
    assert counts[0] == component_ranges(config)[0].size
    assert counts == sorted(counts, reverse=True)
    assert state.stage == "tracking"
    assert abs(state.range_m - track.ranges_m[-1]) < 4.0 * state.range_sigma_m


def test_a_stored_state_refuses_components_outside_the_mixture_stage():
    config = paper_config("joint_ukf", True)
    track = simulate_emitter(paper_001_scenario(epochs=2), np.random.default_rng(5))
    state = step(new_state(config), track.epochs[0], config)
    data = state.to_dict()
    assert data["stage"] == "mixture"
    with pytest.raises(InvalidInput):
        TrackState.from_dict({**data, "stage": "tracking"})
    broken = json.loads(json.dumps(data))
    broken["components"]["weights"][0] = -1.0
    with pytest.raises(InvalidInput):
        TrackState.from_dict(broken)


@pytest.mark.parametrize("period_known", [True, False])
@pytest.mark.parametrize("use_toa", [True, False])
def test_the_batched_update_equals_one_joint_epoch_per_component(period_known, use_toa):
    """joint_epochs (what the mixture and the IMM run) against joint_epoch on each component alone, with
    each component's own acceleration level, with and without a usable TOA."""
    config = paper_config("joint_ukf", period_known, accel_sigma_mps2=0.05, imm_accel_sigmas_mps2=(0.05, 1.0))
    track = simulate_emitter(paper_001_scenario(epochs=8, accel_sigma_mps2=0.05), np.random.default_rng(1))
    state = new_state(config)
    for epoch in track.epochs[:6]:
        state = step(state, epoch, config)
    epoch, parts = track.epochs[6], state.components
    dt, dtoa = epoch.time_s - state.time_s, epoch.toa_s - state.toa_s
    merged = state.mean.tolist()
    predicted = [merged[i] + dt * merged[i + 3] for i in range(3)] + merged[3:]
    count = pulse_count(predicted, state.pulse_period_s, dt, dtoa) if use_toa else (1000, False, ())
    assert count[1] == use_toa
    levels = [0.05, 1.0] * (parts.weights.size // 2)
    measured = (epoch.azimuth_rad, epoch.elevation_rad, epoch.azimuth_rate_rad_s)
    batch = joint_epochs(parts.means, parts.covariances, levels, state.pulse_period_s, dt, dtoa, *measured, config,
                         count)
    for i, (mean, cov) in enumerate(zip(parts.means.tolist(), parts.covariances)):
        one = joint_epoch(mean, cov, state.pulse_period_s, dt, dtoa, *measured, config, count, fold_period=False,
                          accel_sigma_mps2=levels[i])
        scale = np.sqrt(np.diag(one.cov))
        np.testing.assert_allclose(batch.means[i] / scale, np.array(one.mean) / scale, rtol=0, atol=1e-12)
        np.testing.assert_allclose(batch.covariances[i] / np.outer(scale, scale), one.cov / np.outer(scale, scale),
                                   rtol=0, atol=1e-12)
        assert batch.log_likelihoods[i] == pytest.approx(one.log_likelihood, rel=1e-12, abs=1e-12)
        assert batch.warnings[i] == one.warnings
