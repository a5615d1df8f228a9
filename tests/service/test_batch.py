"""POST /v1/fixes/batch: each slot equals what POST /v1/fixes gives for that problem; errors stay in their slot."""

from __future__ import annotations

import copy
import math
import re

import numpy as np
import orjson
import pytest

from core import geodesy
from core.estimators import REGISTRY
from service import schemas
from service.fixes.rules import READ_FIELDS, VALIDATORS
from tests.service.conftest import STATIONS_300KM, TARGET, bearing_request, look_angles_deg

REL = 1e-9  # batch and single fixes agree to this relative precision
C = 299_792_458.0


def _noisy(request: dict, seed: int, sigma_deg: float = 0.3) -> dict:
    rng = np.random.default_rng(seed)
    out = copy.deepcopy(request)
    for m in out["measurements"]:
        if m["type"] == "bearing":
            m["azimuth_deg"] = (m["azimuth_deg"] + sigma_deg * rng.standard_normal()) % 360.0
            if m.get("elevation_deg") is not None:
                m["elevation_deg"] += sigma_deg * rng.standard_normal()
        elif m["type"] == "range":
            m["range_m"] += m["sigma_m"] * rng.standard_normal()
        else:
            m["toa_s"] += m["sigma_s"] * rng.standard_normal()
    return out


def _subset(ids) -> dict:
    return {k: STATIONS_300KM[k] for k in ids}


def _with_ranges(ids, seed) -> dict:
    request = bearing_request(_subset(ids), TARGET)
    for sid in ids:
        request["measurements"].append({"type": "range", "station_id": sid, "sigma_m": 300.0,
                                        "range_m": look_angles_deg(STATIONS_300KM[sid], TARGET)[2]})
    return _noisy(request, seed)


def _toa_only(seed) -> dict:
    stations = _subset(["rx-1", "rx-2", "rx-3", "rx-4"])
    measurements = [{"type": "toa", "station_id": sid, "sigma_s": 1e-7,
                     "toa_s": 1000.0 + look_angles_deg(pos, TARGET)[2] / C} for sid, pos in stations.items()]
    request = {"frame": "wgs84", "stations": [{"id": k, "position": v} for k, v in stations.items()],
               "measurements": measurements, "method": "ml"}
    return _noisy(request, seed)


def _azimuth_only(ids, seed, sigma=True, **extra) -> dict:
    request = bearing_request(_subset(ids), TARGET, **extra)
    for m in request["measurements"]:
        del m["elevation_deg"], m["sigma_elevation_deg"]
        if not sigma:
            del m["sigma_azimuth_deg"]
    return _noisy(request, seed)


def _local(request: dict, with_origin: bool) -> dict:
    """The same scene in a local ENU frame at rx-1 (with or without the origin that places it on earth)."""
    origin = STATIONS_300KM["rx-1"]
    o = (math.radians(origin["lat_deg"]), math.radians(origin["lon_deg"]), origin["alt_m"])
    out = copy.deepcopy(request)
    out["frame"] = "local"
    for station in out["stations"]:
        p = station["position"]
        e, n, u = geodesy.geodetic_to_enu(math.radians(p["lat_deg"]), math.radians(p["lon_deg"]), p["alt_m"], *o)
        station["position"] = {"east_m": float(e), "north_m": float(n), "up_m": float(u)}
    if with_origin:
        out["origin"] = dict(origin)
    return out


