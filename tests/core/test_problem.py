"""build_problem: the common frame, exact placement of stations and lines of sight, input validation."""

from __future__ import annotations

import numpy as np
import pymap3d
import pytest

from core import geodesy
from core.errors import InvalidInput
from core.measurements import Kind
from core.problem.build import Bearing, Range, TimeOfArrival, build_problem
from core.problem.frame import GeodeticPoint, LocalPoint

d2r = np.deg2rad
ONE_DEG = d2r(1.0)

# Three stations about 300 km apart and a target at 9 km; geodetic degrees and metres.
STATIONS_DEG = {"w": (47.0, 7.0, 500.0), "e": (47.3, 11.0, 800.0), "s": (45.2, 9.0, 150.0)}
TARGET_DEG = (46.4, 9.2, 9000.0)


def geodetic_stations():
    return [(sid, GeodeticPoint(d2r(la), d2r(lo), h)) for sid, (la, lo, h) in STATIONS_DEG.items()]


def bearings_by_pymap3d(target=TARGET_DEG):
    """Azimuth/elevation of the target at every station, computed by pymap3d (independent of core)."""
    out = []
    for sid, (la, lo, h) in STATIONS_DEG.items():
        az, el, _ = pymap3d.geodetic2aer(*target, la, lo, h)
        out.append(Bearing(sid, d2r(az), d2r(el), ONE_DEG, ONE_DEG))
    return out


def test_geodetic_stations_sit_where_pymap3d_puts_them_in_the_centroid_frame():
    problem = build_problem(geodetic_stations(), bearings_by_pymap3d())
    origin = problem.frame.origin
    assert origin.alt_m == 0.0
    # The origin is the ECEF centroid pushed to the ellipsoid: the centroid lies on its normal.
    centroid = np.mean([geodesy.geodetic_to_ecef(*d2r([la, lo]), 0.0) for la, lo, _ in STATIONS_DEG.values()], axis=0)
    in_frame = geodesy.ecef_to_enu(centroid, origin.lat_rad, origin.lon_rad, 0.0)
    np.testing.assert_allclose(in_frame[:2], 0.0, rtol=0, atol=1e-6)  # 1 micrometre off the normal
    for k, (la, lo, h) in enumerate(STATIONS_DEG.values()):
        expected = pymap3d.geodetic2enu(la, lo, h, np.rad2deg(origin.lat_rad), np.rad2deg(origin.lon_rad), 0.0)
        np.testing.assert_allclose(problem.stations_enu_m[k], expected, rtol=0, atol=1e-6)  # 1 micrometre


def test_lines_of_sight_in_the_common_frame_pass_through_the_target():
    """Bearings measured in each station's own ENU, rotated exactly: every line hits the target."""
    problem = build_problem(geodetic_stations(), bearings_by_pymap3d())
    target = problem.frame.from_geodetic(d2r(TARGET_DEG[0]), d2r(TARGET_DEG[1]), TARGET_DEG[2])
    los = problem.lines_of_sight()
    u = los.directions_enu()
    np.testing.assert_allclose(np.linalg.norm(u, axis=-1), 1.0, rtol=0, atol=1e-15)
    to_target = target - los.origins_enu_m
    miss = np.linalg.norm(to_target - np.einsum("ki,ki->k", to_target, u)[:, None] * u, axis=-1)
    assert np.all(miss < 1e-6)  # 1 micrometre at 150-200 km
    # Without the per-station rotation (flat earth) the same lines miss by kilometres.
    flat = np.stack([np.sin(los.azimuth_rad) * np.cos(los.elevation_rad),
                     np.cos(los.azimuth_rad) * np.cos(los.elevation_rad), np.sin(los.elevation_rad)], axis=-1)
    flat_miss = np.linalg.norm(to_target - np.einsum("ki,ki->k", to_target, flat)[:, None] * flat, axis=-1)
    assert np.max(flat_miss) > 1000.0


def test_local_stations_with_an_origin_match_the_same_geodetic_stations():
    geodetic = build_problem(geodetic_stations(), bearings_by_pymap3d())
    origin = geodetic.frame.origin
    local = [(sid, LocalPoint(*pos)) for sid, pos in zip(geodetic.station_ids, geodetic.stations_enu_m)]
    placed = build_problem(local, bearings_by_pymap3d(), origin=origin)
    np.testing.assert_allclose(placed.stations_enu_m, geodetic.stations_enu_m, rtol=0, atol=0)
    np.testing.assert_allclose(placed.station_rotations, geodetic.station_rotations,
                               rtol=0, atol=1e-12)  # 1e-12 rad: round-off through geodetic
    # And the stations' frames are really tilted (300 km apart is ~3 deg of earth).
    tilt = np.arccos(np.clip(placed.station_rotations[:, 2, 2], -1, 1))
    assert np.max(tilt) > d2r(1.0)


