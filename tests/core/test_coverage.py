"""Coverage maps: where the bound is good and bad, its GDOP, and the same result on a Dask cluster."""

from __future__ import annotations

import numpy as np
import pytest

from core.problem.batch import ProblemBatch
from core.coverage import cells_per_side, coverage_grid, coverage_map, grid
from core.crlb import information_at
from core.parallel import Stopped
from core.problem.build import Bearing, Range, TimeOfArrival, build_problem
from core.problem.frame import GeodeticPoint, LocalPoint

SIGMA_RAD = np.radians(1.0)
BASELINE_M = 10_000.0
C_MPS = 299_792_458.0


def two_stations(**kwargs):
    """Azimuth-only stations at east -5 km and +5 km, surface target (known altitude 0)."""
    return build_problem(
        stations=[("a", LocalPoint(-BASELINE_M / 2, 0.0, 0.0)), ("b", LocalPoint(BASELINE_M / 2, 0.0, 0.0))],
        measurements=[Bearing("a", 0.0, None, SIGMA_RAD, None), Bearing("b", 0.0, None, SIGMA_RAD, None)],
        altitude_m=0.0, **kwargs)


def fields_equal(a, b) -> bool:
    return all(np.array_equal(getattr(a, f), getattr(b, f), equal_nan=True) for f in a.__dataclass_fields__)


def test_grid_is_square_around_the_centre_with_the_centre_a_cell():
    g = grid(two_stations(), (100.0, -200.0), 1000.0, 250.0, 0.0)
    assert g.shape == (9, 9)
    np.testing.assert_allclose(g.east_m, 100.0 + 250.0 * np.arange(-4, 5))
    np.testing.assert_allclose(g.north_m, -200.0 + 250.0 * np.arange(-4, 5))
    np.testing.assert_allclose(g.cells_enu_m[9 * 4 + 4], [100.0, -200.0, 0.0])
    assert cells_per_side(999.0, 250.0) == 7
    assert cells_per_side(1.0, 250.0) == 1
    with pytest.raises(ValueError):
        grid(two_stations(), (0.0, 0.0), 0.0, 10.0, 0.0)


def test_cells_at_the_stations_are_unobservable():
    problem = two_stations()
    stations = np.array([[-BASELINE_M / 2, 0.0, 0.0], [BASELINE_M / 2, 0.0, 0.0]])
    c = coverage_grid(problem, stations)
    assert not np.any(c.observable)
    assert np.all(np.isnan(c.cep50_m)) and np.all(np.isnan(c.gdop))


def test_broadside_cell_is_the_best_of_its_row():
    problem = two_stations()
    g = grid(problem, (0.0, 0.0), 20_000.0, 1000.0, 0.0)
    c = coverage_map(problem, g.cells_enu_m, chunk_cells=97)
    cep = c.cep50_m.reshape(g.shape)
    centre = np.flatnonzero(g.east_m == 0.0)[0]
    # broadside at least half a baseline out, the lines of sight cross at 90 degrees or less (closer in, a
    # cell nearer one station does better: its shorter range outweighs the wider crossing)
    rows = np.flatnonzero(np.abs(g.north_m) >= BASELINE_M / 2)
    assert rows.size == 32
    for row in rows:
        others = np.delete(cep[row], centre)
        assert cep[row, centre] < np.min(others), g.north_m[row]
    # the baseline itself (north 0) is collinear with both stations: no cell there is observable
    assert not np.any(c.observable.reshape(g.shape)[g.north_m == 0.0])


def test_each_cell_is_the_single_problem_bound():
    problem = two_stations()
    g = grid(problem, (0.0, 3000.0), 4000.0, 2000.0, 0.0)
    c = coverage_map(problem, g.cells_enu_m)
    for k in (0, 7, 24):
        bound = information_at(problem, g.cells_enu_m[k]).covariance_enu_m2[0]
        assert c.sqrt_trace_crlb_m[k] == pytest.approx(np.sqrt(np.trace(bound)), rel=1e-12)


def test_gdop_of_a_right_angle_crossing_is_sqrt_2():
    """Two lines of sight at 90 degrees, equal distance, equal sigma: H^T H = I, GDOP = sqrt(2)."""
    c = coverage_grid(two_stations(), [[0.0, BASELINE_M / 2, 0.0]])
    range_m = np.hypot(BASELINE_M / 2, BASELINE_M / 2)
    assert c.reference_sigma_m[0] == pytest.approx(SIGMA_RAD * range_m, rel=1e-9)
    assert c.gdop[0] == pytest.approx(np.sqrt(2.0), rel=1e-9)