def mixed_batch() -> list:
    """Problems of every kind the batch must keep apart, and some that must fail in their slot."""
    four = ["rx-1", "rx-2", "rx-3", "rx-4"]
    good = [
        _noisy(bearing_request(_subset(four), TARGET, method="ml"), 1),
        _noisy(bearing_request(_subset(four[:3]), TARGET), 2),
        _noisy(bearing_request(_subset(four[:2]), TARGET, formats=["geojson", "cot"], cot={"uid": "emitter-3"},
                               observed_at="2026-12-01T12:00:00Z"), 3),
        _with_ranges(four[:2], 4),
        _with_ranges(four, 5) | {"method": "ml", "options": {"max_iterations": 30, "tolerance_m": 0.01}},
        _toa_only(6),
        _azimuth_only(four[:3], 7, constraints={"altitude_m": TARGET["alt_m"]}),
        _local(_noisy(bearing_request(_subset(four), TARGET), 8), with_origin=False),
        _local(_noisy(bearing_request(_subset(four), TARGET), 9), with_origin=True),
        _noisy(bearing_request(_subset(four), TARGET, options={"initial_guess": dict(TARGET)}), 10),
        _azimuth_only(four, 11, sigma=False),
    ]
    for k, method in enumerate(sorted(REGISTRY)):
        good.append(_noisy(bearing_request(_subset(four), TARGET, method=method), 100 + k))
        good.append(_with_ranges(four, 200 + k) | {"method": method})
        good.append(_azimuth_only(four, 300 + k, method=method, constraints={"altitude_m": TARGET["alt_m"]}))
    negative_sigma = copy.deepcopy(good[0])
    negative_sigma["measurements"][1]["sigma_azimuth_deg"] = -1.0
    unknown_station = copy.deepcopy(good[0])
    unknown_station["measurements"][2]["station_id"] = "nobody"
    duplicate = copy.deepcopy(good[1])
    duplicate["stations"][1]["id"] = duplicate["stations"][0]["id"]
    too_few = bearing_request(_subset(four[:1]), TARGET, method="ml")
    extra_field = copy.deepcopy(good[2]) | {"colour": "red"}
    text_number = copy.deepcopy(good[0])
    text_number["measurements"][0]["azimuth_deg"] = "12.5"
    bad = [negative_sigma, unknown_station, duplicate, too_few, extra_field, text_number]
    mixed = []
    for i in range(max(len(good), len(bad))):
        mixed.extend(([good[i]] if i < len(good) else []) + ([bad[i]] if i < len(bad) else []))
    return mixed


#: Absolute floors for values that are zero up to round-off (an exactly determined fix has zero
#: residuals): 1e-9 of a sigma for residuals, and the matching chi-square.
FLOORS = {"normalized": 1e-9, "chi2": 1e-9, "sigma_scale": 1e-9}


#: What differs between two renderings of one fix made at different moments: the CoT uid (unique per fix
#: without cot.uid) and the times (now, without observed_at).
_MOMENT = re.compile(r'( uid| time| start| stale)="[^"]*"')


def assert_close(a, b, path="fix", floor=1e-12):
    if path.endswith(".cot") and isinstance(a, str) and isinstance(b, str):
        a, b = _MOMENT.sub(r'\1=""', a), _MOMENT.sub(r'\1=""', b)
    if path.endswith(".properties") and isinstance(a, dict) and isinstance(b, dict) and "time" in a:
        a, b = {**a, "time": None}, {**b, "time": None}
    if isinstance(a, dict):
        assert a.keys() == b.keys(), f"{path}: {sorted(a.keys() ^ b.keys())}"
        sigma = abs(a["residual"] / a["normalized"]) if a.get("normalized") else 1.0
        for key in a:
            key_floor = 1e-9 * sigma if key == "residual" else FLOORS.get(key, floor)
            assert_close(a[key], b[key], f"{path}.{key}", key_floor)
    elif isinstance(a, list):
        assert len(a) == len(b), path
        for i, (x, y) in enumerate(zip(a, b)):
            assert_close(x, y, f"{path}[{i}]", floor)
    elif isinstance(a, float) and isinstance(b, float):
        assert math.isclose(a, b, rel_tol=REL, abs_tol=floor), f"{path}: {a} != {b}"
    else:
        assert a == b, f"{path}: {a!r} != {b!r}"


@pytest.fixture(scope="module")
def mixed_results(tmp_path_factory):
    from fastapi.testclient import TestClient

    from service.app import create_app
    from service.settings import Settings

    problems = mixed_batch() + [7, "not a problem"]
    with TestClient(create_app(Settings(store=f"sqlite:///{tmp_path_factory.mktemp('b')}/s.db"))) as client:
        response = client.post("/v1/fixes/batch", json={"problems": problems})
        singles = [client.post("/v1/fixes", json=p) for p in problems if isinstance(p, dict)]
    return problems, response, singles


