"""One road: every problem of a mixed batch gets from every method what it gets alone (a batch of one),
whatever else is in the batch and however it is chunked; problem padding round-trips."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from core.problem.batch import ProblemBatch, size_groups
from core.problem.batch_build import build_problem_batch
from core.errors import LocalizationError
from core.estimators import REGISTRY, SolveOptions, solve_batch
from core.estimators.base import get_estimator
from core.measurements import SPEED_OF_LIGHT_MPS, Kind
from core.problem.build import Bearing, Range, TimeOfArrival, build_problem
from core.problem.frame import GeodeticPoint, LocalPoint
from core.simulation.measurements import measure

d2r = np.deg2rad
SIGMA = d2r(0.5)
REL = 1e-9  # relative agreement asked of batch and single fixes
GEODETIC = {"a": (34.0, 108.5, 300.0), "b": (34.4, 108.9, 500.0), "c": (33.8, 109.1, 100.0),
            "d": (34.1, 109.4, 800.0), "e": (33.6, 108.7, 50.0)}


def _geodetic(ids):
    return [(k, GeodeticPoint(d2r(GEODETIC[k][0]), d2r(GEODETIC[k][1]), GEODETIC[k][2])) for k in ids]


def _local(ids):
    return [(k, LocalPoint(*(np.array(GEODETIC[k]) - [34.0, 108.5, 0.0]) * [90e3, 90e3, 1.0])) for k in ids]


def _bearings(ids, elevation=True, sigma=SIGMA):
    return [Bearing(k, 0.0, 0.0 if elevation else None, sigma, sigma if elevation else None) for k in ids]


def _noisy(problem, target, seed):
    return measure(problem, np.asarray(target, dtype=float), np.random.default_rng(seed))


def mixed_problems():
    """Different station counts, measurement mixes, constraints and frames; a few unsolvable."""
    target = np.array([20e3, 30e3, 6e3])
    out = []
    for seed, ids in enumerate(("abcd", "abc", "abcde", "ab")):
        out.append(_noisy(build_problem(_geodetic(ids), _bearings(ids)), target, seed))
    out.append(_noisy(build_problem(_local("abcd"), _bearings("abcd")), target, 10))
    origin = GeodeticPoint(d2r(34.0), d2r(108.5), 0.0)
    out.append(_noisy(build_problem(_local("abc"), _bearings("abc"), origin=origin), target, 11))
    ranges = [Range(k, 0.0, 50.0) for k in "ab"]
    out.append(_noisy(build_problem(_geodetic("ab"), _bearings("ab") + ranges), target, 12))
    toas = [TimeOfArrival(k, 0.0, 30.0 / SPEED_OF_LIGHT_MPS) for k in "abcde"]
    out.append(_noisy(build_problem(_geodetic("abcde"), toas), target, 13))
    out.append(_noisy(build_problem(_geodetic("abc"), _bearings("abc") + toas[:3]), target, 14))
    out.append(_noisy(build_problem(_geodetic("abcd"), [Range(k, 0.0, 40.0) for k in "abcd"]), target, 15))
    surface = build_problem(_geodetic("abc"), _bearings("abc", elevation=False), altitude_m=6000.0)
    out.append(_noisy(surface, surface.frame.onto_altitude(target, 6000.0), 16))
    flat = build_problem(_local("abcd"), _bearings("abcd", elevation=False), altitude_m=6000.0)
    out.append(_noisy(flat, target, 17))
    guessed = build_problem(_geodetic("abcd"), _bearings("abcd"), initial_guess=LocalPoint(1e4, 1e4, 0.0))
    out.append(_noisy(guessed, target, 18))
    bad = _noisy(build_problem(_geodetic("abcd"), _bearings("abcd")), target, 19)
    out.append(bad.with_values(bad.values + np.r_[0.2, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0]))
    out.append(build_problem(_geodetic("a"), _bearings("a")))
    out.append(build_problem(_geodetic("ab"), [Range("a", 1e4, 10.0), Range("b", 1e4, 10.0)]))
    return out


def assert_same_fix(a, b):
    assert type(a) is type(b)
    if isinstance(a, LocalizationError):
        assert (a.code, a.message, a.loc) == (b.code, b.message, b.loc)
        return
    for f in dataclasses.fields(a):
        x, y = getattr(a, f.name), getattr(b, f.name)
        if isinstance(x, np.ndarray) or isinstance(x, float):
            np.testing.assert_allclose(x, y, rtol=REL, atol=1e-12, err_msg=f.name)
        elif isinstance(x, dict):
            assert x.keys() == y.keys(), f.name
            for key in x:
                np.testing.assert_equal(x[key], y[key], err_msg=f"{f.name}.{key}")
        else:
            assert x == y, f.name


def test_batch_equals_each_problem_alone():
    problems = mixed_problems()
    together = solve_batch(problems, "ml")
    assert sum(isinstance(r, LocalizationError) for r in together) == 2
    assert any(r.warnings for r in together if not isinstance(r, LocalizationError))
    for problem, batched in zip(problems, together):
        assert_same_fix(batched, solve_batch([problem], "ml")[0])


@pytest.mark.parametrize("method", sorted(set(REGISTRY) - {"ml"}))
def test_every_method_gives_each_problem_what_it_gets_alone(method):
    problems = mixed_problems()
    together = solve_batch(problems, method)
    assert any(not isinstance(r, LocalizationError) for r in together) or method in ("tls", "ctls", "taylor_wls")
    for problem, batched in zip(problems, together):
        assert_same_fix(batched, solve_batch([problem], method)[0])


def test_chunking_the_search_does_not_change_results(monkeypatch):
    import core.estimators.ties as ties

    problems = [p for p in mixed_problems() if p.n_measurements == 8] * 20
    batch = ProblemBatch.from_problems(problems)
    whole = get_estimator("ml").solve_batch(batch, SolveOptions())
    monkeypatch.setattr(ties, "CHUNK_ENTRIES", 8)
    chunked = get_estimator("ml").solve_batch(batch, SolveOptions())
    for b in range(batch.size):
        assert_same_fix(whole.fix(b), chunked.fix(b))


def test_problem_batch_round_trip():
    problems = mixed_problems()
    batch = ProblemBatch.from_problems(problems)
    for b, problem in enumerate(problems):
        again = batch.problem(b)
        for f in dataclasses.fields(problem):
            x, y = getattr(problem, f.name), getattr(again, f.name)
            if isinstance(x, np.ndarray):
                np.testing.assert_array_equal(x, y, err_msg=f.name)
            else:
                assert x == y, f.name


@pytest.mark.parametrize("frame", ["wgs84", "local", "local+origin"])
def test_build_problem_batch_equals_build_problem(frame):
    origin = GeodeticPoint(d2r(34.0), d2r(108.5), 10.0) if frame == "local+origin" else None
    stations = _geodetic("abcd") if frame == "wgs84" else _local("abcd")
    measurements = [Bearing("a", 0.3, 0.05, SIGMA, SIGMA), TimeOfArrival("b", 12.5, 1e-7), Range("c", 3e4, 20.0),
                    Bearing("d", 5.9, None, SIGMA, None), TimeOfArrival("c", 12.49, 1e-7)]
    expected = build_problem(stations, measurements, origin=origin, altitude_m=500.0)
    geodetic = frame == "wgs84"
    coordinates = [(p.lat_rad, p.lon_rad, p.alt_m) if geodetic else (p.east_m, p.north_m, p.up_m)
                   for _, p in stations]
    rows = [(Kind.AZIMUTH, 0, 0.3, SIGMA, 0, 0), (Kind.ELEVATION, 0, 0.05, SIGMA, 0, 0), (Kind.TOA, 1, 12.5, 1e-7, -1, 1),
            (Kind.RANGE, 2, 3e4, 20.0, -1, 2), (Kind.AZIMUTH, 3, 5.9, SIGMA, 1, 3), (Kind.TOA, 2, 12.49, 1e-7, -1, 4)]
    kinds, index, values, sigmas, bearing, source = (np.array(c) for c in zip(*rows))
    origin_row = [origin.lat_rad, origin.lon_rad, origin.alt_m] if origin else [np.nan] * 3
    built = build_problem_batch([4], [tuple("abcd")], coordinates, [geodetic], [origin_row], [6], kinds, index,
                                values, sigmas, bearing, source, [500.0], [[np.nan] * 3], [False])
    reference = ProblemBatch.from_problems([expected])
    for f in dataclasses.fields(ProblemBatch):
        x, y = getattr(built, f.name), getattr(reference, f.name)
        if isinstance(x, np.ndarray):
            np.testing.assert_allclose(x, y, rtol=1e-12, atol=1e-9, err_msg=f.name)  # 1 nanometre
        else:
            assert x == y, f.name


def test_size_groups_bound_padding():
    sizes = np.array([1, 2, 3, 8, 9, 4096, 100, 5])
    groups = size_groups(sizes)
    assert sorted(np.concatenate(groups).tolist()) == list(range(sizes.size))
    for group in groups:
        assert sizes[group].max() <= 2 * max(sizes[group].min(), 1)


def test_an_elevation_whose_azimuth_is_set_aside_joins_no_other_line():
    """Lines of sight pair each used elevation with its own bearing's azimuth: with that azimuth set aside (outlier
    exclusion), the elevation must not land on another bearing's line (it went to row 0 once)."""
    problem = _noisy(build_problem(_geodetic("abc"), _bearings("abc")), [20e3, 30e3, 6e3], 3)
    batch = ProblemBatch.from_problems([problem])
    kinds, bearing = batch.kinds[0], batch.bearing_index[0]
    azimuth_rows = {int(bearing[m]): m for m in np.flatnonzero(kinds == Kind.AZIMUTH)}
    elevation_rows = {int(bearing[m]): m for m in np.flatnonzero(kinds == Kind.ELEVATION)}
    for dropped in azimuth_rows:
        used = np.ones(kinds.shape, dtype=bool)
        used[azimuth_rows[dropped]] = False
        is_line, elevation, sigma = batch.with_used(used[None]).lines_of_sight()
        for k, row in azimuth_rows.items():
            assert is_line[0, row] == (k != dropped)
            expected = np.nan if k == dropped else batch.values[0, elevation_rows[k]]
            np.testing.assert_equal(elevation[0, row], expected)
        assert np.count_nonzero(~np.isnan(elevation)) == len(azimuth_rows) - 1


