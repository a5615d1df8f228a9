"""The network tracker: reports in any order, exact TOA elimination, honest starts, round trips, long runs."""

from __future__ import annotations

import json
import math

import numpy as np
import pytest
from scipy.stats import chi2

from core.errors import InvalidInput
from core.measurements import AZIMUTH, ELEVATION, RANGE, TOA, Kind, predict
from core.problem.frame import LocalPoint
from core.problem.build import TimeOfArrival, Bearing, build_problem
from core.crlb import information_at
from core.parallel import Stopped
from core.simulation.network import (START_TIME_S, df_network_scene, evaluate_network, simulate_network,
                                     station_frame, toa_network_scene)
from core.tracking.network import (NetworkConfig, NetworkState, Report, apply_reports, new_network_state,
                                   predict_tracks, validate_report)
from core.tracking.network_bound import network_pcrb


def _apply_each(reports, config, state=None):
    state = state or new_network_state(config)
    late = 0
    for report in reports:
        outcome = apply_reports(state, [report], config)
        state, late = outcome.state, late + outcome.late
    return state, late


def _bearing_report(seq, time_s, station_enu_m, target_enu_m, rng, sigma_rad=math.radians(1.0), emitter="e1"):
    stations = np.array([station_enu_m, station_enu_m], dtype=float)
    rotations = np.tile(np.eye(3), (2, 1, 1))
    kinds = np.array([AZIMUTH, ELEVATION])
    exact, _ = predict(np.asarray(target_enu_m, dtype=float), 0.0, stations, rotations, kinds)
    values = exact + (rng.normal(0.0, sigma_rad, 2) if rng is not None else 0.0)
    return Report(seq, time_s, emitter, ("s", "s"), stations, rotations, kinds, values, [sigma_rad] * 2)


# ---------------------------------------------------------------------------------------------------------------
# Reports in any order


def test_late_reports_give_the_time_ordered_answer_bit_for_bit():
    scene = df_network_scene()
    run = simulate_network(scene, np.random.default_rng(7))
    posted = [p.report for p in run.posted]
    out_of_order = sum(1 for a, b in zip(posted, posted[1:]) if b.time_s < a.time_s)
    assert out_of_order > 20  # the scene does post late
    arrived, late = _apply_each(posted, scene.config)
    in_time, _ = _apply_each(sorted(posted, key=lambda r: r.order_key), scene.config)
    assert late == 0
    assert arrived.to_dict() == in_time.to_dict()
    assert arrived.tracks[0].mean_enu.tobytes() == in_time.tracks[0].mean_enu.tobytes()


def test_one_batch_in_any_order_equals_the_reports_in_time_order():
    scene = df_network_scene()
    run = simulate_network(scene, np.random.default_rng(8))
    reports = sorted((p.report for p in run.posted), key=lambda r: r.order_key)
    head, window = reports[:40], reports[40:46]  # six reports within 1.5 s
    state, _ = _apply_each(head, scene.config)
    shuffled = [window[i] for i in (3, 0, 5, 1, 4, 2)]
    outcome = apply_reports(state, shuffled, scene.config)
    expected, _ = _apply_each(window, scene.config, state)
    assert outcome.applied == 6 and outcome.late == 0
    assert outcome.state.to_dict() == expected.to_dict()


def test_a_report_older_than_the_window_is_counted_late_and_not_applied():
    config = NetworkConfig(reorder_window_s=2.0)
    rng = np.random.default_rng(1)
    station, target = (0.0, 0.0, 0.0), (10e3, 10e3, 0.0)
    state, _ = _apply_each([_bearing_report(k, START_TIME_S + k, station, target, rng) for k in range(5)], config)
    old = _bearing_report(9, START_TIME_S + 4 - 2.5, station, target, rng)
    outcome = apply_reports(state, [old], config)
    assert (outcome.applied, outcome.late) == (0, 1)
    assert outcome.state.to_dict() == state.to_dict()
    assert [code for code, _ in outcome.warnings] == ["late_report"]