def test_local_stations_without_origin_share_the_plane_axes():
    problem = build_problem([("a", LocalPoint(0, 0, 0)), ("b", LocalPoint(300e3, 0, 0))],
                            [Bearing("a", 0.3, 0.1, ONE_DEG, ONE_DEG), Bearing("b", -0.3, None, ONE_DEG)])
    assert not problem.frame.is_geodetic
    np.testing.assert_array_equal(problem.station_rotations, np.broadcast_to(np.eye(3), (2, 3, 3)))


def test_scalar_layout_of_mixed_measurements():
    stations = [("a", LocalPoint(0, 0, 0)), ("b", LocalPoint(1000, 0, 0))]
    measurements = [
        Bearing("b", 0.5, None, ONE_DEG),
        Range("a", 1500.0, 10.0),
        Bearing("a", 0.2, 0.05, ONE_DEG, 2 * ONE_DEG),
        TimeOfArrival("b", 12.000183, 1e-8),
        TimeOfArrival("a", 12.000180, 2e-8),
    ]
    problem = build_problem(stations, measurements)
    np.testing.assert_array_equal(problem.kinds, [Kind.AZIMUTH, Kind.RANGE, Kind.AZIMUTH, Kind.ELEVATION,
                                                  Kind.TOA, Kind.TOA])
    np.testing.assert_array_equal(problem.station_index, [1, 0, 0, 0, 1, 0])
    np.testing.assert_array_equal(problem.source_index, [0, 1, 2, 2, 3, 4])
    np.testing.assert_array_equal(problem.bearing_index, [0, -1, 1, 1, -1, -1])
    np.testing.assert_allclose(problem.sigmas[:4], [ONE_DEG, 10.0, ONE_DEG, 2 * ONE_DEG], rtol=0, atol=0)
    # TOAs are kept relative to the earliest one, so the model never sees the 12 s epoch.
    assert problem.toa_reference_s == 12.000180
    # 12.000183 s is stored to ~2e-15 s (its float64 spacing), i.e. ~0.5 micrometre of light travel.
    np.testing.assert_allclose(problem.values[4:], [3e-6, 0.0], rtol=0, atol=1e-14)  # 10 fs, 3 micrometres
    np.testing.assert_allclose(problem.model_values()[4:], [899.377374, 0.0], rtol=0, atol=3e-6)  # 3 micrometres
    los = problem.lines_of_sight()
    assert los.count == 2
    np.testing.assert_array_equal(los.has_elevation, [False, True])


def test_centroid_origin_across_the_antimeridian():
    stations = [("a", GeodeticPoint(d2r(-17.0), d2r(179.8), 0.0)), ("b", GeodeticPoint(d2r(-17.0), d2r(-179.8), 0.0))]
    problem = build_problem(stations, [Bearing("a", 1.0, None, ONE_DEG), Bearing("b", 2.0, None, ONE_DEG)])
    assert abs(abs(problem.frame.origin.lon_rad) - np.pi) < 1e-12
    # The two stations are ~43 km apart, symmetric about the origin, not half a world away.
    np.testing.assert_allclose(problem.stations_enu_m[0, 0], -problem.stations_enu_m[1, 0], rtol=1e-9)
    assert 40e3 < np.linalg.norm(problem.stations_enu_m[0] - problem.stations_enu_m[1]) < 45e3


# --- validation -----------------------------------------------------------

LOCAL = [("a", LocalPoint(0, 0, 0)), ("b", LocalPoint(1000, 0, 0))]
GOOD = Bearing("a", 0.1, None, ONE_DEG)


