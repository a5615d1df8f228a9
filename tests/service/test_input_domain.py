"""The input domain: every class of hostile input found by probing answers 4xx with its field path.

One table: a request, how it is broken, the status and the ``loc`` the problem must name. Booleans are not
numbers, sigmas have floors (1/sigma^2 stays finite), coordinates and times have ranges, and the largest
allowed values still give finite answers (never ``null`` where a number is promised).
"""

from __future__ import annotations

import copy

import numpy as np
import pytest

from service import schemas
from service.schemas import sessions as session_schemas
from tests.service.conftest import STATIONS_300KM, TARGET, bearing_request
from tests.service.sessions.helpers import create_body
from tests.service.test_fixes_api import assert_problem


def _fix() -> dict:
    return bearing_request(STATIONS_300KM, TARGET)


def _local_fix() -> dict:
    return {"frame": "local",
            "stations": [{"id": "a", "position": {"east_m": 0.0, "north_m": 0.0}},
                         {"id": "b", "position": {"east_m": 10000.0, "north_m": 0.0}}],
            "measurements": [{"type": "range", "station_id": "a", "range_m": 7000.0, "sigma_m": 10.0},
                             {"type": "range", "station_id": "b", "range_m": 7000.0, "sigma_m": 10.0},
                             {"type": "bearing", "station_id": "a", "azimuth_deg": 45.0, "sigma_azimuth_deg": 1.0}]}


def _crlb() -> dict:
    return {"stations": [{"id": k, "position": v} for k, v in STATIONS_300KM.items()],
            "sensors": [{"station_id": k, "sigma_azimuth_deg": 1.0, "sigma_elevation_deg": 1.0}
                        for k in STATIONS_300KM],
            "target": dict(TARGET)}


def _add(item):
    return lambda body: body["measurements"].append(item)


def _set(*path_and_value):
    *path, value = path_and_value

    def change(body):
        node = body
        for key in path[:-1]:
            node = node[key]
        node[path[-1]] = value
    return change


RANGE = {"type": "range", "station_id": "rx-1", "range_m": 55000.0, "sigma_m": 250.0}
TOA = {"type": "toa", "station_id": "rx-1", "toa_s": 1.0, "sigma_s": 1e-8}

#: (route, body factory, change, status, loc)
CASES = {
    "range sigma underflows 1/sigma^2": ("/v1/fixes", _fix, _add({**RANGE, "sigma_m": 1e-155}),
                                         422, ["measurements", 4, "sigma_m"]),
    "toa sigma underflows 1/sigma^2": ("/v1/fixes", _fix, _add({**TOA, "sigma_s": 1e-300}),
                                       422, ["measurements", 4, "sigma_s"]),
    "crlb range sigma underflows": ("/v1/crlb", _crlb,
                                    lambda b: b["sensors"][0].update(range=True, sigma_range_m=1e-155),
                                    422, ["sensors", 0, "sigma_range_m"]),
    "crlb toa sigma underflows": ("/v1/crlb", _crlb, lambda b: b["sensors"][0].update(toa=True, sigma_toa_s=1e-300),
                                  422, ["sensors", 0, "sigma_toa_s"]),
    "azimuth sigma zero": ("/v1/fixes", _fix, _set("measurements", 0, "sigma_azimuth_deg", 0.0),
                           422, ["measurements", 0, "sigma_azimuth_deg"]),
    "local coordinate near the float limit": ("/v1/fixes", _local_fix, _set("stations", 0, "position", "east_m", 1e200),
                                              422, ["stations", 0, "position", "east_m"]),
    "local coordinate 1e308": ("/v1/fixes", _local_fix, _set("stations", 1, "position", "up_m", -1e308),
                               422, ["stations", 1, "position", "up_m"]),
    "altitude constraint 1e308": ("/v1/fixes", _fix, _set("constraints", {"altitude_m": 1e308}),
                                  422, ["constraints", "altitude_m"]),
    "crlb target at 1e308": ("/v1/crlb", _crlb, _set("target", {"east_m": 1e308, "north_m": 0.0}),
                             422, ["target", "east_m"]),
    "range 1e308": ("/v1/fixes", _fix, _add({**RANGE, "range_m": 1e308}), 422, ["measurements", 4, "range_m"]),
    "toa 1e308": ("/v1/fixes", _fix, _add({**TOA, "toa_s": 1e308}), 422, ["measurements", 4, "toa_s"]),
    "boolean as a number": ("/v1/fixes", _fix, _add({**TOA, "toa_s": False}), 422, ["measurements", 4, "toa_s"]),
    "boolean as an azimuth": ("/v1/fixes", _fix, _set("measurements", 1, "azimuth_deg", True),
                              422, ["measurements", 1, "azimuth_deg"]),
    "string as a number": ("/v1/fixes", _fix, _set("measurements", 1, "azimuth_deg", "12"),
                           422, ["measurements", 1, "azimuth_deg"]),
    "array as a number": ("/v1/fixes", _fix, _set("measurements", 1, "azimuth_deg", [1.0, 2.0]),
                          422, ["measurements", 1, "azimuth_deg"]),
    "boolean as an integer": ("/v1/fixes", _fix, _set("options", {"max_iterations": True}),
                              422, ["options", "max_iterations"]),
    "tolerance underflow": ("/v1/fixes", _fix, _set("options", {"tolerance_m": 1e-300}),
                            422, ["options", "tolerance_m"]),
    "evaluation trials as a boolean": ("/v1/evaluations", lambda: {"scenario": _crlb(), "methods": ["ml"]},
                                       _set("trials", True), 422, ["trials"]),
    "session ttl 1e-185": ("/v1/sessions", lambda: create_body(), _set("ttl_s", 1e-185), 422, ["ttl_s"]),
    "session sigma as a boolean": ("/v1/sessions", lambda: create_body(), _set("noise", "sigma_toa_s", True),
                                   422, ["noise", "sigma_toa_s"]),
    "session period underflow": ("/v1/sessions", lambda: create_body(), _set("pulse", "period_s", 1e-300),
                                 422, ["pulse", "period_s"]),
}


