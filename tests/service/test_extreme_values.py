"""Extreme numbers everywhere a number goes: nothing non-finite ever leaves the service.

One table per route: a valid body, and every numeric leaf of it set in turn to the extremes of a float
(1e-300 .. 1e308, both signs, zero) and to the bounds the schema states (sigmas at their floor and ceiling,
coordinates and times at their limits). Each answer is either a success whose body parses with a strict JSON
parser (no NaN or Infinity), validates against its response model (no null where a number is promised) and
holds only finite numbers, or a 4xx problem+json; a 422 for an invalid value names that value's field.
"""

from __future__ import annotations

import copy
import json
import math

import orjson
import pytest

from service import schemas
from service.schemas import sessions as session_schemas
from tests.service.conftest import STATIONS_300KM, TARGET, bearing_request
from tests.service.sessions.helpers import create_body
from tests.service.test_fixes_api import PROBLEM_JSON

pytestmark = pytest.mark.slow  # some 700 requests, about 40 s together

#: Every numeric leaf gets each of these.
FLOAT_EXTREMES = (1e-300, -1e-300, 1e300, -1e300, 1e308, -1.7976931348623157e308, 0.0)


def _leaves(node, path=()):
    """Paths of the numeric leaves (not booleans) of a JSON value."""
    if isinstance(node, dict):
        for key, value in node.items():
            yield from _leaves(value, (*path, key))
    elif isinstance(node, list):
        for index, value in enumerate(node):
            yield from _leaves(value, (*path, index))
    elif isinstance(node, (int, float)) and not isinstance(node, bool):
        yield path


def _with(body: dict, path: tuple, value) -> dict:
    changed = copy.deepcopy(body)
    node = changed
    for key in path[:-1]:
        node = node[key]
    node[path[-1]] = value
    return changed


def _by_name(path: tuple) -> str:
    return str(path[-1])


#: Field name -> values at (and just beyond) the bounds the schema states, besides FLOAT_EXTREMES.
BOUNDS = {
    "sigma_azimuth_deg": (schemas.MIN_SIGMA_DEG, schemas.MAX_SIGMA_AZIMUTH_DEG, schemas.MIN_SIGMA_DEG / 2),
    "sigma_elevation_deg": (schemas.MIN_SIGMA_DEG, schemas.MAX_SIGMA_ELEVATION_DEG),
    "sigma_m": (schemas.MIN_SIGMA_M, schemas.MAX_SIGMA_M, schemas.MIN_SIGMA_M / 2, schemas.MAX_SIGMA_M * 2),
    "sigma_range_m": (schemas.MIN_SIGMA_M, schemas.MAX_SIGMA_M),
    "sigma_s": (schemas.MIN_SIGMA_S, schemas.MAX_SIGMA_S, schemas.MIN_SIGMA_S / 2),
    "sigma_toa_s": (schemas.MIN_SIGMA_S, schemas.MAX_SIGMA_S),
    "range_m": (schemas.MAX_RANGE_M, schemas.MAX_RANGE_M * 2),
    "toa_s": (schemas.MAX_ABS_TIME_S, -schemas.MAX_ABS_TIME_S, schemas.MAX_ABS_TIME_S * 2),
    "time_s": (schemas.MAX_ABS_TIME_S, -schemas.MAX_ABS_TIME_S),
    "east_m": (schemas.MAX_COORDINATE_M, -schemas.MAX_COORDINATE_M, schemas.MAX_COORDINATE_M * 2),
    "north_m": (schemas.MAX_COORDINATE_M, -schemas.MAX_COORDINATE_M),
    "up_m": (schemas.MAX_COORDINATE_M, -schemas.MAX_COORDINATE_M),
    "lat_deg": (90.0, -90.0, 90.0000001),
    "lon_deg": (180.0, -180.0, 180.0000001),
    "alt_m": (schemas.MAX_COORDINATE_M, -schemas.MAX_COORDINATE_M),
    "azimuth_deg": (-360.0, 720.0),
    "elevation_deg": (89.999999, -89.999999),
}


def _values(path: tuple) -> tuple:
    return FLOAT_EXTREMES + BOUNDS.get(_by_name(path), ())