def test_batch_slots_equal_single_fixes(mixed_results):
    problems, response, singles = mixed_results
    assert response.status_code == 200
    results = response.json()["results"]
    assert [r["index"] for r in results] == list(range(len(problems)))
    assert sum(r["ok"] for r in results) >= len(problems) // 2
    for result, single in zip(results, singles):
        if single.status_code == 200:
            assert result["ok"], (result["index"], result.get("error"))
            assert orjson.dumps(result["fix"]) == single.content, f"slot {result['index']}"
        else:
            assert not result["ok"], result["index"]
            error, expected = result["error"], single.json()
            assert error["status"] == single.status_code
            assert {**error, "request_id": None, "instance": None} == {**expected, "request_id": None, "instance": None}


def test_every_method_and_mix_is_exercised(mixed_results):
    problems, response, _ = mixed_results
    results = response.json()["results"]
    methods = {r["fix"]["method"] for r in results if r["ok"]}
    assert {"ml", "eove", "weighted_eove"} <= methods
    components = {res["component"] for r in results if r["ok"] for res in r["fix"]["residuals"]}
    assert components == {"azimuth", "elevation", "range", "toa"}
    assert any("geojson" in r["fix"] and "cot" in r["fix"] for r in results if r["ok"])
    assert any("position" not in r["fix"] for r in results if r["ok"])  # the flat local frame


def test_ok_slots_validate_against_the_schemas(mixed_results):
    _, response, _ = mixed_results
    body = response.json()
    schemas.BatchResponse.model_validate(body)
    for result in body["results"]:
        if result["ok"]:
            schemas.FixResponse.model_validate(result["fix"])
            assert "error" not in result
        else:
            schemas.Problem.model_validate(result["error"])
            assert result["error"]["type"].endswith(result["error"]["code"])
            assert "fix" not in result


def test_a_malformed_problem_fails_only_its_slot(client):
    good = _noisy(bearing_request(STATIONS_300KM, TARGET), 42)
    bad = copy.deepcopy(good)
    bad["measurements"][3]["elevation_deg"] = 123.0
    response = client.post("/v1/fixes/batch", json={"problems": [good, good, bad, good]})
    assert response.status_code == 200
    results = response.json()["results"]
    assert [r["ok"] for r in results] == [True, True, False, True]
    error = results[2]["error"]
    assert error["status"] == 422 and error["code"] == "invalid_input"
    assert error["errors"][0]["loc"] == ["measurements", 3, "elevation_deg"]
    single = client.post("/v1/fixes", json=good).json()
    for k in (0, 1, 3):
        assert_close(results[k]["fix"], single)


def test_a_bug_in_one_problem_fails_only_its_slot(client, monkeypatch):
    from service.fixes import pipeline

    real = pipeline.iter_solutions

    def buggy(batch, methods, options, should_stop=None, **kwargs):
        if any(o.max_iterations == 17 for o in options):
            raise ZeroDivisionError("a bug")
        return real(batch, methods, options, should_stop, **kwargs)

    monkeypatch.setattr(pipeline, "iter_solutions", buggy)
    good = _noisy(bearing_request(STATIONS_300KM, TARGET), 43)
    poisoned = copy.deepcopy(good) | {"options": {"max_iterations": 17}}
    response = client.post("/v1/fixes/batch", json={"problems": [good, poisoned, good]},
                           headers={"x-request-id": "bug-1"})
    assert response.status_code == 200
    results = response.json()["results"]
    assert [r["ok"] for r in results] == [True, False, True]
    assert (results[1]["error"]["status"], results[1]["error"]["code"]) == (500, "internal_error")
    assert "bug-1" in results[1]["error"]["detail"]
    single = client.post("/v1/fixes", json=good).json()
    for k in (0, 2):
        assert_close(results[k]["fix"], single)


def test_unsolvable_and_unknown_station_are_reported_in_their_slots(client):
    good = _noisy(bearing_request(STATIONS_300KM, TARGET), 43)
    unknown = copy.deepcopy(good)
    unknown["measurements"][0]["station_id"] = "rx-9"
    lonely = bearing_request(_subset(["rx-1"]), TARGET, method="ml")
    results = client.post("/v1/fixes/batch", json={"problems": [unknown, good, lonely]}).json()["results"]
    assert [r["ok"] for r in results] == [False, True, False]
    assert results[0]["error"]["errors"][0]["loc"] == ["measurements", 0, "station_id"]
    assert results[2]["error"]["status"] == 422