@pytest.mark.parametrize("stations, measurements, loc", [
    (LOCAL, [GOOD, Bearing("zz", 0.1, None, ONE_DEG)], ("measurements", 1, "station_id")),
    (LOCAL + [("a", LocalPoint(5, 5, 5))], [GOOD], ("stations", 2, "id")),
    (LOCAL, [GOOD, Bearing("b", 0.1, None, 0.0)], ("measurements", 1, "sigma_azimuth_rad")),
    (LOCAL, [Bearing("b", 0.1, None, -ONE_DEG)], ("measurements", 0, "sigma_azimuth_rad")),
    (LOCAL, [Bearing("b", 0.1, None, float("nan"))], ("measurements", 0, "sigma_azimuth_rad")),
    (LOCAL, [GOOD, Bearing("b", 0.1, 0.2, ONE_DEG, 0.0)], ("measurements", 1, "sigma_elevation_rad")),
    (LOCAL, [Bearing("b", 0.1, 0.2, ONE_DEG, None)], ("measurements", 0, "sigma_elevation_rad")),
    (LOCAL, [GOOD, Range("b", 100.0, 0.0)], ("measurements", 1, "sigma_m")),
    (LOCAL, [GOOD, Range("b", 100.0, -1.0)], ("measurements", 1, "sigma_m")),
    (LOCAL, [GOOD, Range("b", -5.0, 1.0)], ("measurements", 1, "range_m")),
    (LOCAL, [GOOD, TimeOfArrival("b", 1.0, 0.0)], ("measurements", 1, "sigma_s")),
    (LOCAL, [GOOD, TimeOfArrival("b", float("nan"), 1e-9)], ("measurements", 1, "toa_s")),
    (LOCAL, [Bearing("a", float("nan"), None, ONE_DEG)], ("measurements", 0, "azimuth_rad")),
    (LOCAL, [Bearing("a", 0.1, float("inf"), ONE_DEG, ONE_DEG)], ("measurements", 0, "elevation_rad")),
    (LOCAL, [Bearing("a", 0.1, d2r(91.0), ONE_DEG, ONE_DEG)], ("measurements", 0, "elevation_rad")),
    (LOCAL, [Bearing("a", 0.1, None, None)], ("measurements", 0, "sigma_azimuth_rad")),
    (LOCAL, [], ("measurements",)),
    ([], [GOOD], ("stations",)),
    ([("a", GeodeticPoint(d2r(91.0), 0.0, 0.0))], [GOOD], ("stations", 0, "position", "lat_rad")),
    ([("b", GeodeticPoint(0.0, 0.0, 0.0)), ("a", GeodeticPoint(d2r(-91.0), 0.0, 0.0))], [GOOD],
     ("stations", 1, "position", "lat_rad")),
    ([("a", GeodeticPoint(float("nan"), 0.0, 0.0))], [GOOD], ("stations", 0, "position", "lat_rad")),
    ([("a", GeodeticPoint(0.0, float("inf"), 0.0))], [GOOD], ("stations", 0, "position", "lon_rad")),
    ([("a", GeodeticPoint(0.0, 0.0, float("nan")))], [GOOD], ("stations", 0, "position", "alt_m")),
    ([("a", LocalPoint(0.0, float("nan"), 0.0))], [GOOD], ("stations", 0, "position", "north_m")),
    ([("a", GeodeticPoint(0.0, 0.0, 0.0)), ("b", LocalPoint(0, 0, 0))], [GOOD], ("stations", 1, "position")),
], ids=["unknown-id", "duplicate-id", "sigma-zero", "sigma-negative", "sigma-nan", "sigma-el-zero",
        "sigma-el-missing", "sigma-range-zero", "sigma-range-negative", "range-negative", "sigma-toa-zero",
        "toa-nan", "azimuth-nan", "elevation-inf", "elevation-91", "sigma-missing", "no-measurements",
        "no-stations", "lat-91", "lat-minus-91", "lat-nan", "lon-inf", "alt-nan", "local-nan", "mixed-frames"])
def test_invalid_input_names_the_field(stations, measurements, loc):
    with pytest.raises(InvalidInput) as caught:
        build_problem(stations, measurements)
    assert caught.value.loc == loc
    assert caught.value.code == "invalid_input"


def test_invalid_constraint_and_initial_guess_name_their_fields():
    with pytest.raises(InvalidInput) as caught:
        build_problem(LOCAL, [GOOD], altitude_m=float("nan"))
    assert caught.value.loc == ("altitude_m",)
    with pytest.raises(InvalidInput) as caught:
        build_problem(LOCAL, [GOOD], initial_guess=LocalPoint(0.0, 0.0, float("inf")))
    assert caught.value.loc == ("initial_guess", "up_m")
    with pytest.raises(InvalidInput) as caught:
        build_problem(LOCAL, [GOOD], initial_guess=GeodeticPoint(0.1, 0.2, 0.0))
    assert caught.value.loc == ("initial_guess",)


