"""WGS84 geodesy: reference values at the hard places, round trips, frame rotations.

References are computed here from a and f alone (closed forms at the poles,
the equator and along a meridian), and pyproj serves as an independent
cross-check where its own accuracy is known to be good (low altitude).
"""

from __future__ import annotations

import numpy as np
import pyproj
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from core import geodesy
from core.problem.frame import CommonFrame, GeodeticPoint

A = 6378137.0
F = 1.0 / 298.257223563
B = A * (1.0 - F)
E2 = F * (2.0 - F)
GEO_ALTITUDE_M = 20_000e3

d2r = np.deg2rad

latitudes = st.floats(-90.0, 90.0)
polar_latitudes = st.floats(89.9, 90.0) | st.floats(-90.0, -89.9)
longitudes = st.floats(-180.0, 180.0)
altitudes = st.floats(-10e3, GEO_ALTITUDE_M)


def ecef_by_hand(lat_deg, lon_deg, alt_m):
    """Textbook geodetic -> ECEF from a and f (prime-vertical radius N)."""
    lat, lon = d2r(lat_deg), d2r(lon_deg)
    n = A / np.sqrt(1.0 - E2 * np.sin(lat) ** 2)
    return np.array([(n + alt_m) * np.cos(lat) * np.cos(lon),
                     (n + alt_m) * np.cos(lat) * np.sin(lon),
                     (n * (1.0 - E2) + alt_m) * np.sin(lat)])


def distance_m(lat1_rad, lon1_rad, alt1_m, lat2_rad, lon2_rad, alt2_m):
    """Euclidean distance between two geodetic points, via the hand-written formula."""
    p1 = ecef_by_hand(np.rad2deg(lat1_rad), np.rad2deg(lon1_rad), alt1_m)
    p2 = ecef_by_hand(np.rad2deg(lat2_rad), np.rad2deg(lon2_rad), alt2_m)
    return float(np.linalg.norm(p1 - p2))


# --- reference values -------------------------------------------------------

REFERENCE_POINTS = [
    # lat_deg, lon_deg, alt_m, expected ECEF (closed forms from a and f)
    (0.0, 0.0, 0.0, (A, 0.0, 0.0)),
    (0.0, 90.0, 0.0, (0.0, A, 0.0)),
    (0.0, -90.0, 1000.0, (0.0, -(A + 1000.0), 0.0)),
    (0.0, 180.0, 0.0, (-A, 0.0, 0.0)),
    (0.0, -180.0, 0.0, (-A, 0.0, 0.0)),
    (90.0, 0.0, 0.0, (0.0, 0.0, B)),
    (-90.0, 0.0, 0.0, (0.0, 0.0, -B)),
    (90.0, 123.0, GEO_ALTITUDE_M, (0.0, 0.0, B + GEO_ALTITUDE_M)),
    (0.0, 0.0, GEO_ALTITUDE_M, (A + GEO_ALTITUDE_M, 0.0, 0.0)),
    (0.0, 180.0, GEO_ALTITUDE_M, (-(A + GEO_ALTITUDE_M), 0.0, 0.0)),
]


@pytest.mark.parametrize("lat_deg, lon_deg, alt_m, expected", REFERENCE_POINTS)
def test_geodetic_to_ecef_closed_forms(lat_deg, lon_deg, alt_m, expected):
    got = geodesy.geodetic_to_ecef(d2r(lat_deg), d2r(lon_deg), alt_m)
    np.testing.assert_allclose(got, expected, rtol=0, atol=1e-6)  # 1 micrometre


@pytest.mark.parametrize("lat_deg, lon_deg, alt_m, expected", REFERENCE_POINTS)
def test_ecef_to_geodetic_closed_forms(lat_deg, lon_deg, alt_m, expected):
    lat, lon, alt = geodesy.ecef_to_geodetic(np.array(expected))
    assert alt == pytest.approx(alt_m, abs=1e-6)  # 1 micrometre
    # Latitude error times the distance from the geocentre is a length.
    assert abs(lat - d2r(lat_deg)) * (A + alt_m) < 1e-6  # 1 micrometre
    if abs(lat_deg) < 90.0:  # longitude is arbitrary at a pole
        wrapped = np.angle(np.exp(1j * (lon - d2r(lon_deg))))
        assert abs(wrapped) * (A + alt_m) < 1e-6  # 1 micrometre


