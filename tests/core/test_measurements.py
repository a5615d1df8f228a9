"""Measurement models: values at known geometries, Jacobians against finite differences, angle wrapping."""

from __future__ import annotations

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from core import geodesy
from core.angles import wrap_to_pi
from core.measurements import Kind, predict, residuals

d2r = np.deg2rad
ALL_KINDS = np.array([Kind.AZIMUTH, Kind.ELEVATION, Kind.RANGE, Kind.TOA], dtype=np.int8)


def random_geometries(rng, batch, per_problem, proper_enu=True):
    """Targets, stations, rotations, kinds and biases for a batch of random problems.

    Half the station frames are real ENU frames at other points of the earth
    (station ENU <- common ENU), half arbitrary rotations. Targets keep their
    horizontal distance above 20 % of the slant distance from every station,
    away from the zenith where azimuth is undefined.
    """
    targets = rng.uniform(-100e3, 100e3, (batch, 3))
    stations = targets[:, None, :] + rng.uniform(-150e3, 150e3, (batch, per_problem, 3))
    lat0, lon0 = d2r(rng.uniform(-80, 80, batch)), d2r(rng.uniform(-180, 180, batch))
    lat = lat0[:, None] + d2r(rng.uniform(-3, 3, (batch, per_problem)))
    lon = lon0[:, None] + d2r(rng.uniform(-3, 3, (batch, per_problem)))
    enu = geodesy.enu_to_enu_rotation(lat0[:, None], lon0[:, None], lat, lon)
    arbitrary = Rotation.random(batch * per_problem, random_state=rng).as_matrix().reshape(batch, per_problem, 3, 3)
    rotations = enu if proper_enu else arbitrary
    kinds = rng.choice(ALL_KINDS, (batch, per_problem)).astype(np.int8)
    biases = rng.uniform(-3e4, 3e4, batch)
    # Move stations off the target's zenith: keep rho / r >= 0.2 in each station frame.
    d = np.einsum("bmij,bmj->bmi", rotations, targets[:, None, :] - stations)
    rho, r = np.hypot(d[..., 0], d[..., 1]), np.linalg.norm(d, axis=-1)
    ok = rho >= 0.2 * r
    return targets, stations, rotations, kinds, biases, ok


def finite_difference_jacobian(targets, biases, stations, rotations, kinds):
    """Central differences of :func:`predict` w.r.t. (east, north, up, bias), angles wrapped."""
    batch, size = kinds.shape
    scale = np.linalg.norm(targets[:, None, :] - stations, axis=-1).min(axis=-1)
    step = 1e-5 * scale  # ~0.1-1 m: truncation ~1e-10 relative, round-off ~1e-10 relative
    jac = np.zeros((batch, size, 4))
    is_angle = (kinds == Kind.AZIMUTH) | (kinds == Kind.ELEVATION)
    for k in range(4):
        delta = np.zeros((batch, 4))
        delta[:, k] = step
        plus, _ = predict(targets + delta[:, :3], biases + delta[:, 3], stations, rotations, kinds)
        minus, _ = predict(targets - delta[:, :3], biases - delta[:, 3], stations, rotations, kinds)
        diff = np.where(is_angle, wrap_to_pi(plus - minus), plus - minus)
        jac[..., k] = diff / (2.0 * step[:, None])
    return jac


@pytest.mark.parametrize("proper_enu", [True, False], ids=["enu-frames", "arbitrary-rotations"])
def test_jacobian_matches_central_differences(proper_enu):
    rng = np.random.default_rng(2024 + proper_enu)
    targets, stations, rotations, kinds, biases, ok = random_geometries(rng, 400, 8, proper_enu)
    _, analytic = predict(targets, biases, stations, rotations, kinds)
    numeric = finite_difference_jacobian(targets, biases, stations, rotations, kinds)
    assert analytic.shape == (400, 8, 4)
    row_norm = np.linalg.norm(analytic, axis=-1, keepdims=True)
    error = np.abs(analytic - numeric) / row_norm
    assert np.all(error[ok] < 1e-6)  # 1 ppm of the gradient's size
    # Every kind was exercised, in many rotated frames.
    for kind in ALL_KINDS:
        assert np.count_nonzero(ok & (kinds == kind)) > 300


def test_bias_column_is_one_for_toa_and_zero_otherwise():
    rng = np.random.default_rng(5)
    targets, stations, rotations, kinds, biases, _ = random_geometries(rng, 50, 8)
    predicted, jac = predict(targets, biases, stations, rotations, kinds)
    np.testing.assert_array_equal(jac[..., 3], (kinds == Kind.TOA).astype(float))
    # And the TOA prediction is range + bias (the range of the same geometry without bias).
    unbiased, _ = predict(targets, np.zeros_like(biases), stations, rotations, kinds)
    is_toa = kinds == Kind.TOA
    np.testing.assert_allclose((predicted - unbiased)[is_toa], np.broadcast_to(biases[:, None], kinds.shape)[is_toa],
                               rtol=0, atol=1e-8)  # 10 nanometres on ~1e5 m
    np.testing.assert_array_equal((predicted - unbiased)[~is_toa], 0.0)


