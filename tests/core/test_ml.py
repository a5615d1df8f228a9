"""Maximum likelihood: noise-free exactness in every frame, constraints, failure modes, warnings.

Noise-free measurements of geodetic scenarios are computed by pymap3d
(azimuth/elevation/slant range in each station's own ENU), not by the core's
models, and fixes are compared with the target in metres (ECEF distance).
"""

from __future__ import annotations

import numpy as np
import pymap3d
import pytest

from core.errors import LocalizationError, UnobservableGeometry
from core.estimators import SolveOptions, solve, solve_batch
from core.geodesy import ecef_to_enu_rotation
from core.measurements import SPEED_OF_LIGHT_MPS
from core.problem.build import Bearing, Range, TimeOfArrival, build_problem
from core.problem.frame import GeodeticPoint, LocalPoint
from core.simulation.measurements import measure

d2r = np.deg2rad
ONE_DEG = d2r(1.0)

# Stations up to ~450 km apart (300 km between neighbours): curvature matters.
STATIONS_DEG = {
    "w": (47.0, 7.0, 500.0), "e": (47.3, 11.0, 800.0), "s": (45.2, 9.0, 150.0),
    "n": (49.0, 9.5, 300.0), "c": (46.8, 8.6, 1200.0),
}
TARGET_DEG = (46.4, 9.2, 9000.0)
LOCAL_ORIGIN_DEG = (46.0, 8.0, 0.0)


def geodetic_stations(ids):
    return [(k, GeodeticPoint(d2r(STATIONS_DEG[k][0]), d2r(STATIONS_DEG[k][1]), STATIONS_DEG[k][2])) for k in ids]


def local_stations(ids, origin_deg=LOCAL_ORIGIN_DEG):
    return [(k, LocalPoint(*pymap3d.geodetic2enu(*STATIONS_DEG[k], *origin_deg))) for k in ids]


def aer(k, target=TARGET_DEG):
    """pymap3d's azimuth (deg), elevation (deg) and slant range (m) of the target at station k."""
    return pymap3d.geodetic2aer(*target, *STATIONS_DEG[k])


def bearings(ids, elevation=True):
    out = []
    for k in ids:
        az, el, _ = aer(k)
        out.append(Bearing(k, d2r(az), d2r(el) if elevation else None, ONE_DEG, ONE_DEG if elevation else None))
    return out


def bearings_and_ranges(ids):
    out = []
    for k in ids:
        az, el, r = aer(k)
        out += [Bearing(k, d2r(az), d2r(el), ONE_DEG, ONE_DEG), Range(k, r, 100.0)]
    return out


def toas(ids, emission_s=12.0):
    return [TimeOfArrival(k, emission_s + aer(k)[2] / SPEED_OF_LIGHT_MPS, 1e-8) for k in ids]


def geodetic_error_m(problem, fix, target_deg=TARGET_DEG):
    """Distance (m) from the fix, converted back to geodetic by the core, to the true target (pymap3d ECEF)."""
    lat, lon, alt = problem.frame.to_geodetic(fix.position_enu_m)
    got = pymap3d.geodetic2ecef(np.rad2deg(lat), np.rad2deg(lon), alt)
    return float(np.linalg.norm(np.subtract(got, pymap3d.geodetic2ecef(*target_deg))))


def local_target(origin_deg=LOCAL_ORIGIN_DEG):
    return np.array(pymap3d.geodetic2enu(*TARGET_DEG, *origin_deg))


SCENARIOS = {
    "bearings-3": (["w", "e", "s"], lambda ids: bearings(ids)),
    "bearings-ranges-2": (["w", "e"], bearings_and_ranges),
    "toa-5": (list(STATIONS_DEG), toas),
}


# --- noise-free exactness ------------------------------------------------------

@pytest.mark.parametrize("scenario", SCENARIOS)
def test_noise_free_fix_is_exact_in_the_wgs84_frame(scenario):
    ids, make = SCENARIOS[scenario]
    problem = build_problem(geodetic_stations(ids), make(ids))
    fix = solve(problem, "ml")
    assert fix.converged
    assert geodetic_error_m(problem, fix) < 1e-3  # 1 millimetre


