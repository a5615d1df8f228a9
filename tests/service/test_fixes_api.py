"""POST /v1/fixes and /v1/crlb through the real app: answers, problem+json errors, headers."""

from __future__ import annotations

import copy
import hashlib
import json
import math

import numpy as np
import pytest

from core import geodesy
from service import schemas
from service.settings import Settings
from tests.service.conftest import STATIONS_300KM, TARGET, bearing_request, look_angles_deg

PROBLEM_JSON = "application/problem+json"


def _ecef(p: dict) -> np.ndarray:
    return geodesy.geodetic_to_ecef(math.radians(p["lat_deg"]), math.radians(p["lon_deg"]), p["alt_m"])


def assert_problem(response, status: int, loc: list | None = None, code: str | None = None) -> dict:
    assert response.status_code == status, response.text
    assert response.headers["content-type"].startswith(PROBLEM_JSON)
    body = response.json()
    schemas.Problem.model_validate(body)
    assert body["status"] == status and body["type"].endswith(body["code"])
    if code is not None:
        assert body["code"] == code
    if loc is not None:
        assert loc in [e["loc"] for e in body["errors"]], body
    return body


def test_noise_free_bearings_300km_geodetic(client):
    response = client.post("/v1/fixes", json=bearing_request(STATIONS_300KM, TARGET, formats=["geojson", "cot"]))
    assert response.status_code == 200, response.text
    fix = response.json()
    schemas.FixResponse.model_validate(fix)
    assert fix["method"] == "ml"
    assert np.linalg.norm(_ecef(fix["position"]) - _ecef(TARGET)) < 1e-3  # 1 mm over 300 km baselines
    assert np.linalg.norm(np.array(fix["position_ecef_m"]) - _ecef(TARGET)) < 1e-3
    assert fix["converged"] and fix["fit"]["chi2"] < 1e-12
    point = fix["geojson"]["features"][0]
    assert point["geometry"]["coordinates"][:2] == pytest.approx([TARGET["lon_deg"], TARGET["lat_deg"]])
    assert "<point" in fix["cot"]
    cov = np.array(fix["covariance_enu_m2"])
    assert np.allclose(cov, cov.T) and np.all(np.linalg.eigvalsh(cov) > 0)
    assert len(fix["residuals"]) == 8 and {r["component"] for r in fix["residuals"]} == {"azimuth", "elevation"}


def test_local_frame_with_origin_places_plane_on_earth(client):
    origin = {"lat_deg": 35.0, "lon_deg": 110.0, "alt_m": 0.0}
    o = [math.radians(origin["lat_deg"]), math.radians(origin["lon_deg"]), 0.0]
    stations, measurements = [], []
    target_enu = geodesy.geodetic_to_enu(math.radians(TARGET["lat_deg"]), math.radians(TARGET["lon_deg"]),
                                         TARGET["alt_m"], *o)
    for sid, pos in STATIONS_300KM.items():
        enu = geodesy.geodetic_to_enu(math.radians(pos["lat_deg"]), math.radians(pos["lon_deg"]), pos["alt_m"], *o)
        stations.append({"id": sid, "position": {"east_m": enu[0], "north_m": enu[1], "up_m": enu[2]}})
        az, el, _ = look_angles_deg(pos, TARGET)
        measurements.append({"type": "bearing", "station_id": sid, "azimuth_deg": az, "elevation_deg": el,
                             "sigma_azimuth_deg": 1, "sigma_elevation_deg": 1})
    body = {"frame": "local", "origin": origin, "stations": stations, "measurements": measurements}
    fix = client.post("/v1/fixes", json=body).json()
    local = fix["position_local"]
    assert np.allclose([local["east_m"], local["north_m"], local["up_m"]], target_enu, atol=1e-3)  # 1 mm
    assert np.linalg.norm(_ecef(fix["position"]) - _ecef(TARGET)) < 1e-3