def test_values_at_known_geometry_identity_frame():
    stations = np.zeros((1, 7, 3))
    rotations = np.broadcast_to(np.eye(3), (1, 7, 3, 3))
    kinds = np.array([[Kind.AZIMUTH] * 4 + [Kind.ELEVATION, Kind.RANGE, Kind.TOA]], dtype=np.int8)
    targets = [[3.0, 0.0, 4.0]]
    predicted, _ = predict(np.array(targets[0]), np.array(7.0), stations[0], rotations[0], kinds[0])
    assert predicted[0] == pytest.approx(np.pi / 2, abs=1e-15)  # due east: 90 deg clockwise from north
    assert predicted[4] == pytest.approx(np.arctan2(4.0, 3.0), abs=1e-15)
    assert predicted[5] == pytest.approx(5.0, abs=1e-12)
    assert predicted[6] == pytest.approx(12.0, abs=1e-12)  # range + bias
    for target, az_deg in [([1.0, 1.0, 0.0], 45.0), ([1.0, -1.0, 0.0], 135.0), ([-1.0, -1.0, 0.0], -135.0),
                           ([-1.0, 1.0, 0.0], -45.0), ([0.0, -1.0, 5.0], 180.0)]:
        value, _ = predict(np.array(target), np.array(0.0), stations[0, :1], rotations[0, :1], kinds[0, :1])
        assert wrap_to_pi(value[0] - d2r(az_deg)) == pytest.approx(0.0, abs=1e-15)


def test_azimuth_is_measured_in_the_station_frame():
    """A station whose own north is the common frame's west sees a common-north target at 90 deg."""
    # Rows: station east, north, up in common coordinates (station ENU <- common ENU).
    rotation = np.array([[0.0, 1.0, 0.0], [-1.0, 0.0, 0.0], [0.0, 0.0, 1.0]])
    value, jac = predict(np.array([0.0, 1000.0, 0.0]), np.array(0.0), np.zeros((1, 3)), rotation[None],
                         np.array([Kind.AZIMUTH], dtype=np.int8))
    assert value[0] == pytest.approx(np.pi / 2, abs=1e-15)
    # Common east is the station's south: moving the target that way turns it clockwise, towards 180 deg.
    assert jac[0, 0] > 0
    assert jac[0, 0] == pytest.approx(1.0 / 1000.0, rel=1e-12)  # 1 rad per 1000 m of lever


# --- wrapping -----------------------------------------------------------------

AZ = np.array([Kind.AZIMUTH], dtype=np.int8)


@pytest.mark.parametrize("measured_deg, predicted_deg, expected_deg", [
    (359.9, 0.1, -0.2),
    (0.1, 359.9, 0.2),
    (0.1, -0.1, 0.2),
    (359.9, -0.1, 0.0),
    (180.1, -179.9, 0.0),
    (-179.9, 179.9, 0.2),
    (90.0, 90.0, 0.0),
])
def test_azimuth_residual_wraps_to_the_short_way_round(measured_deg, predicted_deg, expected_deg):
    r = residuals(np.array([d2r(measured_deg)]), np.array([d2r(predicted_deg)]), AZ)
    assert r[0] == pytest.approx(d2r(expected_deg), abs=1e-12)  # 1e-12 rad: round-off of degrees


def test_residual_at_half_turn_is_plus_pi():
    """Wrapped to (-pi, pi]: a half turn either way is +pi."""
    r = residuals(np.array([np.pi, -np.pi, 0.0]), np.array([0.0, 0.0, np.pi]), np.repeat(AZ, 3))
    np.testing.assert_array_equal(r, [np.pi, np.pi, np.pi])


def test_ranges_and_toa_are_not_wrapped():
    kinds = np.array([Kind.RANGE, Kind.TOA, Kind.ELEVATION], dtype=np.int8)
    r = residuals(np.array([10.0, 10.0, 0.1]), np.array([17.0, 3.0, 0.1 - 2 * np.pi]), kinds)
    np.testing.assert_allclose(r, [-7.0, 7.0, 0.0], rtol=0, atol=1e-12)


def test_predicted_azimuth_across_north_against_a_359_9_deg_measurement():
    """A target 0.1 deg west of north: predicted -0.1 deg; a 359.9 deg measurement fits exactly."""
    target = 5000.0 * np.array([-np.sin(d2r(0.1)), np.cos(d2r(0.1)), 0.0])
    predicted, _ = predict(target, np.array(0.0), np.zeros((2, 3)), np.broadcast_to(np.eye(3), (2, 3, 3)),
                           np.repeat(AZ, 2))
    r = residuals(np.array([d2r(359.9), d2r(0.1)]), predicted, np.repeat(AZ, 2))
    np.testing.assert_allclose(r, [0.0, d2r(0.2)], rtol=0, atol=1e-12)  # 1e-12 rad