@pytest.mark.parametrize("scenario", SCENARIOS)
def test_noise_free_fix_is_exact_in_a_local_frame_with_origin(scenario):
    ids, make = SCENARIOS[scenario]
    origin = GeodeticPoint(*d2r(LOCAL_ORIGIN_DEG[:2]), LOCAL_ORIGIN_DEG[2])
    problem = build_problem(local_stations(ids), make(ids), origin=origin)
    fix = solve(problem, "ml")
    assert np.linalg.norm(fix.position_enu_m - local_target()) < 1e-3  # 1 millimetre
    assert geodetic_error_m(problem, fix) < 1e-3  # 1 millimetre


def test_flat_earth_model_of_the_same_geometry_is_kilometres_off():
    """The teeth of the tests above: drop the per-station frame rotation and the fix moves far more than 1 m."""
    ids = ["w", "e", "s"]
    curved = build_problem(geodetic_stations(ids), bearings(ids))
    flat = build_problem([(k, LocalPoint(*p)) for k, p in zip(ids, curved.stations_enu_m)], bearings(ids))
    target = curved.frame.from_geodetic(d2r(TARGET_DEG[0]), d2r(TARGET_DEG[1]), TARGET_DEG[2])
    assert np.linalg.norm(solve(curved, "ml").position_enu_m - target) < 1e-3  # 1 millimetre
    assert np.linalg.norm(solve(flat, "ml").position_enu_m - target) > 100.0  # metres, not millimetres


def flat_plane_scenario():
    """Stations on small hills in a flat plane (no origin); measurements by hand."""
    stations = {"a": [0.0, 0.0, 0.0], "b": [20e3, 0.0, 300.0], "c": [0.0, 20e3, 800.0],
                "d": [20e3, 20e3, 150.0], "e": [10e3, -5e3, 600.0]}
    target = np.array([7e3, 9e3, 5e3])
    return {k: np.array(v) for k, v in stations.items()}, target


def by_hand(station, target):
    e, n, u = target - station
    return np.arctan2(e, n), np.arctan2(u, np.hypot(e, n)), float(np.linalg.norm(target - station))


@pytest.mark.parametrize("mix", ["bearings-3", "bearings-ranges-2", "toa-5"])
def test_noise_free_fix_is_exact_in_a_flat_local_frame(mix):
    stations, target = flat_plane_scenario()
    ids = {"bearings-3": "abc", "bearings-ranges-2": "ab", "toa-5": "abcde"}[mix]
    measurements = []
    for k in ids:
        az, el, r = by_hand(stations[k], target)
        if mix == "toa-5":
            measurements.append(TimeOfArrival(k, 12.0 + r / SPEED_OF_LIGHT_MPS, 1e-8))
        else:
            measurements.append(Bearing(k, az, el, ONE_DEG, ONE_DEG))
            if mix == "bearings-ranges-2":
                measurements.append(Range(k, r, 10.0))
    problem = build_problem([(k, LocalPoint(*stations[k])) for k in ids], measurements)
    fix = solve(problem, "ml")
    assert np.linalg.norm(fix.position_enu_m - target) < 1e-3  # 1 millimetre


def test_toa_from_ground_receivers_in_a_local_plane():
    """Receivers all at up = 0 (coplanar through the origin) still locate an emitter above them."""
    stations, target = flat_plane_scenario()
    measurements = [TimeOfArrival(k, 12.0 + np.linalg.norm(target - s * [1, 1, 0]) / SPEED_OF_LIGHT_MPS, 1e-8)
                    for k, s in stations.items()]
    problem = build_problem([(k, LocalPoint(s[0], s[1], 0.0)) for k, s in stations.items()], measurements)
    fix = solve(problem, "ml")
    assert np.linalg.norm(fix.position_enu_m - target) < 1e-3  # 1 millimetre, not the underground mirror