@pytest.mark.parametrize("lat_deg", [-89.0, -45.0, -10.0, 30.0, 45.0, 60.0, 89.9])
@pytest.mark.parametrize("alt_m", [-1000.0, 0.0, 10e3, 400e3, GEO_ALTITUDE_M])
def test_along_a_meridian_against_the_textbook_formula(lat_deg, alt_m):
    expected = ecef_by_hand(lat_deg, 37.0, alt_m)
    np.testing.assert_allclose(geodesy.geodetic_to_ecef(d2r(lat_deg), d2r(37.0), alt_m),
                               expected, rtol=0, atol=1e-6)  # 1 micrometre
    lat, lon, alt = geodesy.ecef_to_geodetic(expected)
    assert alt == pytest.approx(alt_m, abs=1e-6)  # 1 micrometre
    assert abs(lat - d2r(lat_deg)) * (A + alt_m) < 1e-6  # 1 micrometre
    assert abs(lon - d2r(37.0)) * (A + alt_m) < 1e-6  # 1 micrometre


def test_pole_latitude_and_altitude_from_ecef_axis():
    """Any point on the polar axis is at latitude +-90 and altitude |z| - b."""
    for z in [B - 1000.0, B, B + 1.0, B + 35_786e3]:
        for sign in (1.0, -1.0):
            lat, _, alt = geodesy.ecef_to_geodetic(np.array([0.0, 0.0, sign * z]))
            assert lat == pytest.approx(sign * np.pi / 2, abs=1e-15)  # exact to round-off
            assert alt == pytest.approx(z - B, abs=1e-6)  # 1 micrometre


def test_antimeridian_plus_and_minus_180_are_the_same_place():
    east = geodesy.geodetic_to_ecef(d2r(12.5), d2r(180.0), 300.0)
    west = geodesy.geodetic_to_ecef(d2r(12.5), d2r(-180.0), 300.0)
    np.testing.assert_allclose(east, west, rtol=0, atol=1e-6)  # 1 micrometre
    _, lon, _ = geodesy.ecef_to_geodetic(east)
    assert abs(abs(lon) - np.pi) < 1e-15  # exactly the antimeridian, either sign


def test_enu_across_the_antimeridian():
    """1/1000 deg east of the antimeridian, seen from it: a short step east, not 40,000 km."""
    step = d2r(1e-3)
    enu = geodesy.geodetic_to_enu(0.0, -np.pi + step, 0.0, 0.0, np.pi, 0.0)
    expected = [A * np.sin(step), 0.0, A * (np.cos(step) - 1.0)]
    np.testing.assert_allclose(enu, expected, rtol=0, atol=1e-6)  # 1 micrometre
    assert 100.0 < enu[0] < 120.0  # about 111 m east


def test_enu_closed_forms_on_the_equator_and_at_a_pole():
    # From (0, 0) the point at longitude 90 deg is a east and a down.
    enu = geodesy.geodetic_to_enu(0.0, d2r(90.0), 0.0, 0.0, 0.0, 0.0)
    np.testing.assert_allclose(enu, [A, 0.0, -A], rtol=0, atol=1e-6)  # 1 micrometre
    # Straight above a point along the ellipsoid normal is pure "up", at any height.
    for lat_deg, lon_deg in [(90.0, 0.0), (-90.0, 0.0), (0.0, 180.0), (51.5, -0.1), (-33.9, 151.2)]:
        enu = geodesy.geodetic_to_enu(d2r(lat_deg), d2r(lon_deg), GEO_ALTITUDE_M, d2r(lat_deg), d2r(lon_deg), 0.0)
        np.testing.assert_allclose(enu, [0.0, 0.0, GEO_ALTITUDE_M], rtol=0, atol=1e-6)  # 1 micrometre
    # From the north pole (lon 0) the equator at lon 0 lies to the south (-north) and below.
    enu = geodesy.geodetic_to_enu(0.0, 0.0, 0.0, d2r(90.0), 0.0, 0.0)
    np.testing.assert_allclose(enu, [0.0, -A, -B], rtol=0, atol=1e-6)  # 1 micrometre


def test_pyproj_cross_check_at_low_altitude():
    rng = np.random.default_rng(7)
    lat = rng.uniform(-90, 90, 2000)
    lon = rng.uniform(-180, 180, 2000)
    alt = rng.uniform(-500.0, 12e3, 2000)
    forward = pyproj.Transformer.from_crs("EPSG:4979", "EPSG:4978", always_xy=True)
    inverse = pyproj.Transformer.from_crs("EPSG:4978", "EPSG:4979", always_xy=True)
    x, y, z = forward.transform(lon, lat, alt)
    ours = geodesy.geodetic_to_ecef(d2r(lat), d2r(lon), alt)
    np.testing.assert_allclose(ours, np.stack([x, y, z], axis=-1), rtol=0, atol=1e-6)  # 1 micrometre
    lon_p, lat_p, alt_p = inverse.transform(x, y, z)
    lat_o, lon_o, alt_o = geodesy.ecef_to_geodetic(np.stack([x, y, z], axis=-1))
    # pyproj's own inverse is good to a few micrometres at these heights.
    np.testing.assert_allclose(alt_o, alt_p, rtol=0, atol=1e-5)  # 10 micrometres
    np.testing.assert_allclose((lat_o - d2r(lat_p)) * A, 0.0, rtol=0, atol=1e-5)  # 10 micrometres