def test_state_round_trips_through_json_and_continues_identically():
    scene = df_network_scene()
    run = simulate_network(scene, np.random.default_rng(9))
    reports = [p.report for p in run.posted]
    state, _ = _apply_each(reports[:100], scene.config)
    reloaded = NetworkState.from_dict(json.loads(json.dumps(state.to_dict())))
    assert reloaded == state
    a, _ = _apply_each(reports[100:140], scene.config, state)
    b, _ = _apply_each(reports[100:140], scene.config, reloaded)
    assert a.to_dict() == b.to_dict()


def test_state_json_keeps_every_tracks_moments_bit_for_bit():
    # A one-component track's stored form leaves its moments out (they are its component); a range mixture's
    # keeps them. Tracks and reports must come back exactly, array by array.
    scene = df_network_scene()
    reports = [p.report for p in simulate_network(scene, np.random.default_rng(9)).posted]
    stages = set()
    for count in (1, 3, 60):
        state, _ = _apply_each(reports[:count], scene.config)
        reloaded = NetworkState.from_dict(json.loads(json.dumps(state.to_dict())))
        pairs = list(zip(state.tracks + state.checkpoint, reloaded.tracks + reloaded.checkpoint))
        pairs += [(e.track, f.track) for e, f in zip(state.history, reloaded.history)]
        assert pairs
        for before, after in pairs:
            stages.add(before.stage)
            for name in ("mean_enu", "covariance_enu", "weights", "means", "covariances"):
                assert getattr(after, name).tobytes() == getattr(before, name).tobytes(), name
                assert getattr(after, name).shape == getattr(before, name).shape, name
                assert not getattr(after, name).flags.writeable
        for e, f in zip(state.history, reloaded.history):
            assert f.report.station_ids == e.report.station_ids
            for name in ("stations_enu_m", "rotations", "kinds", "values", "sigmas"):
                assert getattr(f.report, name).tobytes() == getattr(e.report, name).tobytes(), name
                assert getattr(f.report, name).shape == getattr(e.report, name).shape, name
    assert {"mixture", "single"} <= stages


# ---------------------------------------------------------------------------------------------------------------
# TOA groups


def _toa_run(offset_s=0.0):
    scene = toa_network_scene()
    run = simulate_network(scene, np.random.default_rng(3))
    reports = [p.report for p in run.posted]
    if offset_s:
        reports = [Report(r.seq, r.time_s, r.emitter_id, r.station_ids, r.stations_enu_m, r.rotations, r.kinds,
                          r.values + offset_s, r.sigmas) for r in reports]
    return scene, reports


def test_the_four_station_toa_scene_leaves_out_the_middle_station():
    assert [s.id for s in toa_network_scene(station_count=4).stations] == ["toa-a", "toa-b", "toa-c", "toa-d"]
    assert len(toa_network_scene(2).stations) == 5
    with pytest.raises(ValueError):
        toa_network_scene(station_count=3)


def test_an_evaluation_stops_between_trials_when_asked():
    asked = []

    def should_stop():
        asked.append(True)
        return len(asked) > 2

    with pytest.raises(Stopped):
        evaluate_network(toa_network_scene(duration_s=5.0), 10, should_stop=should_stop)
    assert len(asked) == 3  # two trials ran; the third was not started


def test_toa_elimination_ignores_the_clock_epoch():
    scene, reports = _toa_run()
    # At 1e6 s float64 carries TOAs to 1.2e-10 s (3.5 cm), far below the 20-50 ns sigmas: the shifted TOAs
    # differ from the originals by that rounding alone, and the track by as little.
    _, shifted = _toa_run(offset_s=1.0e6)
    a, _ = _apply_each(reports[:30], scene.config)
    b, _ = _apply_each(shifted[:30], scene.config)
    np.testing.assert_allclose(b.tracks[0].mean_enu[:3], a.tracks[0].mean_enu[:3], rtol=0, atol=0.05)
    np.testing.assert_allclose(b.tracks[0].covariance_enu, a.tracks[0].covariance_enu, rtol=1e-4)  # points about a mean mm away