def test_gdop_of_toa_is_the_gnss_pdop():
    """Four TOA stations in a square, the target above its centre (3D, emission time unknown): the
    position block of ((H|1)^T (H|1))^-1 with unit line-of-sight rows H, whatever the clock sigma."""
    corners = [(-1e4, -1e4, 0.0), (1e4, -1e4, 0.0), (1e4, 1e4, 0.0), (-1e4, 1e4, 0.0), (0.0, 0.0, 3e3)]
    stations = [(f"s{i}", LocalPoint(*xyz)) for i, xyz in enumerate(corners)]
    problem = build_problem(stations=stations, measurements=[TimeOfArrival(s, 0.0, 3e-8) for s, _ in stations])
    target = np.array([500.0, -300.0, 8000.0])
    c = coverage_grid(problem, target[None])
    lines = target - np.array(corners)
    h = np.hstack([lines / np.linalg.norm(lines, axis=1, keepdims=True), np.ones((5, 1))])
    pdop = np.sqrt(np.trace(np.linalg.inv(h.T @ h)[:3, :3]))
    assert c.reference_sigma_m[0] == pytest.approx(C_MPS * 3e-8, rel=1e-9)
    assert c.gdop[0] == pytest.approx(pdop, rel=1e-9)


def test_mixed_kinds_reference_is_the_information_mean():
    """A bearing (2 deg at 10 km: 349 m) and a range (100 m): sigma_ref = (mean r^-2)^-1/2."""
    problem = build_problem(stations=[("a", LocalPoint(0.0, 0.0, 0.0))],
                            measurements=[Bearing("a", 0.0, None, np.radians(2.0), None), Range("a", 0.0, 100.0)],
                            altitude_m=0.0)
    c = coverage_grid(problem, [[0.0, 10_000.0, 0.0]])
    r = np.array([np.radians(2.0) * 10_000.0, 100.0])
    assert c.reference_sigma_m[0] == pytest.approx(np.mean(r ** -2.0) ** -0.5, rel=1e-9)
    # orthogonal rows with metres-equivalent sigmas r: C = diag(r^2), trace = sum r^2
    assert c.gdop[0] == pytest.approx(np.sqrt(np.sum(r ** 2)) / c.reference_sigma_m[0], rel=1e-9)


def test_geodetic_cells_lie_at_the_altitude():
    origin = GeodeticPoint(np.radians(34.0), np.radians(108.0), 0.0)
    problem = build_problem(stations=[("a", LocalPoint(-5e4, 0.0, 0.0)), ("b", LocalPoint(5e4, 0.0, 0.0))],
                            measurements=[Bearing("a", 0.0, 0.0, SIGMA_RAD, SIGMA_RAD),
                                          Bearing("b", 0.0, 0.0, SIGMA_RAD, SIGMA_RAD)], origin=origin)
    g = grid(problem, (0.0, 0.0), 1e5, 5e4, 8000.0)
    _, _, alt = problem.frame.to_geodetic(g.cells_enu_m)
    np.testing.assert_allclose(alt, 8000.0, atol=1e-3)  # 1 mm
    assert g.cells_enu_m[0, 2] < 8000.0 - 1000.0  # the earth curves away 141 km from the origin


def test_chunks_and_stop():
    problem = two_stations()
    g = grid(problem, (0.0, 0.0), 5000.0, 500.0, 0.0)
    whole = coverage_grid(problem, g.cells_enu_m)
    seen = []
    chunked = coverage_map(ProblemBatch.from_problems([problem]), g.cells_enu_m, chunk_cells=10,
                           progress=lambda done, total: seen.append((done, total)))
    assert fields_equal(whole, chunked)
    assert seen[-1] == (45, 45)  # 21 x 21 cells
    with pytest.raises(Stopped):
        coverage_map(problem, g.cells_enu_m, chunk_cells=10, should_stop=lambda: True)


def test_dask_cluster_gives_the_same_map_bit_for_bit():
    distributed = pytest.importorskip("distributed")
    problem = two_stations()
    g = grid(problem, (0.0, 2000.0), 8000.0, 400.0, 0.0)
    here = coverage_map(problem, g.cells_enu_m, chunk_cells=64)
    with distributed.LocalCluster(n_workers=2, threads_per_worker=1, processes=False, dashboard_address=None) \
            as cluster, distributed.Client(cluster) as client:
        there = coverage_map(problem, g.cells_enu_m, chunk_cells=64, scheduler=client)
        by_address = coverage_map(problem, g.cells_enu_m, chunk_cells=64, scheduler=cluster.scheduler_address)
    assert fields_equal(here, there)
    assert fields_equal(here, by_address)