def test_a_problem_whose_bearing_lost_its_azimuth_has_one_line_fewer():
    """The single-problem lines of sight agree with the batch's: a bearing left with only its elevation (its
    azimuth set aside) is no line (row -1 stood in for its azimuth once)."""
    problem = _noisy(build_problem(_geodetic("abc"), _bearings("abc")), [20e3, 30e3, 6e3], 3)
    batch = ProblemBatch.from_problems([problem])
    used = np.ones(batch.kinds.shape, dtype=bool)
    used[0, np.flatnonzero((batch.kinds[0] == Kind.AZIMUTH) & (batch.bearing_index[0] == 1))] = False
    alone = batch.with_used(used).problem(0).lines_of_sight()
    is_line, elevation, _ = batch.with_used(used).lines_of_sight()
    assert alone.count == np.count_nonzero(is_line) == 2
    np.testing.assert_array_equal(alone.azimuth_rad, batch.values[0, is_line[0]])
    np.testing.assert_array_equal(alone.elevation_rad, elevation[0, is_line[0]])


def test_problems_group_by_method_and_options_value_in_order_of_first_appearance():
    from core.estimators import _groups

    a, b, c = SolveOptions(), SolveOptions(), SolveOptions(max_iterations=3)  # a == b, separate objects
    groups = _groups(["ml", "tls", "ml", "ml", "tls", "ml"], [a, b, c, a, a, b])
    assert [(name, opts.max_iterations, rows.tolist()) for (name, opts), rows in groups.items()] == [
        ("ml", 50, [0, 3, 5]), ("tls", 50, [1, 4]), ("ml", 3, [2])]
    # One options object per problem, as a batch of requests that each send options has them: one group.
    ((key, rows),) = _groups(["ml"] * 1000, [SolveOptions(outliers="exclude") for _ in range(1000)]).items()
    assert key == ("ml", SolveOptions(outliers="exclude")) and rows.tolist() == list(range(1000))
    assert _groups([], []) == {}