# --- round trips (property tests) -----------------------------------------

@settings(max_examples=300, deadline=None)
@given(lat=latitudes | polar_latitudes, lon=longitudes, alt=altitudes)
def test_geodetic_ecef_geodetic_round_trip(lat, lon, alt):
    ecef = geodesy.geodetic_to_ecef(d2r(lat), d2r(lon), alt)
    lat2, lon2, alt2 = geodesy.ecef_to_geodetic(ecef)
    assert abs(alt2 - alt) < 1e-6  # 1 micrometre
    # Compare positions, not angles: longitude is meaningless at the pole.
    assert distance_m(d2r(lat), d2r(lon), alt, lat2, lon2, alt2) < 1e-6  # 1 micrometre


@settings(max_examples=300, deadline=None)
@given(lat=latitudes | polar_latitudes, lon=longitudes, alt=altitudes,
       o_lat=latitudes | polar_latitudes, o_lon=longitudes, o_alt=st.floats(-500.0, 10e3))
def test_ecef_enu_ecef_round_trip(lat, lon, alt, o_lat, o_lon, o_alt):
    ecef = geodesy.geodetic_to_ecef(d2r(lat), d2r(lon), alt)
    enu = geodesy.ecef_to_enu(ecef, d2r(o_lat), d2r(o_lon), o_alt)
    back = geodesy.enu_to_ecef(enu, d2r(o_lat), d2r(o_lon), o_alt)
    assert np.linalg.norm(back - ecef) < 1e-6  # 1 micrometre
    # ENU is a rigid motion of ECEF: distances from the origin are kept.
    origin = geodesy.geodetic_to_ecef(d2r(o_lat), d2r(o_lon), o_alt)
    assert abs(np.linalg.norm(enu) - np.linalg.norm(ecef - origin)) < 1e-6  # 1 micrometre


@settings(max_examples=200, deadline=None)
@given(lat=latitudes | polar_latitudes, lon=longitudes, alt=altitudes,
       o_lat=latitudes, o_lon=longitudes)
def test_enu_geodetic_round_trip(lat, lon, alt, o_lat, o_lon):
    enu = geodesy.geodetic_to_enu(d2r(lat), d2r(lon), alt, d2r(o_lat), d2r(o_lon), 0.0)
    lat2, lon2, alt2 = geodesy.enu_to_geodetic(enu, d2r(o_lat), d2r(o_lon), 0.0)
    assert abs(alt2 - alt) < 1e-6  # 1 micrometre
    assert distance_m(d2r(lat), d2r(lon), alt, lat2, lon2, alt2) < 1e-6  # 1 micrometre


def test_batched_round_trip_matches_scalar_calls():
    rng = np.random.default_rng(3)
    lat = d2r(rng.uniform(-90, 90, (4, 5)))
    lon = d2r(rng.uniform(-180, 180, (4, 5)))
    alt = rng.uniform(0, GEO_ALTITUDE_M, (4, 5))
    ecef = geodesy.geodetic_to_ecef(lat, lon, alt)
    assert ecef.shape == (4, 5, 3)
    lat2, lon2, alt2 = geodesy.ecef_to_geodetic(ecef)
    assert lat2.shape == (4, 5)
    for i, j in [(0, 0), (3, 4), (2, 1)]:
        single = geodesy.geodetic_to_ecef(lat[i, j], lon[i, j], alt[i, j])
        np.testing.assert_allclose(ecef[i, j], single, rtol=0, atol=1e-9)  # 1 nanometre
    np.testing.assert_allclose(alt2, alt, rtol=0, atol=1e-6)  # 1 micrometre


# --- rotations ---------------------------------------------------------------

@settings(max_examples=200, deadline=None)
@given(lat=latitudes | polar_latitudes, lon=longitudes)
def test_enu_rotation_is_proper_orthonormal(lat, lon):
    r = geodesy.ecef_to_enu_rotation(d2r(lat), d2r(lon))
    np.testing.assert_allclose(r @ r.T, np.eye(3), rtol=0, atol=1e-14)  # round-off of unit vectors
    assert np.linalg.det(r) == pytest.approx(1.0, abs=1e-14)  # right-handed, not a reflection


@pytest.mark.parametrize("lat_deg, lon_deg", [(0.0, 0.0), (45.0, 30.0), (-60.0, -120.0), (89.99, 180.0),
                                              (-89.99, -180.0), (10.0, 179.999)])