def test_noisy_toa_from_ground_receivers_stays_above_ground():
    """Near-coplanar receivers: the mirror image below ground fits almost as well; the fix must not take it."""
    rng = np.random.default_rng(17)
    lat, lon = 34.0 + rng.uniform(-0.1, 0.1, 5), 108.0 + rng.uniform(-0.1, 0.1, 5)
    stations = [(str(i), GeodeticPoint(d2r(a), d2r(b), 0.0)) for i, (a, b) in enumerate(zip(lat, lon))]
    problem = build_problem(stations, [TimeOfArrival(str(i), 12.0, 1e-8) for i in range(5)])
    target = problem.frame.from_geodetic(d2r(34.02), d2r(108.03), 3000.0)
    fixes = solve_batch([measure(problem, target, rng) for _ in range(200)], "ml")
    altitudes = np.array([problem.frame.to_geodetic(f.position_enu_m)[2] for f in fixes])
    # sigma 3 m of range: the altitude error is tens of metres, the mirror is 6 km away.
    assert np.all(altitudes > 0.0)


def test_two_lines_of_sight_meet_exactly():
    target = np.array([200.0, 100.0, 50.0])
    stations = {"a": np.zeros(3), "b": np.array([100.0, 0.0, 0.0])}
    measurements = [Bearing(k, *by_hand(s, target)[:2], ONE_DEG, ONE_DEG) for k, s in stations.items()]
    problem = build_problem([(k, LocalPoint(*s)) for k, s in stations.items()], measurements)
    fix = solve(problem, "ml")
    np.testing.assert_allclose(fix.position_enu_m, target, rtol=0, atol=1e-9)  # 1 nanometre
    np.testing.assert_allclose(fix.residuals, 0.0, rtol=0, atol=1e-12)  # 1e-12 rad
    assert fix.chi2 < 1e-12 and fix.dof == 1


def test_known_altitude_with_azimuths_only_in_wgs84():
    ids = ["w", "e"]
    problem = build_problem(geodetic_stations(ids), bearings(ids, elevation=False), altitude_m=TARGET_DEG[2])
    fix = solve(problem, "ml")
    assert geodetic_error_m(problem, fix) < 1e-3  # 1 millimetre
    _, _, alt = problem.frame.to_geodetic(fix.position_enu_m)
    assert alt == pytest.approx(TARGET_DEG[2], abs=1e-6)  # 1 micrometre: on the altitude surface
    # 2 unknowns on the surface: the covariance has no extent along the local vertical there.
    lat, lon, _ = problem.frame.to_geodetic(fix.position_enu_m)
    up = ecef_to_enu_rotation(lat, lon)[2] @ problem.frame.ecef_to_enu_rotation.T
    assert up @ fix.covariance_enu_m2 @ up < 1e-6 * np.trace(fix.covariance_enu_m2)
    assert fix.dof == 0


def test_known_altitude_stays_on_the_surface_with_noise():
    ids = ["w", "e", "s"]
    problem = build_problem(geodetic_stations(ids), bearings(ids, elevation=False), altitude_m=2500.0)
    rng = np.random.default_rng(4)
    target = problem.frame.from_geodetic(d2r(46.4), d2r(9.2), 2500.0)
    for noisy in [measure(problem, target, rng) for _ in range(20)]:
        _, _, alt = problem.frame.to_geodetic(solve(noisy, "ml").position_enu_m)
        assert alt == pytest.approx(2500.0, abs=1e-6)  # 1 micrometre


def test_known_altitude_in_a_flat_plane():
    stations, target = flat_plane_scenario()
    measurements = [Bearing(k, by_hand(stations[k], target)[0], None, ONE_DEG) for k in "ab"]
    problem = build_problem([(k, LocalPoint(*stations[k])) for k in "ab"], measurements, altitude_m=target[2])
    fix = solve(problem, "ml")
    np.testing.assert_allclose(fix.position_enu_m, target, rtol=0, atol=1e-3)  # 1 millimetre
    assert fix.position_enu_m[2] == pytest.approx(target[2], abs=1e-9)  # 1 nanometre: exactly on the plane


def test_azimuths_either_side_of_north_in_compass_form():
    """Bearings given in [0, 360): 358.85 deg and 1.15 deg straddle north; the fix is exact and residuals tiny."""
    target = np.array([0.0, 50e3, 1000.0])
    stations = {"a": np.array([-1000.0, 0.0, 0.0]), "b": np.array([1000.0, 0.0, 0.0])}
    measurements = []
    for k, s in stations.items():
        az, el, _ = by_hand(s, target)
        measurements.append(Bearing(k, np.mod(az, 2 * np.pi), el, d2r(0.01), d2r(0.01)))
    assert np.rad2deg(measurements[1].azimuth_rad) > 358.0
    fix = solve(build_problem([(k, LocalPoint(*s)) for k, s in stations.items()], measurements), "ml")
    assert np.linalg.norm(fix.position_enu_m - target) < 1e-3  # 1 millimetre
    assert np.max(np.abs(fix.residuals)) < 1e-9  # rad; an unwrapped residual would be ~6.28