@pytest.mark.parametrize("route, make, change, status, loc", list(CASES.values()), ids=list(CASES))
def test_hostile_input_is_refused_with_its_field_path(client, route, make, change, status, loc):
    body = make()
    change(body)
    assert_problem(client.post(route, json=body), status, loc=loc)


def _session(client) -> str:
    response = client.post("/v1/sessions", json=create_body())
    assert response.status_code == 201, response.text
    return response.json()["id"]


EPOCH = {"seq": 1, "time_s": 0.0, "azimuth_deg": 10.0, "elevation_deg": 5.0, "azimuth_rate_deg_s": 0.1,
         "toa_s": 0.0}

EPOCH_CASES = {
    "toa after a normal epoch at +1.7e308": ({"toa_s": 1.7e308}, ["measurements", 1, "toa_s"]),
    "toa at -1.7e308": ({"toa_s": -1.7e308}, ["measurements", 1, "toa_s"]),
    "time 1e300": ({"time_s": 1e300}, ["measurements", 1, "time_s"]),
    "seq as a boolean": ({"seq": True}, ["measurements", 1, "seq"]),
    "seq as a float": ({"seq": 2.0}, ["measurements", 1, "seq"]),
}


@pytest.mark.parametrize("change, loc", list(EPOCH_CASES.values()), ids=list(EPOCH_CASES))
def test_hostile_epochs_are_refused_with_their_path(client, change, loc):
    session_id = _session(client)
    second = {**EPOCH, "seq": 2, "time_s": 1.0, "toa_s": 1.000001, **change}
    response = client.post(f"/v1/sessions/{session_id}/measurements", json={"measurements": [EPOCH, second]})
    assert_problem(response, 422, loc=loc)


def test_a_malformed_batch_slot_stays_in_its_slot(client):
    good = _fix()
    bad_array = copy.deepcopy(good)
    bad_array["measurements"][0]["azimuth_deg"] = [1.0, 2.0]
    bad_bool = copy.deepcopy(good)
    bad_bool["measurements"][2]["sigma_azimuth_deg"] = True
    local_far = _local_fix()
    local_far["stations"][0]["position"]["east_m"] = 1e200
    response = client.post("/v1/fixes/batch", json={"problems": [good, bad_array, good, bad_bool, local_far]})
    assert response.status_code == 200, response.text
    results = response.json()["results"]
    assert [r["ok"] for r in results] == [True, False, True, False, False]
    assert ["measurements", 0, "azimuth_deg"] in [e["loc"] for e in results[1]["error"]["errors"]]
    assert ["measurements", 2, "sigma_azimuth_deg"] in [e["loc"] for e in results[3]["error"]["errors"]]
    assert ["stations", 0, "position", "east_m"] in [e["loc"] for e in results[4]["error"]["errors"]]