def test_toa_elimination_does_not_depend_on_the_reference():
    """Any TOA may be the reference of the differences: the marginal over the emission time is the same."""
    scene, reports = _toa_run()
    state, _ = _apply_each(reports[:10], scene.config)
    report = reports[10]
    sigmas = np.full(report.kinds.size, 30e-9)  # equal sigmas: the first TOA listed is the reference

    def listed(order):
        return Report(report.seq, report.time_s, report.emitter_id, tuple(np.array(report.station_ids)[order]),
                      report.stations_enu_m[order], report.rotations[order], report.kinds[order],
                      report.values[order], sigmas[order])

    a = apply_reports(state, [listed(np.arange(5))], scene.config).state.tracks[0]
    b = apply_reports(state, [listed(np.array([3, 1, 4, 0, 2]))], scene.config).state.tracks[0]
    np.testing.assert_allclose(b.mean_enu, a.mean_enu, rtol=0, atol=1e-6)
    np.testing.assert_allclose(b.covariance_enu, a.covariance_enu, rtol=1e-8, atol=1e-12)


def test_a_lone_toa_is_reported_and_not_used():
    config = NetworkConfig()
    rng = np.random.default_rng(2)
    station, target = np.zeros(3), np.array([10e3, 10e3, 0.0])
    first = _bearing_report(0, START_TIME_S, station, target, rng)
    state = apply_reports(new_network_state(config), [first], config).state
    bearing = _bearing_report(1, START_TIME_S + 1, station, target, rng)
    with_toa = Report(1, bearing.time_s, "e1", ("s", "s", "t"), np.vstack([bearing.stations_enu_m, [5e3, 0, 0]]),
                      np.concatenate([bearing.rotations, np.eye(3)[None]]), [AZIMUTH, ELEVATION, TOA],
                      np.append(bearing.values, 1234.5), np.append(bearing.sigmas, 20e-9))
    outcome = apply_reports(state, [with_toa], config)
    plain = apply_reports(state, [bearing], config)
    assert "toa_single" in [code for code, _ in outcome.warnings]
    assert outcome.state.tracks[0].mean_enu.tobytes() == plain.state.tracks[0].mean_enu.tobytes()


# ---------------------------------------------------------------------------------------------------------------
# The bound


def test_pcrb_of_a_still_target_is_the_static_crlb_with_the_emission_time_marginalised():
    """With no process noise and a still target known to be still, the bound after one report of bearings and
    TOAs is the fix's CRLB (core.crlb), which marginalises the emission time its own way."""
    stations = np.array([[0.0, 0.0, 0.0], [20e3, 0.0, 100.0], [0.0, 25e3, 50.0], [22e3, 24e3, 0.0]])
    target = np.array([9e3, 11e3, 3e3])
    ids = ("a", "b", "c", "d")
    kinds = [TOA, TOA, TOA, TOA, AZIMUTH, ELEVATION]
    rows = [0, 1, 2, 3, 0, 0]
    sigmas = [20e-9, 30e-9, 40e-9, 50e-9, 0.01, 0.02]
    report = Report(0, 0.0, "e1", tuple(ids[i] for i in rows), stations[rows], np.tile(np.eye(3), (6, 1, 1)), kinds,
                    np.zeros(6), sigmas)
    bound = network_pcrb(np.append(target, [0.0, 0.0, 0.0])[None], [report], 1e-12, 1e-9)
    exact, _ = predict(target, 0.0, stations[rows], np.tile(np.eye(3), (6, 1, 1)), np.array(kinds))
    measurements = [TimeOfArrival(ids[i], float(exact[i] / 299_792_458.0), sigmas[i]) for i in range(4)]
    measurements.append(Bearing("a", float(exact[4]), float(exact[5]), sigmas[4], sigmas[5]))
    problem = build_problem([(i, LocalPoint(*p)) for i, p in zip(ids, stations.tolist())], measurements)
    crlb = information_at(problem, target).covariance_enu_m2
    np.testing.assert_allclose(bound.covariance[0, :3, :3], crlb[0], rtol=1e-6)


# ---------------------------------------------------------------------------------------------------------------
# Starting honestly