def _cases(body: dict, every_leaf: bool = True) -> list[tuple[tuple, float]]:
    """(path, value) per leaf and value; with ``every_leaf`` False, only the first leaf of each field (the first
    station's east_m, the first range's sigma_m, ...): the batch route takes every leaf, in one request."""
    paths, fields = [], set()
    for path in _leaves(body):
        field = tuple(key for key in path if isinstance(key, str))
        if every_leaf or field not in fields:
            fields.add(field)
            paths.append(path)
    return [(path, value) for path in paths for value in _values(path)]


def _local_hybrid() -> dict:
    """A local-frame fix with every measurement kind: ranges, bearings and TOAs."""
    stations = {"a": (0.0, 0.0, 0.0), "b": (20000.0, 0.0, 10.0), "c": (0.0, 20000.0, 20.0),
                "d": (20000.0, 20000.0, 30.0)}
    target = (9000.0, 12000.0, 500.0)
    measurements = []
    for sid, (e, n, u) in stations.items():
        de, dn, du = target[0] - e, target[1] - n, target[2] - u
        distance = math.sqrt(de * de + dn * dn + du * du)
        measurements.append({"type": "range", "station_id": sid, "range_m": distance, "sigma_m": 10.0})
        measurements.append({"type": "toa", "station_id": sid, "toa_s": 1.0 + distance / 299792458.0,
                             "sigma_s": 1e-8})
    measurements.append({"type": "bearing", "station_id": "a", "azimuth_deg": math.degrees(math.atan2(9000, 12000)),
                         "sigma_azimuth_deg": 1.0})
    return {"frame": "local",
            "stations": [{"id": k, "position": {"east_m": e, "north_m": n, "up_m": u}}
                         for k, (e, n, u) in stations.items()],
            "measurements": measurements,
            "constraints": {"altitude_m": 500.0},
            "options": {"tolerance_m": 1e-3, "max_iterations": 50,
                        "initial_guess": {"east_m": 8000.0, "north_m": 11000.0, "up_m": 500.0}}}


def _geodetic_fix() -> dict:
    """Bearings in WGS84 with an origin, a starting point and both renderings (their numbers are checked too)."""
    return bearing_request(STATIONS_300KM, TARGET, origin={"lat_deg": 35.0, "lon_deg": 110.0, "alt_m": 0.0},
                           options={"initial_guess": {"lat_deg": 35.1, "lon_deg": 110.1, "alt_m": 5000.0}},
                           formats=["geojson", "cot"])


def _local_crlb() -> dict:
    return {"frame": "local",
            "stations": [{"id": k, "position": {"east_m": e, "north_m": n, "up_m": 0.0}}
                         for k, (e, n) in {"a": (0.0, 0.0), "b": (30000.0, 0.0), "c": (0.0, 30000.0)}.items()],
            "sensors": [{"station_id": k, "elevation": False, "sigma_azimuth_deg": 0.5, "range": True,
                         "sigma_range_m": 50.0} for k in "abc"],
            "target": {"east_m": 12000.0, "north_m": 9000.0, "up_m": 100.0},
            "constraints": {"altitude_m": 100.0}}


def _crlb() -> dict:
    return {"stations": [{"id": k, "position": v} for k, v in STATIONS_300KM.items()],
            "sensors": [{"station_id": k, "sigma_azimuth_deg": 1.0, "sigma_elevation_deg": 1.0, "range": True,
                         "sigma_range_m": 100.0, "toa": True, "sigma_toa_s": 1e-7} for k in STATIONS_300KM],
            "target": dict(TARGET)}


def _finite_numbers(value) -> bool:
    if isinstance(value, dict):
        return all(_finite_numbers(v) for v in value.values())
    if isinstance(value, list):
        return all(_finite_numbers(v) for v in value)
    if isinstance(value, float):
        return math.isfinite(value)
    return True


def check_answer(status: int, content: bytes, content_type: str, model, path: tuple) -> str:
    """Assert one answer is finite and valid, or a 4xx problem naming the field; returns what it was."""
    assert status < 500, content[:2000]
    parsed = orjson.loads(content)  # strict: NaN, Infinity are not JSON
    if status < 300:
        model.model_validate(parsed)  # a null where a number is promised fails here
        assert _finite_numbers(parsed), parsed
        return "ok"
    assert content_type.startswith(PROBLEM_JSON), content_type
    return check_problem(parsed, path)