def _numbers(value):
    if isinstance(value, dict):
        for item in value.values():
            yield from _numbers(item)
    elif isinstance(value, list):
        for item in value:
            yield from _numbers(item)
    elif isinstance(value, (int, float)) and not isinstance(value, bool):
        yield value


EXTREMES = {
    "farthest range, finest sigma": _add({**RANGE, "range_m": schemas.MAX_RANGE_M, "sigma_m": schemas.MIN_SIGMA_M}),
    "latest toa, finest sigma": _add({**TOA, "toa_s": schemas.MAX_ABS_TIME_S, "sigma_s": schemas.MIN_SIGMA_S}),
    "earliest toa": _add({**TOA, "toa_s": -schemas.MAX_ABS_TIME_S, "sigma_s": schemas.MIN_SIGMA_S}),
    "highest altitude constraint": _set("constraints", {"altitude_m": schemas.MAX_COORDINATE_M}),
    "finest bearing sigmas": lambda b: [m.update(sigma_azimuth_deg=schemas.MIN_SIGMA_DEG,
                                                 sigma_elevation_deg=schemas.MIN_SIGMA_DEG)
                                        for m in b["measurements"]],
}


@pytest.mark.parametrize("change", list(EXTREMES.values()), ids=list(EXTREMES))
def test_the_largest_allowed_values_give_finite_answers(client, change):
    """What the issue saw as ``fit.chi2: null`` and ``residual: null``: at the bounds every number is finite."""
    body = _fix()
    change(body)
    for route, payload in (("/v1/fixes", body), ("/v1/fixes/batch", {"problems": [body]})):
        response = client.post(route, json=payload)
        assert response.status_code in (200, 422), response.text
        if response.status_code == 200:
            answer = response.json()
            fix = answer if route == "/v1/fixes" else answer["results"][0].get("fix")
            if fix is not None:
                schemas.FixResponse.model_validate(fix)
                assert fix["fit"]["chi2"] is not None and all(r["residual"] is not None for r in fix["residuals"])
            assert all(np.isfinite(list(_numbers(answer))))


def test_bounds_are_in_the_published_schema():
    spec = schemas.FixRequest.model_json_schema()["$defs"]
    assert spec["RangeMeasurement"]["properties"]["sigma_m"]["minimum"] == schemas.MIN_SIGMA_M
    assert spec["LocalPosition"]["properties"]["east_m"]["maximum"] == schemas.MAX_COORDINATE_M
    assert spec["ToaMeasurement"]["properties"]["toa_s"]["minimum"] == -schemas.MAX_ABS_TIME_S
    ttl = session_schemas.SessionCreate.model_json_schema()["properties"]["ttl_s"]
    assert ttl["minimum"] == session_schemas.MIN_TTL_S


def test_max_fix_cost_limits_a_fix_and_each_batch_problem(make_client):
    small = make_client(max_fix_cost=15)  # 4 stations x 4 bearings = 16
    body = _fix()
    response = small.post("/v1/fixes", json=body)
    problem = assert_problem(response, 422)
    assert "max_fix_cost" in problem["detail"]
    three = copy.deepcopy(body)
    three["measurements"] = three["measurements"][:3]  # 4 x 3 = 12
    results = small.post("/v1/fixes/batch", json={"problems": [body, three]}).json()["results"]
    assert [r["ok"] for r in results] == [False, True]
    assert "max_fix_cost" in results[0]["error"]["detail"]


def test_the_fix_cost_limit_is_passed_to_validation_as_an_argument():
    from pydantic import ValidationError

    from service.fixes.read import read_fix_requests
    from service.limits import fix_cost_context

    body = _fix()  # 4 stations x 4 bearings = 16
    schemas.FixRequest.model_validate(body)  # no limit given: none applies
    schemas.FixRequest.model_validate(body, context=fix_cost_context(16))
    with pytest.raises(ValidationError, match="over the limit max_fix_cost = 15"):
        schemas.FixRequest.model_validate(body, context=fix_cost_context(15))
    assert read_fix_requests([body], 16).errors == {}
    refused = read_fix_requests([body], 15)
    assert refused.batch is None and "max_fix_cost = 15" in refused.errors[0]["detail"]