def test_a_single_fixed_bearing_station_stays_tentative_and_honest():
    """One fixed direction finder watching a vehicle: the range is not observable; the track must say so."""
    config = NetworkConfig(accel_sigma_mps2=0.2, velocity_prior_sigma_mps=30.0)
    trials, steps = 60, 30
    nees = []
    for r in range(trials):
        rng = np.random.default_rng(500 + r)
        start = np.array([rng.uniform(-5e3, 5e3), rng.uniform(15e3, 25e3), 0.0])
        velocity = np.array([rng.uniform(-20, 20), rng.uniform(-20, 20), 0.0])
        reports = [_bearing_report(k, START_TIME_S + k, (0.0, 0.0, 600.0), start + k * velocity, rng)
                   for k in range(steps)]
        state, _ = _apply_each(reports, config)
        track = state.tracks[0]
        assert track.status == "tentative"
        error = track.mean_enu[:3] - (start + (steps - 1) * velocity)
        cov = track.covariance_enu[:3, :3]
        nees.append(float(error @ np.linalg.solve(cov, error)))
        range_m = float(np.linalg.norm(start))
        assert math.sqrt(np.linalg.eigvalsh(cov)[-1]) > 0.2 * range_m  # it does not claim to know the range
    assert np.mean(nees) <= chi2.ppf(0.995, 3 * trials) / trials  # not overconfident


def test_confirmed_once_the_network_places_it_then_coasting_then_ended():
    config = NetworkConfig(accel_sigma_mps2=0.2, velocity_prior_sigma_mps=30.0, coast_after_s=5.0,
                           end_after_s=20.0)
    rng = np.random.default_rng(4)
    stations = [(0.0, 0.0, 0.0), (30e3, 0.0, 0.0), (0.0, 30e3, 0.0)]
    target = np.array([12e3, 14e3, 0.0])
    reports = [_bearing_report(3 * k + s, START_TIME_S + k + 0.3 * s, stations[s], target, rng)
               for k in range(6) for s in range(3)]
    state, _ = _apply_each(reports, config)
    assert state.tracks[0].status == "confirmed"
    assert predict_tracks(state, START_TIME_S + 12.0, config)[0].status == "coasting"
    other = _bearing_report(99, START_TIME_S + 30.0, (0.0, 0.0, 0.0), (5e3, 5e3, 0.0), rng, emitter="e2")
    later = apply_reports(state, [other], config).state
    assert [t.id for t in later.tracks] == ["e2"]  # e1 has ended


def test_predict_tracks_moves_with_the_velocity():
    scene = df_network_scene()
    run = simulate_network(scene, np.random.default_rng(5))
    state, _ = _apply_each(sorted((p.report for p in run.posted[:200]), key=lambda r: r.order_key), scene.config)
    track = state.tracks[0]
    ahead = predict_tracks(state, track.time_s + 10.0, scene.config)[0]
    np.testing.assert_allclose(ahead.mean_enu[:3], track.mean_enu[:3] + 10.0 * track.mean_enu[3:], rtol=1e-9)
    assert np.trace(ahead.covariance_enu) > np.trace(track.covariance_enu)


# ---------------------------------------------------------------------------------------------------------------
# Input and long runs


@pytest.mark.parametrize("change, loc", [
    ({"time_s": math.nan}, ("time_s",)),
    ({"values": [math.inf, 0.1]}, ("measurements", 0, "value")),
    ({"sigmas": [0.01, 0.0]}, ("measurements", 1, "sigma")),
    ({"values": [0.1, 2.0]}, ("measurements", 1, "value")),
    ({"kinds": [AZIMUTH, 7]}, ("measurements", 1, "kind")),
])
def test_bad_reports_name_the_field(change, loc):
    fields = dict(seq=0, time_s=1.0, emitter_id="e1", station_ids=("s", "s"), stations_enu_m=np.zeros((2, 3)),
                  rotations=np.tile(np.eye(3), (2, 1, 1)), kinds=[AZIMUTH, ELEVATION], values=[0.1, 0.1],
                  sigmas=[0.01, 0.01])
    fields.update(change)
    report = Report(**fields)
    with pytest.raises(InvalidInput) as raised:
        validate_report(report)
    assert raised.value.loc == loc
    with pytest.raises(InvalidInput) as raised:
        apply_reports(new_network_state(NetworkConfig()), [report], NetworkConfig())
    assert raised.value.loc == (0,) + loc