@pytest.mark.parametrize("body, status", [
    (b"{not json", 400),
    (b"[]", 422),
    (b'{"problems": []}', 422),
    (b'{"problems": {}}', 422),
    (b'{"problem": [{}]}', 422),
    (b'{"problems": [{}], "extra": 1}', 422),
])
def test_a_body_that_is_not_a_batch_fails_whole(client, body, status):
    response = client.post("/v1/fixes/batch", content=body, headers={"content-type": "application/json"})
    assert response.status_code == status
    assert response.headers["content-type"].startswith("application/problem+json")


def test_more_than_ten_thousand_problems_is_refused(client):
    response = client.post("/v1/fixes/batch", content=orjson.dumps({"problems": [{}] * 10_001}),
                           headers={"content-type": "application/json"})
    assert response.status_code == 422
    assert response.json()["errors"][0]["loc"] == ["problems"]


def test_route_is_documented():
    from service.app import create_app
    from service.settings import Settings

    spec = create_app(Settings(store="sqlite:///:memory:")).openapi()
    operation = spec["paths"]["/v1/fixes/batch"]["post"]
    assert operation["operationId"] == "fixes-batch"
    schema = operation["requestBody"]["content"]["application/json"]["schema"]
    if "$ref" in schema:  # named in components (service/web/openapi.py)
        schema = spec["components"]["schemas"][schema["$ref"].rsplit("/", 1)[-1]]
    items = schema["properties"]["problems"]["items"]
    assert items == {"$ref": "#/components/schemas/FixRequest"}


def test_parts_on_worker_threads_give_the_same_bodies(client, monkeypatch):
    import core.estimators as estimators

    problems = [_noisy(bearing_request(STATIONS_300KM, TARGET), seed) for seed in range(7)]
    problems.insert(3, {"stations": []})
    same_id = {"x-request-id": "parts"}
    whole = client.post("/v1/fixes/batch", json={"problems": problems}, headers=same_id).json()
    monkeypatch.setattr(estimators, "PART_PROBLEMS", 2)
    monkeypatch.setattr(estimators, "MAX_WORKERS", 2)
    parts = client.post("/v1/fixes/batch", json={"problems": problems}, headers=same_id).json()
    assert_close(parts, whole, "batch")
    assert [r["ok"] for r in parts["results"]] == [True] * 3 + [False] + [True] * 4


def test_a_batch_read_in_chunks_while_earlier_chunks_solve_gives_the_same_bytes(client, monkeypatch):
    # More problems than one read chunk: each chunk is read while those before it solve on the threads.
    from service.fixes import pipeline

    problems = mixed_batch()
    same_id = {"x-request-id": "chunks"}
    whole = client.post("/v1/fixes/batch", json={"problems": problems}, headers=same_id)
    monkeypatch.setattr(pipeline, "PART_PROBLEMS", 3)
    chunked = client.post("/v1/fixes/batch", json={"problems": problems}, headers=same_id)
    assert chunked.status_code == whole.status_code == 200
    assert chunked.content == whole.content


def test_the_reader_knows_every_validator_of_the_request_schema():
    """The lean reader re-implements the schema's validators (service.fixes.rules.VALIDATORS); a new one fails
    here until the reader is taught it (or rejects what it cannot check)."""
    found = {(m.__name__, name) for m in READ_FIELDS for kind in ("model_validators", "field_validators")
             for name in getattr(m.__pydantic_decorators__, kind)}
    assert found == VALIDATORS


def test_the_reader_handles_every_field_of_every_request_model():
    """A field added to a request model fails here until the reader reads it."""
    reachable, todo = set(), [schemas.FixRequest]
    while todo:
        model = todo.pop()
        if model in reachable:
            continue
        reachable.add(model)
        for field in model.model_fields.values():
            for arg in _models_in(field.annotation):
                todo.append(arg)
    assert reachable == set(READ_FIELDS)
    for model, fields in READ_FIELDS.items():
        assert fields == frozenset(model.model_fields), model.__name__


def _models_in(annotation):
    import typing

    from pydantic import BaseModel

    if isinstance(annotation, type) and issubclass(annotation, BaseModel):
        yield annotation
    for arg in typing.get_args(annotation):
        yield from _models_in(arg)


