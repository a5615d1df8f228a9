"""The batched orthogonal-vector estimators and closed-form starts against brute-force per-problem references.

The references below are written independently of the estimators: one problem at
a time, rows stacked in Python and solved with ``np.linalg.lstsq`` (LAPACK SVD),
covariances with ``np.linalg.pinv``.
"""

from __future__ import annotations

import numpy as np
import pytest

from core.problem.batch import ProblemBatch
from core.errors import LocalizationError, TooFewMeasurements, UnobservableGeometry
from core.estimators import SolveOptions
from core.estimators.base import REGISTRY
from core.estimators.starting_points import initial_positions
from core.linalg import jacobi_svd
from core.measurements import SPEED_OF_LIGHT_MPS, Kind
from core.problem.build import Bearing, Range, TimeOfArrival, build_problem
from core.problem.frame import LocalPoint
from core.simulation.measurements import measure

from tests.core.test_ml_batch import mixed_problems

REL = 1e-9


def reference_orthogonal_vector(problem, horizontal_rows: bool, weighted: bool):
    """One problem's OVE (no horizontal rows), EOVE or weighted EOVE by lstsq on rows stacked line by line."""
    rows, rhs, sigma, station, is_vertical = [], [], [], [], []
    lines = {}
    for m, kind in enumerate(problem.kinds):
        if kind in (Kind.AZIMUTH, Kind.ELEVATION):
            lines.setdefault(int(problem.bearing_index[m]), {})[int(kind)] = m
    for line in sorted(lines):
        az_row, el_row = lines[line][Kind.AZIMUTH], lines[line].get(Kind.ELEVATION)
        n = int(problem.station_index[az_row])
        rotation, origin = problem.station_rotations[n], problem.stations_enu_m[n]
        az = problem.values[az_row]
        el = 0.0 if el_row is None else problem.values[el_row]
        candidates = []
        if el_row is not None:
            candidates.append((np.array([-np.sin(el) * np.sin(az), -np.sin(el) * np.cos(az), np.cos(el)]),
                               problem.sigmas[el_row], True))
        if horizontal_rows:
            candidates.append((np.array([np.cos(az), -np.sin(az), 0.0]), problem.sigmas[az_row], False))
        for local, s, vertical in candidates:
            c = rotation.T @ local
            rows.append(c)
            rhs.append(c @ origin)
            sigma.append(s if np.isfinite(s) else 1.0)
            station.append(n)
            is_vertical.append(vertical)
    rows, rhs, sigma, is_vertical = np.array(rows), np.array(rhs), np.array(sigma), np.array(is_vertical)
    station = np.array(station)
    altitude, frame = problem.altitude_m, problem.frame

    def scale_at(p):
        seen = np.einsum("kij,kj->ki", problem.station_rotations[station], p - problem.stations_enu_m[station])
        horizontal = np.hypot(seen[:, 0], seen[:, 1])
        return np.where(is_vertical, np.linalg.norm(seen, axis=-1), horizontal)

    def lstsq(weights, up, up_rhs):
        a, b = rows * weights[:, None], rhs * weights
        if altitude is not None:
            strong = 1e3 * weights.max()
            a, b = np.vstack([a, strong * up]), np.append(b, strong * up_rhs)
        s = np.linalg.svd(a, compute_uv=False)
        if s.size < 3 or s[-1] <= 1e-9 * s[0]:
            raise UnobservableGeometry("rank")
        return np.linalg.lstsq(a, b, rcond=None)[0]

    up, up_rhs = np.array([0.0, 0.0, 1.0]), altitude or 0.0
    position = lstsq(np.ones(len(rows)), up, up_rhs)
    for _ in range(2 if weighted or altitude is not None else 0):
        if altitude is not None:
            on_surface = frame.onto_altitude(position, altitude)
            up = frame.local_axes(on_surface)[2]
            up_rhs = up @ on_surface
        weights = 1.0 / (sigma * np.maximum(scale_at(position), 1e-9)) if weighted else np.ones(len(rows))
        position = lstsq(weights, up, up_rhs)
    if altitude is not None:
        position = frame.onto_altitude(position, altitude)
    scale = scale_at(position)
    weights = 1.0 / (sigma * np.maximum(scale, 1e-9)) if weighted else np.ones(len(rows))
    a = rows if altitude is None else rows @ frame.local_axes(position)[:2].T
    gain = np.linalg.pinv(a.T @ (a * weights[:, None] ** 2))
    middle = a.T @ (a * (weights**4 * (sigma * scale) ** 2)[:, None])
    covariance = gain @ middle @ gain
    if altitude is not None:
        axes = frame.local_axes(position)[:2]
        covariance = axes.T @ covariance @ axes
    return position, covariance