def test_two_lines_of_sight_meet_exactly_local_frame(client):
    target = np.array([200.0, 100.0, 50.0])
    measurements = []
    for sid, s in (("a", np.zeros(3)), ("b", np.array([100.0, 0.0, 0.0]))):
        v = target - s
        measurements.append({"type": "bearing", "station_id": sid,
                             "azimuth_deg": math.degrees(math.atan2(v[0], v[1])),
                             "elevation_deg": math.degrees(math.atan2(v[2], math.hypot(v[0], v[1]))),
                             "sigma_azimuth_deg": 0.5, "sigma_elevation_deg": 0.5})
    body = {"frame": "local", "measurements": measurements,
            "stations": [{"id": "a", "position": {"east_m": 0, "north_m": 0, "up_m": 0}},
                         {"id": "b", "position": {"east_m": 100, "north_m": 0, "up_m": 0}}]}
    fix = client.post("/v1/fixes", json=body).json()
    p = fix["position_local"]
    assert np.allclose([p["east_m"], p["north_m"], p["up_m"]], target, atol=1e-9)  # 1 nm
    assert "position" not in fix and "position_ecef_m" not in fix


def test_bearings_and_ranges_from_two_stations(client):
    request = bearing_request(dict(list(STATIONS_300KM.items())[:2]), TARGET)
    for sid, pos in list(STATIONS_300KM.items())[:2]:
        request["measurements"].append({"type": "range", "station_id": sid,
                                        "range_m": look_angles_deg(pos, TARGET)[2], "sigma_m": 100.0})
    fix = client.post("/v1/fixes", json=request).json()
    assert np.linalg.norm(_ecef(fix["position"]) - _ecef(TARGET)) < 1e-3


def test_toa_from_five_stations(client):
    stations = dict(STATIONS_300KM, **{"rx-5": {"lat_deg": 35.5, "lon_deg": 110.5, "alt_m": 2000.0}})
    measurements = [{"type": "toa", "station_id": sid, "sigma_s": 1e-8,
                     "toa_s": 12.000183 + look_angles_deg(pos, TARGET)[2] / 299_792_458.0}
                    for sid, pos in stations.items()]
    body = {"stations": [{"id": k, "position": v} for k, v in stations.items()], "measurements": measurements}
    fix = client.post("/v1/fixes", json=body).json()
    assert np.linalg.norm(_ecef(fix["position"]) - _ecef(TARGET)) < 1e-3
    assert {r["component"] for r in fix["residuals"]} == {"toa"}


@pytest.mark.parametrize("outliers", ["report", "exclude"])
def test_a_fault_among_five_toas_is_detected_and_no_station_is_blamed(client, outliers):
    """Five TOAs leave one degree of freedom: a TOA 1 us off (100 sigma) fails the test, and no measurement can
    be told from another as its cause (every studentized residual is as large)."""
    stations = dict(STATIONS_300KM, **{"rx-5": {"lat_deg": 35.5, "lon_deg": 110.5, "alt_m": 2000.0}})
    measurements = [{"type": "toa", "station_id": sid, "sigma_s": 1e-8,
                     "toa_s": 12.000183 + look_angles_deg(pos, TARGET)[2] / 299_792_458.0}
                    for sid, pos in stations.items()]
    measurements[2]["toa_s"] += 1e-6
    body = {"stations": [{"id": k, "position": v} for k, v in stations.items()], "measurements": measurements,
            "options": {"outliers": outliers}}
    response = client.post("/v1/fixes", json=body)
    assert response.status_code == 200, response.text
    fix = response.json()
    codes = [w["code"] for w in fix["warnings"]]
    assert "fault_detected_not_isolable" in codes
    assert "outlier_suspected" not in codes and "measurement_excluded" not in codes
    assert fix["converged"]


def test_known_altitude_constraint_with_azimuth_only(client):
    request = bearing_request(dict(list(STATIONS_300KM.items())[:2]), TARGET, constraints={"altitude_m": 9000.0})
    for m in request["measurements"]:
        del m["elevation_deg"], m["sigma_elevation_deg"]
    fix = client.post("/v1/fixes", json=request).json()
    assert fix["position"]["alt_m"] == pytest.approx(9000.0, abs=1e-6)  # on the surface
    assert np.linalg.norm(_ecef(fix["position"]) - _ecef(TARGET)) < 1e-3


