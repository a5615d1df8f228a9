"""The posterior CRLB of the session model against brute-force oracles."""

from __future__ import annotations

import math

import numpy as np
import pytest

from core.measurements import azimuth_rate
from core.simulation.emitter import paper_001_scenario, simulate_emitter
from core.tracking.bound import (C, information_predict, invert_information, measurement_weights, pcrb_recursion,
                                 prior_information, session_pcrb, session_transition)
from core.simulation.tracking import paper_config


def random_spd(rng, n, scale=1.0):
    a = rng.normal(size=(n, n))
    return scale * (a @ a.T + 0.1 * np.eye(n))


def batch_information(prior, transitions, noises, measurement_informations):
    """Information of the whole trajectory ``(x_0 .. x_(K-1))`` as one block-tridiagonal matrix."""
    k, n = measurement_informations.shape[:2]
    big = np.zeros((k * n, k * n))
    big[:n, :n] += prior
    for i in range(k):
        big[i * n:(i + 1) * n, i * n:(i + 1) * n] += measurement_informations[i]
    for i in range(k - 1):
        f, w = transitions[i], np.linalg.inv(noises[i])
        a, b = slice(i * n, (i + 1) * n), slice((i + 1) * n, (i + 2) * n)
        big[a, a] += f.T @ w @ f
        big[a, b] -= f.T @ w
        big[b, a] -= w @ f
        big[b, b] += w
    return big


def test_recursion_equals_the_inverse_of_the_batch_information_for_a_linear_gaussian_model():
    """For linear-Gaussian motion and measurements the PCRB is exact: the recursion's J_k^-1 equals the
    last block of the inverse of the joint information of x_0 .. x_k, at every k."""
    rng = np.random.default_rng(3)
    n, k = 4, 7
    prior = random_spd(rng, n)
    transitions = np.eye(n) + 0.3 * rng.normal(size=(k - 1, n, n))
    noises = np.array([random_spd(rng, n, 0.2) for _ in range(k - 1)])
    measurement = np.array([(h := rng.normal(size=(2, n))).T @ np.diag([2.0, 0.5]) @ h for _ in range(k)])
    got = pcrb_recursion(prior, transitions, noises, measurement)
    for last in range(1, k + 1):
        joint = np.linalg.inv(batch_information(prior, transitions[:last - 1], noises[:last - 1], measurement[:last]))
        np.testing.assert_allclose(np.linalg.inv(got[last - 1]), joint[-n:, -n:], rtol=1e-9, atol=1e-12)


def test_prediction_handles_a_singular_information_and_a_singular_noise():
    """(F J^-1 F^T + Q)^-1 by its limits: a diffuse component stays diffuse, a noise-free one keeps its
    information, and for invertible J and Q the formula is the plain one."""
    rng = np.random.default_rng(4)
    f = np.eye(3) + 0.2 * rng.normal(size=(3, 3))
    j, q = random_spd(rng, 3), random_spd(rng, 3, 0.5)
    np.testing.assert_allclose(information_predict(j, f, q), np.linalg.inv(f @ np.linalg.inv(j) @ f.T + q),
                               rtol=1e-10)
    np.testing.assert_allclose(information_predict(j, f, np.zeros((3, 3))),
                               np.linalg.inv(f).T @ j @ np.linalg.inv(f), rtol=1e-10)
    diffuse = np.diag([1.0, 2.0, 0.0])
    identity_motion = information_predict(diffuse, np.eye(3), np.diag([0.5, 0.0, 1.0]))
    np.testing.assert_allclose(identity_motion, np.diag([1.0 / 1.5, 2.0, 0.0]), atol=1e-15)


def measurements_from_initial_state(x0, times_s, n_pulses):
    """(azimuth, elevation, azimuth rate, b + r) per report of a constant-velocity emitter, written out
    from the initial state ``[p, v, b, (pe)]`` without the bound module's state recursion."""
    p0, v0, b0 = x0[:3], x0[3:6], x0[6]
    pe = x0[7] if x0.size == 8 else 0.0
    out = []
    for t, n in zip(times_s, n_pulses):
        p = p0 + t * v0
        rho = math.hypot(p[0], p[1])
        out += [math.atan2(p[0], p[1]), math.atan2(p[2], rho), (p[1] * v0[0] - p[0] * v0[1]) / rho**2,
                b0 + n * pe + float(np.linalg.norm(p))]
    return np.array(out)