def random_four_station_problems(count, seed, elevation=True):
    rng = np.random.default_rng(seed)
    problems = []
    for _ in range(count):
        stations = [(f"s{i}", LocalPoint(*rng.uniform([-30e3, -30e3, 0.0], [30e3, 30e3, 500.0]))) for i in range(4)]
        sigma = np.deg2rad(rng.uniform(0.2, 2.0))
        bearings = [Bearing(k, 0.0, 0.0 if elevation else None, sigma, sigma if elevation else None) for k, _ in stations]
        target = rng.uniform([-50e3, -50e3, 1e3], [50e3, 50e3, 10e3])
        problems.append(measure(build_problem(stations, bearings), target, rng))
    return problems


METHODS = {"ove": (False, False), "eove": (True, False), "weighted_eove": (True, True)}


@pytest.mark.parametrize("method", sorted(METHODS))
def test_batched_orthogonal_vector_equals_lstsq_per_problem(method):
    problems = mixed_problems() + random_four_station_problems(40, 7)
    batch = ProblemBatch.from_problems(problems)
    estimates = REGISTRY[method].estimate(batch, SolveOptions())
    solved = 0
    for b, problem in enumerate(problems):
        bearings = problem.count(Kind.AZIMUTH)
        try:
            if method == "ove" and problem.count(Kind.ELEVATION) < 3:
                raise TooFewMeasurements("needs 3")
            if bearings == 0:
                raise TooFewMeasurements("needs bearings")
            expected = reference_orthogonal_vector(problem, *METHODS[method])
        except LocalizationError as error:
            assert b in estimates.errors, b
            assert type(estimates.errors[b]) is type(error), (b, estimates.errors[b])
            continue
        assert b not in estimates.errors, (b, estimates.errors.get(b))
        position, covariance = expected
        np.testing.assert_allclose(estimates.position_enu_m[b], position, rtol=REL, atol=1e-6)  # 1 micrometre
        np.testing.assert_allclose(estimates.covariance_enu_m2[b], covariance, rtol=REL,
                                   atol=REL * np.abs(covariance).max())
        solved += 1
    assert solved >= 40


def test_orthogonal_vector_errors_keep_their_messages():
    problems = mixed_problems()
    batch = ProblemBatch.from_problems(problems)
    ove = REGISTRY["ove"].estimate(batch, SolveOptions())
    b = next(i for i, p in enumerate(problems) if p.count(Kind.AZIMUTH) == 2 and p.count(Kind.ELEVATION) == 2)
    assert (ove.errors[b].message, ove.errors[b].loc) == (
        "ove needs at least 3 lines of sight with elevation; got 2", ("measurements",))
    eove = REGISTRY["eove"].estimate(batch, SolveOptions())
    no_bearings = next(i for i, p in enumerate(problems) if p.count(Kind.AZIMUTH) == 0)
    assert isinstance(eove.errors[no_bearings], TooFewMeasurements)
    assert eove.errors[no_bearings].message == "eove needs bearings"
    one_line = next(i for i, p in enumerate(problems) if p.count(Kind.AZIMUTH) == 1)
    assert isinstance(eove.errors[one_line], UnobservableGeometry)
    assert eove.errors[one_line].message.startswith("eove: the lines of sight do not determine a point")