def check_problem(problem: dict, path: tuple) -> str:
    schemas.Problem.model_validate(problem)
    assert 400 <= problem["status"] < 500, problem
    if problem["code"] == "invalid_input":
        locs = [e["loc"] for e in problem["errors"]]
        assert list(path) in locs, (path, problem)
    return problem["code"]


def _post(client, route: str, body: dict):
    return client.post(route, content=orjson.dumps(body), headers={"content-type": "application/json"})


FIX_BODIES = {"geodetic bearings": _geodetic_fix, "local hybrid": _local_hybrid}


@pytest.mark.parametrize("make", list(FIX_BODIES.values()), ids=list(FIX_BODIES))
def test_extreme_values_in_a_fix(client, make):
    base = make()
    assert _post(client, "/v1/fixes", base).status_code == 200
    cases = _cases(base, every_leaf=False)
    outcomes = {}
    for path, value in cases:
        response = _post(client, "/v1/fixes", _with(base, path, value))
        outcome = check_answer(response.status_code, response.content, response.headers["content-type"],
                               schemas.FixResponse, path)
        outcomes[outcome] = outcomes.get(outcome, 0) + 1
    assert outcomes.get("ok", 0) > 0 and outcomes.get("invalid_input", 0) > 0, outcomes


@pytest.mark.parametrize("make", list(FIX_BODIES.values()), ids=list(FIX_BODIES))
def test_extreme_values_in_batch_slots(client, make):
    base = make()
    cases = _cases(base)
    response = _post(client, "/v1/fixes/batch", {"problems": [_with(base, p, v) for p, v in cases]})
    assert response.status_code == 200, response.text
    answer = orjson.loads(response.content)
    schemas.BatchResponse.model_validate(answer)
    assert _finite_numbers(answer)
    for (path, _), result in zip(cases, answer["results"], strict=True):
        if not result["ok"]:
            check_problem(result["error"], path)


@pytest.mark.parametrize("make", [_crlb, _local_crlb], ids=["geodetic", "local"])
def test_extreme_values_in_a_crlb(client, make):
    base = make()
    assert _post(client, "/v1/crlb", base).status_code == 200
    for path, value in _cases(base):
        response = _post(client, "/v1/crlb", _with(base, path, value))
        check_answer(response.status_code, response.content, response.headers["content-type"],
                     schemas.CrlbResponse, path)


def test_extreme_values_in_an_evaluation(client):
    base = {"scenario": _crlb(), "methods": ["ml", "tls"], "trials": 4, "seed": 3}
    assert _post(client, "/v1/evaluations", base).status_code == 200
    for path, value in _cases(base, every_leaf=False):
        response = _post(client, "/v1/evaluations", _with(base, path, value))
        check_answer(response.status_code, response.content, response.headers["content-type"],
                     schemas.EvaluationResponse, path)


EPOCHS = [{"seq": 1, "time_s": 0.0, "azimuth_deg": 10.0, "elevation_deg": 5.0, "azimuth_rate_deg_s": 0.1,
           "toa_s": 0.0},
          {"seq": 2, "time_s": 1.0, "azimuth_deg": 10.1, "elevation_deg": 5.0, "azimuth_rate_deg_s": 0.1,
           "toa_s": 1.0000002}]


def test_extreme_values_in_a_session(client):
    base = create_body(frame="wgs84")
    for path, value in _cases(base, every_leaf=False):
        response = _post(client, "/v1/sessions", _with(base, path, value))
        outcome = check_answer(response.status_code, response.content, response.headers["content-type"],
                               session_schemas.SessionState, path)
        if outcome == "ok":
            session_id = response.json()["id"]
            posted = _post(client, f"/v1/sessions/{session_id}/measurements", {"measurements": EPOCHS})
            check_answer(posted.status_code, posted.content, posted.headers["content-type"],
                         session_schemas.MeasurementResult, ())
            client.delete(f"/v1/sessions/{session_id}")


def test_extreme_values_in_session_epochs(client):
    body = {"measurements": EPOCHS}
    for path, value in _cases(body):
        if path[-1] == "seq":
            continue  # a sequence number is an integer: a float is refused like any other type error
        session_id = _post(client, "/v1/sessions", create_body(frame="wgs84")).json()["id"]
        response = _post(client, f"/v1/sessions/{session_id}/measurements", _with(body, path, value))
        check_answer(response.status_code, response.content, response.headers["content-type"],
                     session_schemas.MeasurementResult, path)
        state = client.get(f"/v1/sessions/{session_id}")
        check_answer(state.status_code, state.content, state.headers["content-type"],
                     session_schemas.SessionState, ())
        client.delete(f"/v1/sessions/{session_id}")