def test_latitude_exactly_at_the_poles_is_valid():
    stations = [("n", GeodeticPoint(np.pi / 2, 0.0, 0.0)), ("s", GeodeticPoint(d2r(89.0), d2r(45.0), 0.0))]
    problem = build_problem(stations, [Bearing("n", 0.1, None, ONE_DEG)])
    assert np.all(np.isfinite(problem.stations_enu_m))
    assert np.all(np.isfinite(problem.station_rotations))


def test_bearing_sigma_may_be_omitted_only_when_allowed():
    problem = build_problem(LOCAL, [Bearing("a", 0.1, None, None)], require_sigmas=False)
    assert np.isnan(problem.sigmas[0])


def test_leave_one_out_lists_each_problems_most_suspect_request_measurements_first():
    from core.problem.batch import ProblemBatch

    stations = [(f"s{k}", LocalPoint(1e3 * k, 5e2 * k * k, 0.0)) for k in range(4)]
    bearings = [Bearing(sid, 0.1 * k, 0.01, 0.01, 0.01) for k, (sid, _) in enumerate(stations)]
    batch = ProblemBatch.from_problems([build_problem(stations, bearings),
                                        build_problem(stations, bearings[:3] + [Range("s3", 2e3, 5.0)])])
    # Rows: azimuth and elevation of each bearing (request measurements 0-3); problem 1 ends with a range.
    suspicion = np.array([[0.5, 3.0, 0.1, 0.2, 2.0, 0.0, 1.0, np.nan],
                          [0.1, 0.2, 4.0, 0.0, 0.3, 0.3, 9.0, 0.0]])
    used = batch.valid.copy()
    used[0, [6, 7]] = False  # problem 0's last bearing is already out
    owners, dropped = batch.leave_one_out(np.array([0, 1]), used, suspicion, 2)
    assert owners.tolist() == [0, 0, 1, 1]
    left_out = [sorted(set(batch.source_index[b, d].tolist())) for b, d in zip(owners, dropped)]
    assert left_out == [[0], [2], [3], [1]]  # by each one's largest row; a bearing's two rows go together
    assert not (dropped & ~used[owners]).any()


def test_problems_placed_in_one_batch_are_those_placed_one_by_one():
    """build_problems of checked inputs gives each problem exactly as build_problem does on its own (same
    frame, same bits), whatever the other problems of the batch hold."""
    from core.problem.build import build_problems, checked_inputs

    local = [("a", LocalPoint(0.0, 0.0, 0.0)), ("b", LocalPoint(5_000.0, 1_000.0, 20.0))]
    cases = [
        (geodetic_stations(), bearings_by_pymap3d(), {}),
        (local, [Range("a", 4_000.0, 5.0), TimeOfArrival("a", 2.0e-5, 1e-9), TimeOfArrival("b", 3.0e-5, 1e-9)],
         {"origin": GeodeticPoint(d2r(46.0), d2r(8.0), 300.0)}),
        (geodetic_stations()[:2], [Bearing("e", 0.4, None, ONE_DEG)], {"altitude_m": 1_000.0}),
    ]
    batch = build_problems([checked_inputs(stations, measurements, **options)
                            for stations, measurements, options in cases])
    for b, (stations, measurements, options) in enumerate(cases):
        alone, placed = build_problem(stations, measurements, **options), batch.problem(b)
        assert placed.frame == alone.frame and placed.station_ids == alone.station_ids
        for name in ("stations_enu_m", "station_rotations", "kinds", "station_index", "values", "sigmas",
                     "bearing_index", "source_index"):
            assert np.array_equal(getattr(placed, name), getattr(alone, name)), name
        assert placed.toa_reference_s == alone.toa_reference_s and placed.altitude_m == alone.altitude_m


def test_one_point_of_a_frame_matches_the_broadcast_path_bit_for_bit():
    """CommonFrame's one-point local axes and geodetic position (compiled, on the frame's placement made once)
    equal the broadcast functions' for the same point, in a geodetic and in a flat frame."""
    from core.problem.frame import CommonFrame, local_axes

    frame = CommonFrame(GeodeticPoint(d2r(46.0), d2r(8.0), 300.0))
    points = np.random.default_rng(3).normal(scale=80_000.0, size=(50, 3))
    for point in points:
        assert np.array_equal(frame.local_axes(point), local_axes(point, frame.origin_array(), True))
        assert frame.to_geodetic(point) == geodesy.ecef_to_geodetic(frame.to_ecef(point))
    assert np.array_equal(frame.local_axes(points), local_axes(points, frame.origin_array(), True))
    assert np.array_equal(CommonFrame(None).local_axes(points[0]), np.eye(3))