@pytest.mark.parametrize("emission_s", [12.0, 1e5, 1.7e9])
def test_toa_fix_loses_only_the_rounding_of_its_input(emission_s):
    """TOA must be given against a recent epoch (12.000183 s, not Unix time).

    A TOA near ``t`` is stored to float64 spacing(t)/2: 0.9e-15 s at 12 s, 7e-12 s
    at 1e5 s (2.2 mm of light) and 1.2e-7 s at 1.7e9 s (36 m). The core
    subtracts the earliest TOA exactly, so the fix may be off by no more than
    that rounding carried through the geometry: |dp| <= sqrt(trace(CRLB)) / (c
    sigma) * sqrt(M) * c * spacing / 2 to first order.
    """
    ids = list(STATIONS_DEG)
    problem = build_problem(geodetic_stations(ids), toas(ids, emission_s))
    fix = solve(problem, "ml")
    dilution = np.sqrt(np.trace(fix.crlb_enu_m2)) / (SPEED_OF_LIGHT_MPS * 1e-8)
    rounding_m = SPEED_OF_LIGHT_MPS * np.spacing(emission_s) / 2
    bound_m = dilution * np.sqrt(len(ids)) * rounding_m + 1e-4  # + 0.1 mm for the iteration's stop
    error_m = geodetic_error_m(problem, fix)
    assert error_m <= bound_m
    if emission_s < 100:
        assert error_m < 1e-3  # 1 millimetre
    if emission_s > 1e9:
        assert error_m > 1.0  # documents the limit: metres lost at a Unix-time epoch


# --- failure modes ------------------------------------------------------------

def test_azimuth_only_without_altitude_is_unobservable():
    ids = ["w", "e"]
    problem = build_problem(geodetic_stations(ids), bearings(ids, elevation=False))
    with pytest.raises(UnobservableGeometry):
        solve(problem, "ml")
    # The batch path reports the same error in place, without failing its neighbours.
    good = build_problem(geodetic_stations(ids), bearings(ids))
    results = solve_batch([good, problem, good], "ml")
    assert isinstance(results[1], UnobservableGeometry)
    assert not isinstance(results[0], LocalizationError) and not isinstance(results[2], LocalizationError)
    assert geodetic_error_m(good, results[2]) < 1e-3  # 1 millimetre


def test_parallel_lines_of_sight_are_unobservable():
    stations = [("a", LocalPoint(0.0, 0.0, 0.0)), ("b", LocalPoint(100.0, 0.0, 0.0))]
    measurements = [Bearing(k, d2r(10.0), d2r(5.0), ONE_DEG, ONE_DEG) for k in "ab"]
    with pytest.raises(UnobservableGeometry):
        solve(build_problem(stations, measurements), "ml")


# --- warnings ---------------------------------------------------------------

def codes(fix):
    return {w.code for w in fix.warnings}


def square_scenario(sigma=d2r(0.1)):
    stations = {"a": [0.0, 0.0, 0.0], "b": [10e3, 0.0, 0.0], "c": [0.0, 10e3, 0.0], "d": [10e3, 10e3, 200.0]}
    stations = {k: np.array(v) for k, v in stations.items()}
    target = np.array([4e3, 6e3, 2e3])
    measurements = [Bearing(k, *by_hand(s, target)[:2], sigma, sigma) for k, s in stations.items()]
    return stations, target, measurements


def test_clean_fix_has_no_warnings():
    stations, target, measurements = square_scenario()
    fix = solve(build_problem([(k, LocalPoint(*s)) for k, s in stations.items()], measurements), "ml")
    assert codes(fix) == set()