#: Sessions whose derived quantities are extreme though each value is allowed: the shortest period with the
#: most pulses per report, the latest and earliest times, the finest and coarsest noise.
SESSION_COMBINATIONS = {
    "shortest period, latest times": ({"pulse": {"period_s": 1e-7, "period_known": True,
                                                 "pulses_per_observation": 10**9}},
                                      {"time_s": schemas.MAX_ABS_TIME_S - 1, "toa_s": schemas.MAX_ABS_TIME_S - 1}),
    "longest period, earliest times": ({"pulse": {"period_s": 10.0, "period_known": False,
                                                  "pulses_per_observation": 1}},
                                       {"time_s": -schemas.MAX_ABS_TIME_S + 1, "toa_s": -schemas.MAX_ABS_TIME_S + 1}),
    "finest noise": ({"noise": {"sigma_azimuth_deg": schemas.MIN_SIGMA_DEG,
                                "sigma_elevation_deg": schemas.MIN_SIGMA_DEG,
                                "sigma_azimuth_rate_deg_s": 1e-9, "sigma_toa_s": schemas.MIN_SIGMA_S}}, {}),
    "coarsest noise, fastest rates": ({"noise": {"sigma_azimuth_deg": 27.9, "sigma_elevation_deg": 27.9,
                                                 "sigma_azimuth_rate_deg_s": 360.0, "sigma_toa_s": 1.0},
                                       "process_noise": {"accel_sigma_mps2": 1e4}},
                                      {"azimuth_rate_deg_s": 1e5}),
}


@pytest.mark.parametrize("create, second", list(SESSION_COMBINATIONS.values()), ids=list(SESSION_COMBINATIONS))
@pytest.mark.parametrize("model", ["velocity_kinematic", "joint_ukf"])
def test_extreme_combinations_in_a_session(client, create, second, model):
    created = _post(client, "/v1/sessions", {**create_body(frame="wgs84", model=model), **create})
    assert check_answer(created.status_code, created.content, created.headers["content-type"],
                        session_schemas.SessionState, ()) == "ok"
    session_id = created.json()["id"]
    first = dict(EPOCHS[0])
    later = {**EPOCHS[1], **second}
    if "time_s" in second and second["time_s"] < 0:
        first = {**first, "time_s": second["time_s"] - 1, "toa_s": second["toa_s"] - 1}
    for epochs in ([first, later], [{**later, "seq": 3, "time_s": later["time_s"] + 1e-3,
                                     "toa_s": later["toa_s"] + 1e-3}]):
        posted = _post(client, f"/v1/sessions/{session_id}/measurements", {"measurements": epochs})
        check_answer(posted.status_code, posted.content, posted.headers["content-type"],
                     session_schemas.MeasurementResult, ())
    state = client.get(f"/v1/sessions/{session_id}", params={"formats": "cot,geojson"})
    check_answer(state.status_code, state.content, state.headers["content-type"], session_schemas.SessionState, ())


@pytest.mark.parametrize("path", [("constraints", "altitude_m"), ("options", "tolerance_m"), ("options", "loss_scale"),
                                  ("options", "initial_guess", "lat_deg")], ids=lambda p: ".".join(p))
def test_an_integer_past_the_float_range_is_a_422_at_its_field(client, path):
    # 10**400 is valid JSON (orjson will not write it, the stdlib will); float() of it overflows
    body = _geodetic_fix()
    target = body
    for key in path[:-1]:
        target = target.setdefault(key, {})
    target[path[-1]] = 10**400
    if path[-1] == "lat_deg":
        target["lon_deg"] = 109.0
    content = json.dumps(body).encode()
    single = client.post("/v1/fixes", content=content, headers={"content-type": "application/json"})
    assert single.status_code == 422 and single.json()["errors"][0]["loc"] == list(path)
    batch = client.post("/v1/fixes/batch", content=json.dumps({"problems": [body, _geodetic_fix()]}).encode(),
                        headers={"content-type": "application/json"})
    assert batch.status_code == 200
    results = batch.json()["results"]
    assert results[0]["error"]["status"] == 422 and results[0]["error"]["errors"][0]["loc"] == list(path)
    assert results[1]["ok"]