def test_a_batch_over_its_cost_is_422_naming_the_limit(make_client):
    small = make_client(max_batch_cost=100)
    body = _fix()
    assert small.post("/v1/fixes/batch", json={"problems": [body] * 25}).status_code == 200  # 25 x 4 = 100
    problem = assert_problem(small.post("/v1/fixes/batch", json={"problems": [body] * 26}), 422,
                             loc=["problems"], code="over_limit")
    assert "max_batch_cost" in problem["detail"]
    eove = {**body, "method": "eove"}
    assert small.post("/v1/fixes/batch", json={"problems": [eove] * 25}).status_code == 200  # every method weighs 1
    assert_problem(small.post("/v1/fixes/batch", json={"problems": [eove] * 26}), 422, code="over_limit")


def test_outlier_exclusion_is_priced_as_the_refits_it_may_take(make_client):
    """Four bearings with exclusion may be solved 1 + 4 + 3 + 2 = 10 times: a fix costs 4 x 4 x 10 and a
    batch problem 4 x 10 (256 x 1,024 with los_intersection took 28 s with exclusion, unpriced)."""
    from service.limits import exclusion_solves

    assert [exclusion_solves(False, 1024), exclusion_solves(True, 1), exclusion_solves(True, 4),
            exclusion_solves(True, 1024)] == [1, 1, 10, 65]
    body = _fix()
    excluding = {**body, "options": {"outliers": "exclude"}}
    fixes = make_client(max_fix_cost=159)
    assert fixes.post("/v1/fixes", json=body).status_code == 200
    problem = assert_problem(fixes.post("/v1/fixes", json=excluding), 422)
    assert "x 10 solves" in problem["detail"] and "max_fix_cost" in problem["detail"]
    slots = fixes.post("/v1/fixes/batch", json={"problems": [body, excluding]}).json()["results"]
    assert [slot["ok"] for slot in slots] == [True, False]
    assert make_client(max_fix_cost=160).post("/v1/fixes", json=excluding).status_code == 200
    batches = make_client(max_batch_cost=80)
    assert batches.post("/v1/fixes/batch", json={"problems": [excluding] * 2}).status_code == 200
    assert_problem(batches.post("/v1/fixes/batch", json={"problems": [excluding] * 3}), 422, code="over_limit")
    assert batches.post("/v1/fixes/batch", json={"problems": [body] * 20}).status_code == 200


def test_los_intersection_is_priced_by_its_pairs_of_lines_of_sight(make_client):
    """It intersects every pair: 2 stations x 1,008 bearings took 0.4 s alone and 25 s with exclusion while
    costing 2 x 1,008. Here 2 stations x 12 bearings cost 24, and 12^2 / 4 = 36 for los_intersection."""
    body = {"frame": "local", "stations": [{"id": s, "position": {"east_m": e, "north_m": 0.0}}
                                           for s, e in (("a", 0.0), ("b", 10_000.0))],
            "measurements": [{"type": "bearing", "station_id": s, "azimuth_deg": a + k * 0.01,
                              "elevation_deg": 5.0, "sigma_azimuth_deg": 1.0, "sigma_elevation_deg": 1.0}
                             for k in range(6) for s, a in (("a", 45.0), ("b", 315.0))]}
    los = {**body, "method": "los_intersection"}
    tight = make_client(max_fix_cost=35, max_batch_cost=35)
    assert tight.post("/v1/fixes", json={**body, "method": "ml"}).status_code == 200
    problem = assert_problem(tight.post("/v1/fixes", json=los), 422)
    assert "12^2 / 4" in problem["detail"] and "max_fix_cost" in problem["detail"]
    assert make_client(max_fix_cost=36).post("/v1/fixes", json=los).status_code == 200
    assert tight.post("/v1/fixes/batch", json={"problems": [{**body, "method": "ml"}]}).status_code == 200
    assert_problem(tight.post("/v1/fixes/batch", json={"problems": [los]}), 422, code="over_limit")