@pytest.mark.parametrize("method", ["eove", "weighted_eove", "ove", "ml", "auto"])
def test_methods_report_what_ran(client, method):
    response = client.post("/v1/fixes", json=bearing_request(STATIONS_300KM, TARGET, method=method))
    assert response.status_code == 200
    assert response.json()["method"] == ("ml" if method == "auto" else method)


# --- bad input: each a 4xx problem+json with the field path, never a 500 -------------------------

def _good() -> dict:
    return bearing_request(STATIONS_300KM, TARGET)


def _raw(client, text: str):
    return client.post("/v1/fixes", content=text.encode(), headers={"content-type": "application/json"})


@pytest.mark.parametrize("literal", ["NaN", "Infinity", "-Infinity"])
def test_non_finite_numbers_rejected(client, literal):
    body = _good()
    body["measurements"][0]["azimuth_deg"] = "PLACEHOLDER"
    raw = json.dumps(body).replace('"PLACEHOLDER"', literal)
    assert_problem(_raw(client, raw), 422, ["measurements", 0, "azimuth_deg"])


def test_nan_in_station_position(client):
    raw = json.dumps(_good()).replace('"lat_deg": 34.0', '"lat_deg": NaN', 1)
    assert_problem(_raw(client, raw), 422, ["stations", 0, "position", "lat_deg"])


def test_latitude_91(client):
    body = _good()
    body["stations"][1]["position"]["lat_deg"] = 91
    assert_problem(client.post("/v1/fixes", json=body), 422, ["stations", 1, "position", "lat_deg"])


@pytest.mark.parametrize("sigma", [0, -1])
def test_sigma_not_positive(client, sigma):
    body = _good()
    body["measurements"][2]["sigma_elevation_deg"] = sigma
    assert_problem(client.post("/v1/fixes", json=body), 422, ["measurements", 2, "sigma_elevation_deg"])


def test_unknown_station_id(client):
    body = _good()
    body["measurements"][3]["station_id"] = "nobody"
    assert_problem(client.post("/v1/fixes", json=body), 422, ["measurements", 3, "station_id"])


def test_duplicate_station_ids(client):
    body = _good()
    body["stations"][2]["id"] = body["stations"][0]["id"]
    assert_problem(client.post("/v1/fixes", json=body), 422, ["stations", 2, "id"])


def test_zero_measurements(client):
    body = _good()
    body["measurements"] = []
    assert_problem(client.post("/v1/fixes", json=body), 422, ["measurements"])


def test_missing_sigma_for_ml(client):
    body = _good()
    del body["measurements"][1]["sigma_azimuth_deg"]
    assert_problem(client.post("/v1/fixes", json=body), 422, ["measurements", 1, "sigma_azimuth_deg"])


def test_elevation_without_sigma(client):
    body = _good()
    del body["measurements"][1]["sigma_elevation_deg"]
    assert_problem(client.post("/v1/fixes", json=body), 422, ["measurements", 1])


def test_frame_and_position_kinds_must_agree(client):
    body = _good()
    body["stations"][0]["position"] = {"east_m": 1, "north_m": 2, "up_m": 3}
    assert_problem(client.post("/v1/fixes", json=body), 422)


def test_unknown_field_rejected(client):
    body = _good()
    body["measurements"][0]["sigma_azimuth"] = 1.0
    assert_problem(client.post("/v1/fixes", json=body), 422, ["measurements", 0, "sigma_azimuth"])


def test_unknown_method(client):
    body = _good()
    body["method"] = "magic"
    assert_problem(client.post("/v1/fixes", json=body), 422, ["method"])


def test_malformed_json_is_400(client):
    assert_problem(_raw(client, '{"frame": "wgs84", '), 400, code="malformed_json")


def test_body_over_limit_is_413(make_client):
    small = make_client(max_body_bytes=2048)
    body = _good()
    body["stations"][0]["id"] = "x" * 100
    body["measurements"] = body["measurements"] * 20
    assert_problem(small.post("/v1/fixes", json=body), 413, code="body_too_large")
    assert small.get("/healthz").status_code == 200