@pytest.mark.parametrize("period_known", [True, False])
def test_without_process_noise_the_bound_is_the_fisher_information_of_the_initial_state(period_known):
    """q = 0: the emitter's motion is deterministic, so the PCRB at the last report is the prior plus the
    Fisher information of the initial state (Jacobian of all measurements by central differences), carried
    to the last report by the constant-velocity map, with a gap of 3 reports in the run."""
    config = paper_config("velocity_kinematic", period_known, accel_sigma_mps2=0.0)
    scenario = paper_001_scenario(epochs=40, missed_epochs=(20, 21, 22))
    track = simulate_emitter(scenario, np.random.default_rng(1))
    times = track.emission_times_s
    n_pulses = np.rint(times / scenario.period_s).astype(int)
    bound = session_pcrb(track.states_enu, times, config)

    x0 = np.r_[track.states_enu[0], 0.0, 0.0][: 7 if period_known else 8]
    steps = np.r_[1.0, 1.0, 1.0, 1e-3, 1e-3, 1e-3, 1.0, 1e-3][:x0.size]
    columns = []
    for i, h in enumerate(steps):
        up, down = x0.copy(), x0.copy()
        up[i] += h
        down[i] -= h
        columns.append((measurements_from_initial_state(up, times, n_pulses)
                        - measurements_from_initial_state(down, times, n_pulses)) / (2 * h))
    jacobian = np.array(columns).T
    weights = np.tile(measurement_weights(config), times.size)
    fisher = prior_information(config) + jacobian.T @ (weights[:, None] * jacobian)
    carry, _ = session_transition(config, float(times[-1]), int(n_pulses[-1]))
    inverse = np.linalg.inv(carry)
    want = inverse.T @ fisher @ inverse
    scale = 1.0 / np.sqrt(np.diag(want))
    np.testing.assert_allclose(bound.information[-1] * np.outer(scale, scale), want * np.outer(scale, scale),
                               rtol=0, atol=1e-6)
    np.testing.assert_allclose(bound.covariance[-1], np.linalg.inv(want), rtol=1e-5)


def test_azimuth_rate_jacobian_matches_finite_differences():
    state = np.array([120e3, 100e3, 8e3, -300.0, 100.0, 2.0])
    _, jacobian = azimuth_rate(state[:3], state[3:])
    steps = np.array([1.0, 1.0, 1.0, 1e-3, 1e-3, 1e-3])
    numeric = [(azimuth_rate((s := state + h * e)[:3], s[3:])[0] - azimuth_rate((s := state - h * e)[:3], s[3:])[0])
               / (2 * h) for h, e in zip(steps, np.eye(6))]
    np.testing.assert_allclose(jacobian, numeric, rtol=1e-7, atol=1e-16)


def test_expectation_is_the_mean_over_the_truths():
    """The bound over R truths uses the mean of their information; with R copies of one truth it equals
    the bound of that truth."""
    config = paper_config("velocity_kinematic", True)
    track = simulate_emitter(paper_001_scenario(epochs=30), np.random.default_rng(2))
    one = session_pcrb(track.states_enu, track.emission_times_s, config)
    copies = session_pcrb(np.stack([track.states_enu] * 3), track.emission_times_s, config)
    np.testing.assert_allclose(copies.information, one.information, rtol=1e-14)


