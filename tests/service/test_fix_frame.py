"""The frame of a fix's covariance: east/north/up at the fix, for every figure and rendering of it.

A geodetic problem's common frame is the tangent plane at the stations' centroid; 400 km away its axes are
turned by about 3.5 degrees against the fix's, which moves the vertical variance by a few percent. A fix body's
covariance, CRLB, error figures and CoT errors must all be in the fix's axes.
"""

from __future__ import annotations

import math

import numpy as np
import pytest

from core import geodesy
from core.crlb import information_at
from service import schemas
from service.convert import to_problem
from tests.service.conftest import STATIONS_300KM, bearing_request

#: About 400 km north-east of the stations' centroid (34.8 N, 110.3 E).
FAR_TARGET = {"lat_deg": 37.5, "lon_deg": 113.5, "alt_m": 9000.0}


def _le(cot: str) -> float:
    from lxml import etree

    return float(etree.fromstring(cot.encode()).find("point").get("le"))


def _bound_in_the_fix_axes(request: dict, fix: dict) -> tuple[np.ndarray, float]:
    """The CRLB at the fix computed by core in the common frame, turned by geodesy's own rotation between the
    frames, and the angle (deg) between the two frames' up axes."""
    problem = to_problem(schemas.FixRequest.model_validate(request))
    frame = problem.frame
    position = fix["position"]
    lat, lon = math.radians(position["lat_deg"]), math.radians(position["lon_deg"])
    at_fix = frame.from_geodetic(lat, lon, position["alt_m"])
    common = information_at(problem, at_fix).covariance_enu_m2[0]
    turn = geodesy.enu_to_enu_rotation(frame.origin.lat_rad, frame.origin.lon_rad, lat, lon)
    tilt = math.degrees(math.acos(min(1.0, turn[2, 2])))
    return turn @ common @ turn.T, tilt


@pytest.mark.parametrize("method", ["ml", "eove"])
def test_a_far_fix_covariance_crlb_error_and_cot_share_the_fix_axes(client, method):
    request = bearing_request(STATIONS_300KM, FAR_TARGET, 0.5, method=method, formats=["cot"])
    response = client.post("/v1/fixes", json=request)
    assert response.status_code == 200, response.text
    fix = response.json()
    covariance, crlb = np.array(fix["covariance_enu_m2"]), np.array(fix["crlb_enu_m2"])
    expected_crlb, tilt = _bound_in_the_fix_axes(request, fix)
    assert tilt > 3.0  # the test means something: the frames differ
    np.testing.assert_allclose(crlb, expected_crlb, rtol=1e-6, atol=1e-6 * np.abs(expected_crlb).max())

    # The ECEF covariance is frame-free: in the fix's axes it is the body's ENU covariance.
    rotation = geodesy.ecef_to_enu_rotation(math.radians(fix["position"]["lat_deg"]),
                                            math.radians(fix["position"]["lon_deg"]))
    at_fix = rotation @ np.array(fix["covariance_ecef_m2"]) @ rotation.T
    np.testing.assert_allclose(covariance, at_fix, rtol=1e-9, atol=1e-9 * np.abs(at_fix).max())

    # ml reaches the bound: its covariance is the CRLB; another estimator's is no smaller in any direction.
    if method == "ml":
        np.testing.assert_allclose(covariance, crlb, rtol=1e-9, atol=1e-9 * np.abs(crlb).max())
    else:
        assert np.linalg.eigvalsh(covariance - crlb).min() > -1e-6 * np.trace(crlb)

    sigma_up = math.sqrt(covariance[2, 2])
    assert _le(fix["cot"]) == pytest.approx(sigma_up, abs=0.006)
    assert fix["error"]["vertical_sigma_m"] == pytest.approx(sigma_up, rel=1e-12)


def test_the_planning_bound_is_in_the_target_axes_and_matches_the_fix(client):
    request = bearing_request(STATIONS_300KM, FAR_TARGET, 0.5, method="ml")
    fix = client.post("/v1/fixes", json=request).json()
    sensors = [{"station_id": sid, "sigma_azimuth_deg": 0.5, "sigma_elevation_deg": 0.5} for sid in STATIONS_300KM]
    bound = client.post("/v1/crlb", json={"stations": request["stations"], "sensors": sensors,
                                          "target": FAR_TARGET}).json()
    expected, _ = _bound_in_the_fix_axes(request, {"position": FAR_TARGET})
    np.testing.assert_allclose(bound["crlb_enu_m2"], expected, rtol=1e-9, atol=1e-9 * np.abs(expected).max())
    np.testing.assert_allclose(bound["crlb_enu_m2"], fix["crlb_enu_m2"], rtol=1e-6,
                               atol=1e-6 * np.abs(expected).max())
    assert bound["error"]["vertical_sigma_m"] == pytest.approx(math.sqrt(expected[2, 2]), rel=1e-9)


def test_a_batch_writes_the_same_frame_as_a_single_fix(client):
    request = bearing_request(STATIONS_300KM, FAR_TARGET, 0.5, method="ml")
    single = client.post("/v1/fixes", json=request).json()
    batch = client.post("/v1/fixes/batch", json={"problems": [request, request]}).json()
    for result in batch["results"]:
        np.testing.assert_allclose(result["fix"]["covariance_enu_m2"], single["covariance_enu_m2"], rtol=1e-12)


def test_a_flat_frame_keeps_its_one_set_of_axes(client):
    stations = [{"id": "a", "position": {"east_m": 0.0, "north_m": 0.0}},
                {"id": "b", "position": {"east_m": 10000.0, "north_m": 0.0}},
                {"id": "c", "position": {"east_m": 0.0, "north_m": 10000.0}}]
    target = np.array([300000.0, 250000.0, 0.0])
    measurements = []
    for s in stations:
        d = target - np.array([s["position"]["east_m"], s["position"]["north_m"], 0.0])
        measurements.append({"type": "bearing", "station_id": s["id"], "sigma_azimuth_deg": 0.5,
                             "azimuth_deg": math.degrees(math.atan2(d[0], d[1])) % 360.0})
    request = {"frame": "local", "stations": stations, "measurements": measurements, "method": "ml",
               "constraints": {"altitude_m": 0.0}}
    fix = client.post("/v1/fixes", json=request).json()
    problem = to_problem(schemas.FixRequest.model_validate(request))
    position = fix["position_local"]
    bound = information_at(problem, [position["east_m"], position["north_m"], position["up_m"]]).covariance_enu_m2[0]
    np.testing.assert_allclose(fix["crlb_enu_m2"], bound, rtol=1e-6, atol=1e-6 * np.abs(bound).max())