def test_target_behind_a_station_line_of_sight():
    stations, target, measurements = square_scenario()
    far = np.array([5e3, -30e3, 0.0])
    az = by_hand(far, target)[0]
    placed = [(k, LocalPoint(*s)) for k, s in stations.items()] + [("far", LocalPoint(*far))]
    # A weak (30 deg) azimuth pointing away from the target: the others hold the fix, which lies behind it.
    reversed_bearing = Bearing("far", az + np.pi, None, d2r(30.0))
    fix = solve(build_problem(placed, measurements + [reversed_bearing]), "ml")
    assert "behind_station" in codes(fix)
    assert "far" in next(w.message for w in fix.warnings if w.code == "behind_station")
    # Control: the same bearing pointing at the target.
    fix = solve(build_problem(placed, measurements + [Bearing("far", az, None, d2r(30.0))]), "ml")
    assert "behind_station" not in codes(fix)


def test_lines_meeting_behind_a_station_closed_form():
    """EOVE intersects lines, not rays: the point it finds is behind station A's look direction."""
    stations = [("A", LocalPoint(0.0, 0.0, 0.0)), ("B", LocalPoint(-1000.0, -1000.0, 0.0))]
    measurements = [Bearing("A", d2r(90.0), 0.0, ONE_DEG, ONE_DEG), Bearing("B", 0.0, 0.0, ONE_DEG, ONE_DEG)]
    fix = solve(build_problem(stations, measurements), "eove")
    np.testing.assert_allclose(fix.position_enu_m, [-1000.0, 0.0, 0.0], rtol=0, atol=1e-6)  # 1 micrometre
    assert "behind_station" in codes(fix)


def test_target_far_along_the_baseline_is_collinear():
    stations = {"a": np.zeros(3), "b": np.array([1000.0, 0.0, 0.0])}
    placed = [(k, LocalPoint(*s)) for k, s in stations.items()]

    def fix_for(target):
        measurements = [Bearing(k, *by_hand(s, target)[:2], d2r(0.1), d2r(0.1)) for k, s in stations.items()]
        return solve(build_problem(placed, measurements), "ml")

    far_along = fix_for(np.array([50e3, 2e3, 1e3]))  # lines of sight 0.05 deg apart
    assert "collinear_geometry" in codes(far_along)
    broadside = fix_for(np.array([500.0, 20e3, 1e3]))  # lines of sight 2.9 deg apart
    assert "collinear_geometry" not in codes(broadside)


def test_gross_outlier_is_flagged():
    stations, target, measurements = square_scenario()
    placed = [(k, LocalPoint(*s)) for k, s in stations.items()]
    bad = measurements[2]
    measurements[2] = Bearing(bad.station_id, bad.azimuth_rad + d2r(5.0), bad.elevation_rad,
                              bad.sigma_azimuth_rad, bad.sigma_elevation_rad)  # 50 sigma off
    fix = solve(build_problem(placed, measurements), "ml")
    assert {"outlier_suspected", "sigma_mismatch"} <= codes(fix)
    assert "measurement 2 " in next(w.message for w in fix.warnings if w.code == "outlier_suspected")
    assert fix.p_value < 1e-3


def test_bearings_meeting_only_behind_a_station_say_so():
    """Contradictory bearings are a 422 that names the cause, not 'add stations'."""
    from core.errors import UnobservableGeometry
    from core.estimators import solve
    from core.problem.build import Bearing, build_problem
    from core.problem.frame import LocalPoint

    target = np.array([500.0, -3000.0, 300.0])
    one_degree = np.deg2rad(1.0)
    to_a, to_b = target, target - np.array([1000.0, 0.0, 0.0])
    reversed_azimuth_a = np.arctan2(to_a[0], to_a[1]) + np.pi
    problem = build_problem(
        [("a", LocalPoint(0, 0, 0)), ("b", LocalPoint(1000, 0, 0))],
        [Bearing("a", reversed_azimuth_a, None, one_degree),
         Bearing("b", np.arctan2(to_b[0], to_b[1]), np.arctan2(to_b[2], np.hypot(to_b[0], to_b[1])),
                 one_degree, one_degree)])
    with pytest.raises(UnobservableGeometry, match="behind a station"):
        solve(problem, "ml")
    assert "behind_station" in {w.code for w in solve(problem, "eove").warnings}