@pytest.mark.parametrize("period_known", [True, False])
def test_each_truth_is_the_recursion_on_that_truth_alone_and_no_lower_than_the_pcrb(period_known):
    """Per truth, the bound is that of the truth passed alone; and the mean over truths of the trace of
    the position block is at least the PCRB's: the recursion gives a block of the inverse of the
    trajectory's information, which is affine in the averaged measurement information, and the inverse
    is operator-convex (``E[J^-1] >= E[J]^-1``)."""
    config = paper_config("velocity_kinematic", period_known, accel_sigma_mps2=1.0)
    scenario = paper_001_scenario(epochs=80, accel_sigma_mps2=1.0)
    tracks = [simulate_emitter(scenario, np.random.default_rng(s)) for s in range(4)]
    states, times = np.array([t.states_enu for t in tracks]), tracks[0].emission_times_s
    each = session_pcrb(states, times, config, each_truth=True)
    for run, truth in enumerate(states):
        alone = session_pcrb(truth, times, config)
        np.testing.assert_allclose(each.information[run], alone.information, rtol=1e-12)
        np.testing.assert_array_equal(np.isinf(each.position_rmse_m[run]), np.isinf(alone.position_rmse_m))
    pcrb = session_pcrb(states, times, config).position_rmse_m ** 2
    observed = np.isfinite(pcrb) & np.all(np.isfinite(each.position_rmse_m), axis=0)
    assert observed[20:].all()
    assert np.all(np.mean(each.position_rmse_m[:, observed] ** 2, axis=0) >= pcrb[observed] * (1 - 1e-4))  # rounding of the first, ill-conditioned informations


def test_the_pcrb_falls_with_the_process_noise_where_each_truths_own_bound_grows():
    """Why the PCRB is not attainable at q >= 1 m/s^2 on paper 001: the runs' lines of sight spread with q,
    and the averaged information gains range from the spread, so the bound falls from q = 0.5 on, while
    the bound of each truth alone, like any estimator's error, grows with q."""
    pcrb, own = [], []
    for q in (0.5, 1.0, 2.0):
        scenario = paper_001_scenario(accel_sigma_mps2=q)
        tracks = [simulate_emitter(scenario, np.random.default_rng(30000 + r)) for r in range(30)]
        states = np.array([t.states_enu for t in tracks])
        config = paper_config("joint_ukf", True, accel_sigma_mps2=q)
        pcrb.append(session_pcrb(states, tracks[0].emission_times_s, config).position_rmse_m[-1])
        each = session_pcrb(states, tracks[0].emission_times_s, config, each_truth=True).position_rmse_m[:, -1]
        own.append(np.sqrt(np.mean(each**2)))
    assert pcrb[0] > pcrb[1] > pcrb[2]
    assert own[0] < own[1] < own[2]
    assert own[2] > 5.0 * pcrb[2]


def test_paper_geometry_bound_after_200_s():
    """ALGORITHMS.md section 10 gives about 0.9 % of range at q = 0.05 and about 5 % at 0.5 after 200 s; a
    larger q forgets faster, so the bound is larger; an unknown period costs a little."""
    ends = {}
    for q in (0.05, 0.5):
        scenario = paper_001_scenario(accel_sigma_mps2=q)
        tracks = [simulate_emitter(scenario, np.random.default_rng(s)) for s in range(20)]
        states = np.array([t.states_enu for t in tracks])
        last_range = np.linalg.norm(states[:, -1, :3], axis=-1).mean()
        for known in (True, False):
            bound = session_pcrb(states, tracks[0].emission_times_s,
                                 paper_config("velocity_kinematic", known, accel_sigma_mps2=q))
            assert np.all(np.diff(bound.position_rmse_m[100:]) < 0.02 * bound.position_rmse_m[101:])
            ends[q, known] = 100.0 * bound.position_rmse_m[-1] / last_range
    assert 0.7 < ends[0.05, True] < 1.1
    assert 3.5 < ends[0.5, True] < 6.0
    assert ends[0.05, True] <= ends[0.05, False] and ends[0.5, True] <= ends[0.5, False]


def test_invert_information_marks_a_singular_information_as_nan():
    out = invert_information(np.array([np.diag([1.0, 4.0]), np.diag([1.0, 0.0])]))
    np.testing.assert_allclose(out[0], np.diag([1.0, 0.25]))
    assert np.isnan(out[1]).all()
    assert C == 299_792_458.0