def test_azimuth_only_two_stations_without_altitude_is_unobservable(client):
    body = bearing_request(dict(list(STATIONS_300KM.items())[:2]), TARGET)
    for m in body["measurements"]:
        del m["elevation_deg"], m["sigma_elevation_deg"]
    problem = assert_problem(client.post("/v1/fixes", json=body), 422, code="unobservable")
    assert problem["detail"]


def test_parallel_lines_of_sight_are_unobservable(client):
    body = {"frame": "local",
            "stations": [{"id": "a", "position": {"east_m": 0, "north_m": 0, "up_m": 0}},
                         {"id": "b", "position": {"east_m": 1000, "north_m": 0, "up_m": 0}}],
            "measurements": [{"type": "bearing", "station_id": s, "azimuth_deg": 0.0, "elevation_deg": 5.0,
                              "sigma_azimuth_deg": 1, "sigma_elevation_deg": 1} for s in ("a", "b")]}
    assert_problem(client.post("/v1/fixes", json=body), 422, code="unobservable")


def _on_the_ground(stations_en_m: dict, azimuths_deg: dict, others: list = ()) -> dict:
    """An ML request in a local frame, stations and target at up 0 (known): azimuth-only bearings, then
    ``others``."""
    return {"frame": "local", "method": "ml", "constraints": {"altitude_m": 0.0},
            "stations": [{"id": s, "position": {"east_m": e, "north_m": n, "up_m": 0.0}}
                         for s, (e, n) in stations_en_m.items()],
            "measurements": [{"type": "bearing", "station_id": s, "azimuth_deg": a, "sigma_azimuth_deg": 0.5}
                             for s, a in azimuths_deg.items()] + list(others)}


@pytest.mark.parametrize("stations_en_m", [
    {"a": (-1000.0, 0.0), "b": (1000.0, 0.0), "c": (0.0, -2000.0)},  # side by side: the lines meet at infinity
    {"a": (0.0, 0.0), "b": (0.0, 1000.0)},  # in line with the target: the lines coincide
], ids=["parallel", "in_line"])
def test_azimuths_that_do_not_fix_a_point_on_a_known_altitude_are_unobservable_not_a_fix(client, stations_en_m):
    """With the altitude known, every start stage but the search fails and ML's fit slides along the lines
    until every residual is zero (north 1.4e19 m, or anywhere on the line). The Jacobi-scaled information
    stays regular there, so only the fit's slide tells: such a fit is no fix (a 200 would carry a CEP50 of
    about 5e18 m and only a collinear warning)."""
    body = _on_the_ground(stations_en_m, {s: 0.0 for s in stations_en_m})
    single = assert_problem(client.post("/v1/fixes", json=body), 422, code="unobservable")
    batch = client.post("/v1/fixes/batch", json={"problems": [body]}).json()["results"][0]
    assert not batch["ok"] and batch["error"]["code"] == "unobservable"
    assert batch["error"]["detail"] == single["detail"]


def test_azimuths_nearly_parallel_on_a_known_altitude_still_meet_far_away(client):
    """The control: lines 0.01 deg apart from stations 2 km apart do meet, 11,459 km out in the flat frame, and
    that is what ML answers, with its (huge but finite) bound and the collinear warning."""
    stations = {"a": (-1000.0, 0.0), "b": (1000.0, 0.0)}
    response = client.post("/v1/fixes", json=_on_the_ground(stations, {"a": 0.0, "b": -0.01}))
    assert response.status_code == 200, response.text
    fix = response.json()
    meet_north_m = 2000.0 / math.tan(math.radians(0.01))
    assert fix["position_local"]["north_m"] == pytest.approx(meet_north_m, rel=1e-6)
    assert "collinear_geometry" in [w["code"] for w in fix["warnings"]]