def test_enu_axes_are_the_geodetic_partial_derivatives(lat_deg, lon_deg):
    """East, north and up are d(ECEF)/d(lon), d/d(lat), d/d(alt), normalised (finite differences)."""
    lat, lon, h, step = d2r(lat_deg), d2r(lon_deg), 1000.0, 1e-7
    r = geodesy.ecef_to_enu_rotation(lat, lon)

    def unit(v):
        return v / np.linalg.norm(v)

    east = unit(geodesy.geodetic_to_ecef(lat, lon + step, h) - geodesy.geodetic_to_ecef(lat, lon - step, h))
    north = unit(geodesy.geodetic_to_ecef(lat + step, lon, h) - geodesy.geodetic_to_ecef(lat - step, lon, h))
    up = unit(geodesy.geodetic_to_ecef(lat, lon, h + 1.0) - geodesy.geodetic_to_ecef(lat, lon, h - 1.0))
    # Central differences with a 1e-7 rad step: direction error ~1e-9 rad.
    np.testing.assert_allclose(r, np.stack([east, north, up]), rtol=0, atol=1e-7)  # 0.1 microradian
    # Up is the ellipsoid normal, the gradient of x^2/a^2 + y^2/a^2 + z^2/b^2.
    x, y, z = geodesy.geodetic_to_ecef(lat, lon, 0.0)
    np.testing.assert_allclose(r[2], unit(np.array([x / A**2, y / A**2, z / B**2])), rtol=0, atol=1e-12)


def test_covariance_rotation_round_trip_and_consistency_with_points():
    """C_enu = R C_ecef R^T, both ways, and the same as the covariance of rotated samples."""
    rng = np.random.default_rng(11)
    frame = CommonFrame(GeodeticPoint(d2r(-33.0), d2r(151.0), 50.0))
    root = rng.normal(size=(3, 3)) * [100.0, 20.0, 5.0]
    cov_enu = root @ root.T
    cov_ecef = frame.covariance_to_ecef(cov_enu)
    r = frame.ecef_to_enu_rotation
    np.testing.assert_allclose(r @ cov_ecef @ r.T, cov_enu, rtol=0, atol=1e-9)  # 1e-9 m^2 on ~1e4 m^2
    assert np.trace(cov_ecef) == pytest.approx(np.trace(cov_enu), rel=1e-12)  # rotation keeps the trace
    # Points: the sample covariance of the ECEF images of ENU samples is the rotated one.
    samples = rng.normal(size=(500, 3)) @ root.T
    ecef = frame.to_ecef(samples)
    np.testing.assert_allclose(np.cov(ecef.T), frame.covariance_to_ecef(np.cov(samples.T)),
                               rtol=0, atol=1e-6)  # 1e-6 m^2: round-off of 6.4e6 m coordinates


@settings(max_examples=200, deadline=None)
@given(a_lat=latitudes, a_lon=longitudes, b_lat=latitudes | polar_latitudes, b_lon=longitudes)
def test_enu_to_enu_rotation_agrees_with_going_through_ecef(a_lat, a_lon, b_lat, b_lon):
    a_lat, a_lon, b_lat, b_lon = d2r([a_lat, a_lon, b_lat, b_lon])
    rotation = geodesy.enu_to_enu_rotation(a_lat, a_lon, b_lat, b_lon)
    # Two points, expressed in ENU at A and at B; their difference rotates with R_{A->B}.
    p = geodesy.geodetic_to_ecef(np.array([0.3, -0.2]), np.array([1.0, 2.5]), np.array([1e3, 5e5]))
    in_a = geodesy.ecef_to_enu(p, a_lat, a_lon, 0.0)
    in_b = geodesy.ecef_to_enu(p, b_lat, b_lon, 0.0)
    np.testing.assert_allclose(rotation @ (in_a[1] - in_a[0]), in_b[1] - in_b[0],
                               rtol=0, atol=1e-6)  # 1 micrometre
    # A line of sight measured in A's ENU: rotating it must match pushing a point along it.
    direction_a = np.array([0.6, 0.0, 0.8])
    tip_b = geodesy.ecef_to_enu(geodesy.enu_to_ecef(1e5 * direction_a, a_lat, a_lon, 0.0), b_lat, b_lon, 0.0)
    base_b = geodesy.ecef_to_enu(geodesy.enu_to_ecef(np.zeros(3), a_lat, a_lon, 0.0), b_lat, b_lon, 0.0)
    np.testing.assert_allclose(rotation @ direction_a, (tip_b - base_b) / 1e5,
                               rtol=0, atol=1e-11)  # 1 micrometre over the 100 km lever


def test_centroid_on_ellipsoid_across_the_antimeridian():
    lat, lon = geodesy.centroid_on_ellipsoid(d2r(np.array([10.0, 10.0])), d2r(np.array([179.5, -179.5])))
    assert abs(abs(lon) - np.pi) < 1e-12  # on the antimeridian, not at Greenwich
    assert lat == pytest.approx(d2r(10.0), abs=d2r(0.01))  # the chord midpoint's geodetic latitude