def _padded_request(stations: int, seed: int, mix: str) -> dict:
    """A wgs84 request with ``stations`` bearing stations around the bench geometry, of measurement mix
    ``mix``: elevations, azimuths only (with altitude), bearings with ranges, bearings with TOAs."""
    from bench.scenarios import four_station_requests

    rng = np.random.default_rng(seed)
    template = four_station_requests(1, np.random.default_rng(seed), with_range=True)[0]
    bearings = [m for m in template["measurements"] if m["type"] == "bearing"]
    a_range = next(m for m in template["measurements"] if m["type"] == "range")
    request = {"frame": "wgs84", "stations": [], "measurements": []}
    for k in range(stations):
        station = copy.deepcopy(template["stations"][k % 4])
        station["id"] = f"s{k}"
        station["position"]["lat_deg"] += 1e-3 * (k // 4)
        request["stations"].append(station)
        bearing = dict(bearings[k % 4], station_id=f"s{k}")
        bearing["azimuth_deg"] += 0.3 * rng.standard_normal()
        if mix == "azimuths":
            bearing.pop("elevation_deg"), bearing.pop("sigma_elevation_deg")
        else:
            bearing["elevation_deg"] += 0.3 * rng.standard_normal()
        request["measurements"].append(bearing)
        if mix == "ranges" and k < 3:
            request["measurements"].append(dict(a_range, station_id=f"s{k}",
                                                range_m=a_range["range_m"] * (1 + 0.01 * rng.standard_normal())))
        if mix == "toas":
            request["measurements"].append({"type": "toa", "station_id": f"s{k}", "toa_s": 1e-4 * rng.random(),
                                            "sigma_s": 1e-6})
    if mix == "azimuths":
        request["constraints"] = {"altitude_m": 3000.0}
    return request


@pytest.mark.parametrize("mix", ["elevations", "azimuths", "ranges", "toas"])
def test_a_fix_is_the_same_bytes_when_a_larger_problem_pads_it(mix):
    """Padding to a batch's widest problem changes no bit of any method's fix: every sum over measurements,
    lines or pairs is added in order (numpy's pairwise sums over eight or more terms round differently once
    zeros are appended)."""
    from service.web.responses import dumps
    from service.fixes.pipeline import fix_results

    def body(result):
        out = result.get("fix") or {k: v for k, v in result["error"].items() if k not in ("request_id", "instance")}
        return dumps(out)

    options = [None, {"loss": "huber"}, {"outliers": "exclude"}]
    for trial in range(4):
        small, wide = _padded_request(3 + 3 * trial, trial, mix), _padded_request(16, 100 + trial, mix)
        for method in sorted(REGISTRY):
            small["method"] = wide["method"] = method
            for option in options if method == "ml" else [None]:
                for request in (small, wide):
                    request.pop("options", None)
                    if option:
                        request["options"] = option
                alone = fix_results([small])[0]
                padded = fix_results([wide, small])[1]
                assert body(alone) == body(padded), (mix, trial, method, option)


_PADDING_PROBE = """
import copy, json, resource
import numpy as np
from bench.scenarios import four_station_requests
from service.fixes.pipeline import fix_results

def peak_mb():
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024

small = four_station_requests(3000, np.random.default_rng(1))
large = copy.deepcopy(small[0])
large["measurements"] = [dict(m) for m in large["measurements"]] * 256
fix_results(small[:10] + [large])
fix_results(small)
alone = peak_mb()
results = fix_results(small + [large])
print(json.dumps({"growth_mb": peak_mb() - alone, "ok": sum(r["ok"] for r in results)}))
"""


def test_one_large_problem_does_not_pad_a_batch_of_small_ones():
    """A batch pads every problem to its largest. Read as one batch, 3,000 four-bearing problems and one of
    1,024 bearings took 253 MB more than the 3,000 alone (memory grew with problems x the largest one, so a
    cheap batch could take gigabytes); read in groups of like size, 5 MB. Peak RSS in a fresh process."""
    import json
    import subprocess
    import sys

    from tests.service.sessions.helpers import REPO

    run = subprocess.run([sys.executable, "-c", _PADDING_PROBE], cwd=REPO, capture_output=True, text=True,
                         check=False, timeout=300)
    assert run.returncode == 0, run.stderr[-2000:]
    probe = json.loads(run.stdout.strip().splitlines()[-1])
    assert probe["ok"] == 3001
    assert probe["growth_mb"] < 60, probe