def test_ten_thousand_reports_keep_the_covariance_symmetric_positive_definite():
    config = NetworkConfig(accel_sigma_mps2=0.5, velocity_prior_sigma_mps=30.0)
    rng = np.random.default_rng(6)
    stations = [(0.0, 0.0, 0.0), (30e3, 0.0, 0.0), (0.0, 30e3, 0.0), (30e3, 30e3, 0.0)]
    state = new_network_state(config)
    target, velocity = np.array([12e3, 14e3, 0.0]), np.array([10.0, -5.0, 0.0])
    for k in range(10_000):
        t = 0.25 * k
        position = target + velocity * t + 200.0 * np.array([math.sin(t / 300.0), math.cos(t / 200.0), 0.0])
        state = apply_reports(state, [_bearing_report(k, START_TIME_S + t, stations[k % 4], position, rng)],
                              config).state
        if k % 500 == 499:
            cov = state.tracks[0].covariance_enu
            assert np.array_equal(cov, cov.T)
            assert np.linalg.eigvalsh(cov)[0] > 0.0
    track = state.tracks[0]
    assert track.updates == 10_000 and track.status == "confirmed"
    for cov in track.covariances:
        assert np.array_equal(cov, cov.T)
        np.linalg.cholesky(cov)


def test_bearings_across_south_wrap_and_the_track_stays_consistent():
    """A station due north of the emitter sees it at azimuth +-pi: its bearings jump across the wrap and the
    update must treat them as the few milliradians they differ by."""
    config = NetworkConfig(accel_sigma_mps2=0.2, velocity_prior_sigma_mps=30.0)
    stations = [(0.0, 25e3, 0.0), (-20e3, -5e3, 0.0), (20e3, -5e3, 0.0)]
    errors = []
    for r in range(20):
        rng = np.random.default_rng(700 + r)
        velocity = np.array([8.0, 0.0, 0.0])  # crosses the north station's south line
        reports = []
        for k in range(90):
            position = np.array([-360.0, 0.0, 0.0]) + velocity * k
            reports.append(_bearing_report(k, START_TIME_S + k, stations[k % 3], position, rng))
        azimuths = [r.values[0] for r in reports[::3]]
        assert min(azimuths) < -3.0 and max(azimuths) > 3.0  # both sides of the wrap
        state, _ = _apply_each(reports, config)
        track = state.tracks[0]
        error = track.mean_enu[:3] - position
        errors.append(float(error @ np.linalg.solve(track.covariance_enu[:3, :3], error)))
    assert np.mean(errors) <= chi2.ppf(0.995, 3 * 20) / 20


def test_one_report_from_two_stations_places_the_emitter_honestly():
    """Bearings from two stations in one report: the start's sum along the first line of sight, updated with
    the second, must be as uncertain as it is wrong (NEES of the first estimate over 100 emitters)."""
    config = NetworkConfig(accel_sigma_mps2=0.2, velocity_prior_sigma_mps=30.0)
    stations = np.array([[0.0, 0.0, 0.0], [0.0, 0.0, 0.0], [30e3, 0.0, 0.0], [30e3, 0.0, 0.0]])
    rotations, kinds, sigma = np.tile(np.eye(3), (4, 1, 1)), np.array([AZIMUTH, ELEVATION] * 2), math.radians(1.0)
    nees = []
    for r in range(100):
        rng = np.random.default_rng(800 + r)
        target = np.array([rng.uniform(5e3, 25e3), rng.uniform(10e3, 30e3), 0.0])
        exact, _ = predict(target, 0.0, stations, rotations, kinds)
        report = Report(0, 0.0, "e1", ("a", "a", "b", "b"), stations, rotations, kinds,
                        exact + rng.normal(0.0, sigma, 4), [sigma] * 4)
        track = apply_reports(new_network_state(config), [report], config).state.tracks[0]
        error = track.mean_enu[:3] - target
        nees.append(float(error @ np.linalg.solve(track.covariance_enu[:3, :3], error)))
    lo, hi = chi2.ppf([0.005, 0.995], 3 * 100) / 100
    assert lo <= np.mean(nees) <= hi
