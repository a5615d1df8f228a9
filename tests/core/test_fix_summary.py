"""``core.fix_summary.summarise_fixes``: a geodetic fix summarised in the axes at the fix, a flat one in its own."""

from __future__ import annotations

import numpy as np

from core import geodesy
from core.error_summary import error_summary
from core.estimators import SolveOptions, solve_many
from core.fix_summary import summarise_fixes
from core.problem.batch import ProblemBatch
from core.problem.build import Bearing, build_problem
from core.problem.frame import GeodeticPoint, LocalPoint


def _bearings(names, stations_enu_m, target_enu_m) -> list[Bearing]:
    """Exact bearings (azimuth and elevation, 1 mrad sigmas) of the target from each station, in one ENU frame."""
    out = []
    for name, station in zip(names, stations_enu_m):
        d = target_enu_m - station
        out.append(Bearing(name, float(np.arctan2(d[0], d[1])), float(np.arctan2(d[2], np.hypot(d[0], d[1]))),
                           1e-3, 1e-3))
    return out


def test_a_geodetic_fix_is_placed_on_the_earth_and_its_covariance_turned_to_the_axes_at_the_fix():
    stations = [(name, GeodeticPoint(0.6 + 2e-3 * k, 1.9 + 2e-3 * (k % 2), 100.0)) for k, name in enumerate("abcd")]
    seed = build_problem(stations, [Bearing("a", 0.0, 0.0, 1e-3, 1e-3), Bearing("b", 1.0, 0.0, 1e-3, 1e-3)])
    frame = seed.frame
    target = np.array([30_000.0, 40_000.0, 2_000.0])  # far enough from the centroid that the axes turn
    measurements = _bearings("abcd", seed.stations_enu_m, target)
    local = [(name, LocalPoint(*xyz)) for name, xyz in zip("abcd", seed.stations_enu_m)]
    problems = [build_problem(stations, measurements), build_problem(local, measurements)]
    batch = ProblemBatch.from_problems(problems)
    ((_, fixes),) = solve_many(batch, ["ml", "ml"], [SolveOptions(), SolveOptions()])
    summary = summarise_fixes(fixes)

    lat, lon, alt = frame.to_geodetic(fixes.position_enu_m[0])
    assert np.allclose(summary.position_geodetic[0], [lat, lon, alt], rtol=0, atol=1e-9)
    assert np.allclose(summary.position_ecef_m[0], geodesy.geodetic_to_ecef(lat, lon, alt), rtol=0, atol=1e-6)
    at_fix = geodesy.covariances_to_points(fixes.covariance_enu_m2[:1], np.array([lat]), np.array([lon]),
                                           frame.ecef_to_enu_rotation)
    assert np.allclose(summary.covariance_enu_m2[0], at_fix[0], rtol=1e-12, atol=0)
    assert not np.allclose(summary.covariance_enu_m2[0], fixes.covariance_enu_m2[0], rtol=1e-6, atol=0)
    # A flat frame has one set of axes: its covariance is the fix's own.
    assert np.array_equal(summary.covariance_enu_m2[1], fixes.covariance_enu_m2[1])
    # The error figures are of the covariance in those axes.
    expected = error_summary(summary.covariance_enu_m2)
    assert np.allclose(summary.error.cep50_m, expected.cep50_m, rtol=1e-12, atol=0)
    assert np.allclose(summary.error.ellipse_orientation_rad, expected.ellipse_orientation_rad, rtol=0, atol=1e-12)