def test_jacobi_svd_matches_lapack_and_ignores_zero_rows():
    rng = np.random.default_rng(11)
    a = rng.standard_normal((200, 7, 3))
    a[:20, :, 2] = 2.0 * a[:20, :, 0] + 1e-7 * a[:20, :, 1]  # nearly rank-deficient
    a[20:40, :, 2] = a[20:40, :, 0]  # rank-deficient
    rhs = rng.standard_normal((200, 7, 2))
    s, v, projected = jacobi_svd(a, rhs)
    expected = np.linalg.svd(a, compute_uv=False)
    assert np.all(np.abs(-np.sort(-s, axis=-1) - expected) <= 1e-14 * expected[:, :1])
    np.testing.assert_allclose(np.swapaxes(v, -1, -2) @ v, np.broadcast_to(np.eye(3), v.shape), atol=1e-14)
    np.testing.assert_allclose(np.linalg.norm(a @ v, axis=-2), s, rtol=1e-12, atol=1e-13)
    np.testing.assert_allclose(projected, np.swapaxes(a @ v, -1, -2) @ rhs, atol=1e-12)
    full_rank = slice(40, None)
    solution = v[full_rank] @ (projected[full_rank] / s[full_rank, :, None] ** 2)
    reference = np.array([np.linalg.lstsq(m, y, rcond=None)[0] for m, y in zip(a[full_rank], rhs[full_rank])])
    np.testing.assert_allclose(solution, reference, rtol=1e-10, atol=1e-12)
    padded_s, padded_v, padded_projected = jacobi_svd(np.concatenate([a, np.zeros((200, 5, 3))], axis=1),
                                                      np.concatenate([rhs, np.zeros((200, 5, 2))], axis=1))
    np.testing.assert_array_equal(padded_s, s)
    np.testing.assert_array_equal(padded_v, v)
    np.testing.assert_array_equal(padded_projected, projected)
    s_wide, _, _ = jacobi_svd(a[:, :2])  # fewer rows than columns: the third singular value is 0
    assert np.all(np.sort(s_wide, axis=-1)[:, 0] <= 1e-14 * s_wide.max(axis=-1))


def _local(points):
    return [(f"s{i}", LocalPoint(*p)) for i, p in enumerate(points)]