def _stated_too_small(problem, seed, factor):
    """``problem`` measured with noise ``factor`` times what its sigmas say."""
    from dataclasses import replace

    target = problem.frame.from_geodetic(d2r(TARGET_DEG[0]), d2r(TARGET_DEG[1]), TARGET_DEG[2])
    noisy = measure(problem, target, np.random.default_rng(seed))
    return replace(noisy, sigmas=noisy.sigmas / factor)


@pytest.mark.parametrize("mix, loss, factor, searched", [("bearings", "linear", 10, False),
                                                         ("bearings_and_ranges", "linear", 10, True),
                                                         ("bearings", "huber", 100, False),
                                                         ("bearings", "cauchy", 1000, True)])
def test_only_fits_that_may_have_another_basin_are_searched_again(monkeypatch, mix, loss, factor, searched):
    # Sigmas stated far too small make every fit implausible (p < IMPLAUSIBLE_P). Lines of sight meeting ahead
    # of their stations have one basin, so ML does not run the start search (53 LM runs a problem here) that
    # could only find the same fit; a range adds a second crossing of each line, and a redescending loss a
    # minimum per measurement it sets aside, so those are searched.
    import core.estimators.methods.ml as ml

    calls = []
    real = ml.searched_starts
    monkeypatch.setattr(ml, "searched_starts", lambda batch, *args: calls.append(batch.size) or real(batch, *args))
    measurements = bearings("wesn") if mix == "bearings" else bearings_and_ranges("wesn")
    problems = [_stated_too_small(build_problem(geodetic_stations("wesn"), measurements), seed, factor)
                for seed in range(8)]
    fixes = solve_batch(problems, "ml", SolveOptions(loss=loss))
    assert all(fix.p_value < ml.IMPLAUSIBLE_P and "sigma_mismatch" in codes(fix) for fix in fixes)
    assert (len(calls) > 0) if searched else (calls == []), calls


@pytest.mark.parametrize("loss", ["huber", "cauchy", "soft_l1"])
def test_a_robust_fit_of_clean_bearings_stops_at_its_minimum(loss):
    # With every residual past the loss's bend the Gauss-Newton weights vanish (rho' + 2 rho'' z floored at
    # machine epsilon); the Jacobi scaling then came from that vanishing diagonal, the damped steps stayed
    # metres long, and LM stopped short of the minimum (cost 0.2-0.6 above it on this scene).
    from bench.scenarios import four_station_requests
    from core.estimators.lm import levenberg_marquardt
    from core.estimators.starting_points import initial_positions
    from service.fixes.read import read_fix_requests

    batch = read_fix_requests(four_station_requests(2000, np.random.default_rng(22))).batch
    starts, _, _ = initial_positions(batch)
    fit = levenberg_marquardt(batch, starts, 50, 1e-3, (loss, 1.0))
    further = levenberg_marquardt(batch, fit.position_enu_m, 500, 1e-6, (loss, 1.0))
    assert fit.converged.all()
    assert np.max(fit.cost - further.cost) < 1e-6


def test_the_one_call_start_and_fit_is_the_staged_one(monkeypatch):
    # ML starts bearing problems by weighted EOVE and iterates from there in one compiled call; the staged path
    # (initial_positions, then iterate) must give the same numbers, bit for bit, and the same start names.
    from bench.scenarios import four_station_requests
    from core.estimators.methods import ml as ml_module
    from service.fixes.read import read_fix_requests

    requests = four_station_requests(40, np.random.default_rng(5))
    requests[3]["options"] = {"initial_guess": requests[3]["stations"][0]["position"]}  # staged: its guess
    batch = read_fix_requests(requests).batch
    assert ml_module._eove_started_fits(batch, SolveOptions()) is None  # a guess: the staged path
    plain = read_fix_requests(requests[:3] + requests[4:]).batch
    assert ml_module._eove_started_fits(plain, SolveOptions()) is not None
    for options in (SolveOptions(), SolveOptions(loss="huber")):
        fused = ml_module.ml(plain, options)
        monkeypatch.setattr(ml_module, "_eove_started_fits", lambda batch, options: None)
        staged = ml_module.ml(plain, options)
        monkeypatch.undo()
        for name in ("position_enu_m", "converged", "iterations", "bias_m"):
            np.testing.assert_array_equal(getattr(fused, name), getattr(staged, name), err_msg=name)
        assert fused.details == staged.details and fused.errors == staged.errors