@pytest.mark.parametrize("epoch_s, sigma_s, warned", [
    (1.7e9, 1e-8, True),  # float64 spacing at 1.7e9 s is 2.4e-7 s (71 m): the data cannot hold 3 m
    (1.7e9, 1e-6, False),  # coarser sigma than the spacing
    (12.0, 1e-8, False),  # seconds since a recent reference: spacing 1.8e-15 s
])
def test_toas_sent_since_a_distant_epoch_are_named_when_float64_cannot_carry_their_sigma(client, epoch_s, sigma_s,
                                                                                        warned):
    speed_of_light = 299_792_458.0
    stations = {"a": (-1000.0, 0.0), "b": (1000.0, 0.0), "c": (0.0, -2000.0), "d": (3000.0, 3000.0)}
    target = (2000.0, 3000.0)
    toas = [{"type": "toa", "station_id": s, "toa_s": epoch_s + math.dist(stations[s], target) / speed_of_light,
             "sigma_s": sigma_s} for s in "bcd"]
    body = _on_the_ground(stations, {"a": 45.0}, toas)  # a sees the target (2000, 3000) north-east
    single = client.post("/v1/fixes", json=body)
    assert single.status_code == 200, single.text
    codes = [w["code"] for w in single.json()["warnings"]]
    assert ("toa_resolution" in codes) is warned
    if warned:
        assert "2.4e-07 s (71 m)" in next(w["message"] for w in single.json()["warnings"]
                                          if w["code"] == "toa_resolution")
    batch = client.post("/v1/fixes/batch", json={"problems": [body]}).json()["results"][0]
    assert batch["fix"]["warnings"] == single.json()["warnings"]


def test_request_id_echoed_and_generated(client):
    r = client.post("/v1/fixes", json=_good(), headers={"x-request-id": "c2-trace-42"})
    assert r.headers["x-request-id"] == "c2-trace-42"
    bad = client.post("/v1/fixes", json={"stations": []})
    assert len(bad.headers["x-request-id"]) >= 16 and bad.json()["request_id"] == bad.headers["x-request-id"]


def test_unknown_route_is_problem_json(client):
    assert_problem(client.get("/v1/nothing"), 404)


def test_api_keys(make_client, tmp_path):
    digest = hashlib.sha256(b"k1").hexdigest()
    other = tmp_path / "keys"
    other.write_text(f"# the second key\n{hashlib.sha256(b'k2').hexdigest()}\n")
    secured = make_client(api_key_hashes=f"{'0' * 64}, {digest.upper()}", api_key_hashes_file=str(other))
    missing = assert_problem(secured.post("/v1/fixes", json=_good()), 401)
    assert missing and secured.post("/v1/fixes", json=_good()).headers["www-authenticate"].startswith("Bearer")
    wrong = secured.post("/v1/fixes", json=_good(), headers={"authorization": "Bearer nope"})
    assert_problem(wrong, 401)
    assert 'error="invalid_token"' in wrong.headers["www-authenticate"]
    for key in ("k1", "k2"):
        assert secured.post("/v1/fixes", json=_good(), headers={"authorization": f"Bearer {key}"}).status_code == 200
    assert secured.get("/healthz").status_code == 200


def test_plain_keys_in_the_configuration_are_refused():
    with pytest.raises(ValueError):
        Settings(api_key_hashes="my-secret-key")


def test_rate_limit(make_client):
    limited = make_client(rate_limit_per_s=0.001, rate_limit_burst=2)
    codes = [limited.get("/v1/sessions").status_code for _ in range(3)]
    assert codes == [200, 200, 429]
    assert int(limited.get("/v1/sessions").headers["retry-after"]) >= 1
    assert [limited.get(probe).status_code for probe in ("/healthz", "/readyz", "/metrics") for _ in range(3)] \
        == [200] * 9


def test_operations(client):
    assert client.get("/healthz").json()["status"] == "ok"
    assert client.get("/readyz").json()["status"] == "ready"
    client.post("/v1/fixes", json=_good())
    from tests.service.test_metrics import sample

    text = client.get("/metrics").text
    assert sample(text, "passive_locator_requests_total", method="POST", path="/v1/fixes", status="200") == 1