def test_starts_are_exact_without_noise_and_each_as_alone():
    target = np.array([12e3, -7e3, 3e3])
    ground = [(0.0, 0.0, 0.0), (20e3, 0.0, 0.0), (0.0, 25e3, 0.0), (-15e3, -10e3, 0.0), (9e3, 30e3, 0.0)]
    hills = [(0.0, 0.0, 0.0), (20e3, 0.0, 900.0), (0.0, 25e3, 300.0), (-15e3, -10e3, 1500.0)]

    def exact(problem):
        return measure(problem, target)

    toa = exact(build_problem(_local(ground), [TimeOfArrival(f"s{i}", 0.0, 10.0 / SPEED_OF_LIGHT_MPS)
                                              for i in range(5)]))
    ranges_flat = exact(build_problem(_local(ground[:4]), [Range(f"s{i}", 0.0, 10.0) for i in range(4)]))
    ranges_3d = exact(build_problem(_local(hills), [Range(f"s{i}", 0.0, 10.0) for i in range(4)]))
    polar = exact(build_problem(_local(ground[:2]), [Bearing("s0", 0.0, 0.0, 0.01, 0.01), Range("s0", 0.0, 10.0),
                                                     Range("s1", 0.0, 10.0)]))
    bearings = exact(build_problem(_local(hills), [Bearing(f"s{i}", 0.0, 0.0, 0.01, 0.01) for i in range(4)]))
    collinear = exact(build_problem(_local([(0.0, 0.0, 0.0), (1e4, 0.0, 0.0), (2e4, 0.0, 0.0)]),
                                    [Range(f"s{i}", 0.0, 10.0) for i in range(3)]))
    toa_on_a_line = exact(build_problem(_local([(i * 1e4, 0.0, 0.0) for i in range(4)]),
                                        [TimeOfArrival(f"s{i}", 0.0, 1e-8) for i in range(4)]))
    too_few = exact(build_problem(_local(ground[:2]), [Range("s0", 0.0, 10.0), Range("s1", 0.0, 10.0)]))
    problems = [toa, ranges_flat, ranges_3d, polar, bearings, collinear, toa_on_a_line, too_few]
    positions, names, failures = initial_positions(ProblemBatch.from_problems(problems))
    assert names[:5] == ["bancroft", "trilateration", "trilateration", "polar", "weighted_eove"]
    for b in range(5):
        np.testing.assert_allclose(positions[b], target, atol=1e-3)  # 1 mm, noise-free
    assert failures[5].message == "range stations are collinear: the target lies on a circle"
    assert failures[6].message == "TOA stations are coplanar or too few for an algebraic TDOA solution"
    assert isinstance(failures[7], TooFewMeasurements) and failures[7].loc == ("measurements",)
    for b, problem in enumerate(problems):
        alone, alone_names, alone_failures = initial_positions(ProblemBatch.from_problems([problem]))
        assert alone_names[0] == names[b]
        if b in failures:
            assert alone_failures[0].message == failures[b].message
        else:
            np.testing.assert_array_equal(alone[0], positions[b])  # the same bits, as responses must be


def test_a_zero_range_polar_start_does_not_sink_its_batch():
    """A bearing and a range of 0 m from one station: its polar covariance (10 m along, 1e-9 m across before
    MIN_POLAR_SD_RATIO) was singular, and np.linalg.inv raised for the whole batch (a 500 for every request)."""
    at_station = build_problem(_local([(-1466.9, -1225.0, 0.0)]),
                               [Bearing("s0", np.deg2rad(358.66), np.deg2rad(-3.23), np.deg2rad(3.0), np.deg2rad(3.0)),
                                Range("s0", 0.0, 10.0)])
    far = build_problem(_local([(0.0, 0.0, 0.0)]), [Bearing("s0", 0.5, 0.1, 0.01, 0.01), Range("s0", 20e3, 10.0)])
    positions, names, failures = initial_positions(ProblemBatch.from_problems([at_station, far]))
    assert names == ["polar", "polar"] and not failures
    np.testing.assert_allclose(positions[0], at_station.stations_enu_m[0], atol=0.1)  # range sigma 10 m
    np.testing.assert_array_equal(positions[1], initial_positions(ProblemBatch.from_problems([far]))[0][0])


@pytest.mark.parametrize("method", ["ove", "eove", "weighted_eove"])
def test_a_problem_gets_the_same_bits_alone_and_padded_in_a_batch(method):
    """Byte-equal responses need bit-equal fixes: neither the batch size nor zero padding may change rounding."""
    problems = random_four_station_problems(6, 3) + [p for p in mixed_problems() if p.count(Kind.AZIMUTH) >= 3]
    batch = ProblemBatch.from_problems(problems)
    together = REGISTRY[method].estimate(batch, SolveOptions())
    starts, _, _ = initial_positions(batch)
    for b, problem in enumerate(problems):
        alone = REGISTRY[method].estimate(ProblemBatch.from_problems([problem]), SolveOptions())
        if b in together.errors:
            assert 0 in alone.errors
            continue
        np.testing.assert_array_equal(alone.position_enu_m[0], together.position_enu_m[b])
        np.testing.assert_array_equal(alone.covariance_enu_m2[0], together.covariance_enu_m2[b])
        np.testing.assert_array_equal(initial_positions(ProblemBatch.from_problems([problem]))[0][0], starts[b])