def test_crlb_matches_fix_bound(client):
    fix = client.post("/v1/fixes", json=_good()).json()
    sensors = [{"station_id": sid, "sigma_azimuth_deg": 1.0, "sigma_elevation_deg": 1.0} for sid in STATIONS_300KM]
    body = {"stations": [{"id": k, "position": v} for k, v in STATIONS_300KM.items()], "sensors": sensors,
            "target": TARGET}
    response = client.post("/v1/crlb", json=body)
    assert response.status_code == 200, response.text
    bound = np.array(response.json()["crlb_enu_m2"])
    assert np.allclose(bound, fix["crlb_enu_m2"], rtol=1e-6)
    schemas.CrlbResponse.model_validate(response.json())


def test_crlb_unobservable(client):
    sensors = [{"station_id": sid, "elevation": False, "sigma_azimuth_deg": 1.0} for sid in list(STATIONS_300KM)[:2]]
    body = {"stations": [{"id": k, "position": v} for k, v in STATIONS_300KM.items()], "sensors": sensors,
            "target": TARGET}
    assert_problem(client.post("/v1/crlb", json=body), 422, code="unobservable")


def test_every_registered_method_is_in_the_schema(client):
    spec = client.get("/openapi.json").json()
    methods = set(spec["components"]["schemas"]["FixRequest"]["properties"]["method"]["enum"])
    from core.estimators import REGISTRY

    assert methods == {"auto", *REGISTRY}


def test_outlier_is_flagged(client):
    """30 deg on one azimuth of four 1 deg bearings: only leaving that bearing out explains the rest (at 12 deg
    leaving out another also passes the test at 1 %, and no one is named)."""
    body = copy.deepcopy(_good())
    body["measurements"][0]["azimuth_deg"] += 30.0
    fix = client.post("/v1/fixes", json=body).json()
    codes = {w["code"]: w["message"] for w in fix["warnings"]}
    assert "sigma_mismatch" in codes
    assert "measurement 0 " in codes["outlier_suspected"]  # the culprit, not a neighbour it was smeared onto


#: Found by a sweep over the schema's bounds: one station's contradicting bearings, sigmas at their floor and
#: ceiling, and a 1e9 m range. The polar points' covariance was singular in float64: angle_range answered 500.
ONE_STATION_AT_THE_BOUNDS = {
    "frame": "local",
    "stations": [{"id": "s0", "position": {"east_m": -1e8, "north_m": -99999999.8, "up_m": 40.8}}],
    "measurements": [
        {"type": "bearing", "station_id": "s0", "azimuth_deg": 719.99999892, "sigma_azimuth_deg": 1e-06,
         "elevation_deg": 72.81395317778299, "sigma_elevation_deg": 1e-06},
        {"type": "bearing", "station_id": "s0", "azimuth_deg": 276.0054648409979, "sigma_azimuth_deg": 1e-06},
        {"type": "bearing", "station_id": "s0", "azimuth_deg": -359.99999892, "sigma_azimuth_deg": 180.0,
         "elevation_deg": -24.077710728367094, "sigma_elevation_deg": 34.377171996865066},
        {"type": "bearing", "station_id": "s0", "azimuth_deg": -359.99999892, "sigma_azimuth_deg": 179.99999982},
        {"type": "bearing", "station_id": "s0", "azimuth_deg": 719.99999892, "sigma_azimuth_deg": 1e-06,
         "elevation_deg": 0.0, "sigma_elevation_deg": 1e-06},
        {"type": "range", "station_id": "s0", "range_m": 999999999.0, "sigma_m": 0.100001}]}


@pytest.mark.parametrize("method", ["angle_range", "ml", "auto"])
def test_one_station_at_the_schema_bounds_gets_an_answer_not_a_500(client, method):
    body = {**ONE_STATION_AT_THE_BOUNDS, "method": method}
    single = client.post("/v1/fixes", json=body)
    assert single.status_code in (200, 422), single.text
    slot = client.post("/v1/fixes/batch", json={"problems": [body]}).json()["results"][0]
    assert slot["ok"] is (single.status_code == 200)
    assert (slot["fix"] if slot["ok"] else slot["error"]["detail"]) == \
        (single.json() if slot["ok"] else single.json()["detail"])
