"""The fast reader (msgspec structs, then bulk checks) answers every body exactly as the schema path does.

Each field of two full requests (geodetic with every option, local with an
origin) is replaced by values of every JSON type and edge (integers, huge
numbers, booleans, strings, null, lists, objects, NaN and infinity as
non-JSON literals), deleted, or joined by an unknown field. Every such body
gets the same answer, byte for byte, whether it arrives as JSON bytes (the
routes' decoder) or as parsed dicts, and the schema's answer (the schema and
``to_problem`` alone): the same error body, or a fix equal to round-off (the
frame is placed by the batch builder or by ``build_problem``). The reader is
never more lenient than the schema and never words an error differently.
"""

from __future__ import annotations

import copy
import json
import re

import numpy as np
import orjson
import pytest

from service import schemas
from service.fixes import decode as wire
from service.fixes import read as reader
from service.web.deps import parse_json
from service.web.responses import dumps
from service.fixes.rules import READ_FIELDS
from service.fixes.pipeline import fix_results
from tests.service.test_batch import assert_close

FULL = {
    "frame": "wgs84",
    "method": "ml",
    "origin": {"lat_deg": 34.1, "lon_deg": 108.6, "alt_m": 10.0},
    "stations": [{"id": "a", "position": {"lat_deg": 34.0, "lon_deg": 108.5, "alt_m": 100.0}},
                 {"id": "b", "position": {"lat_deg": 34.3, "lon_deg": 108.9, "alt_m": 50.0}},
                 {"id": "c", "position": {"lat_deg": 34.2, "lon_deg": 108.2}}],
    "measurements": [
        {"type": "bearing", "station_id": "a", "azimuth_deg": 40.0, "elevation_deg": 2.0,
         "sigma_azimuth_deg": 0.5, "sigma_elevation_deg": 0.5},
        {"type": "bearing", "station_id": "c", "azimuth_deg": 80.0, "sigma_azimuth_deg": 0.5},
        {"type": "range", "station_id": "b", "range_m": 30_000.0, "sigma_m": 50.0},
        {"type": "toa", "station_id": "b", "toa_s": 1e-3, "sigma_s": 1e-8},
    ],
    "constraints": {"altitude_m": 2000.0},
    "options": {"max_iterations": 40, "tolerance_m": 0.01, "initial_guess": {"lat_deg": 34.3, "lon_deg": 108.7},
                "outliers": "report", "absolute_sigma": False, "loss": "linear", "loss_scale": 1.0},
    "formats": ["geojson"],
}
LOCAL = {
    "frame": "local",
    "stations": [{"id": "a", "position": {"east_m": 0.0, "north_m": 0.0, "up_m": 0.0}},
                 {"id": "b", "position": {"east_m": 9e3, "north_m": 2e3}},
                 {"id": "c", "position": {"east_m": -4e3, "north_m": 7e3, "up_m": 30.0}}],
    "measurements": [
        {"type": "bearing", "station_id": "a", "azimuth_deg": 40.0, "elevation_deg": 2.0,
         "sigma_azimuth_deg": 0.5, "sigma_elevation_deg": 0.5},
        {"type": "bearing", "station_id": "b", "azimuth_deg": 300.0, "elevation_deg": 1.0,
         "sigma_azimuth_deg": 0.5, "sigma_elevation_deg": 0.5},
        {"type": "bearing", "station_id": "c", "azimuth_deg": 170.0, "elevation_deg": 1.5,
         "sigma_azimuth_deg": 0.5, "sigma_elevation_deg": 0.5},
    ],
    "options": {"initial_guess": {"east_m": 1e3, "north_m": 2e4}, "variant": None},
}
VALUES = [0, 3, -7, 2.5, -1e-300, 1e300, 10**20, 10**400, True, False, None, "", "ml", "x" * 129, [], [1.0], {},
          {"lat_deg": 1.0}, float("nan"), float("inf")]


def _paths(node, path=()):
    """Every ``(path, node)`` of a body, the body itself first."""
    yield path, node
    if isinstance(node, dict):
        for key, value in node.items():
            yield from _paths(value, (*path, key))
    elif isinstance(node, list):
        for i, value in enumerate(node):
            yield from _paths(value, (*path, i))


def _changed(body, path, change):
    body = copy.deepcopy(body)
    node = body
    for key in path[:-1]:
        node = node[key]
    change(node, path[-1])
    return body


def _set(value):
    def change(node, key):
        node[key] = value
    return change


def _delete(node, key):
    del node[key]


def _mutations() -> list:
    bodies = []
    for base in (FULL, LOCAL):
        bodies.append(base)
        for path, node in list(_paths(base))[1:]:
            bodies.extend(_changed(base, path, _set(value)) for value in VALUES)
            bodies.append(_changed(base, path, _delete))
            bodies.append(_changed(base, path, _set(copy.deepcopy(base)["stations"][0])))
        for path, node in _paths(base):
            if isinstance(node, dict):
                bodies.append(_changed(base, (*path, "colour"), _set("red")) if path else {**base, "colour": "red"})
    return bodies


#: A GeoJSON fix's time is the moment it was written (the bodies carry no observed_at).
_NOW = re.compile(rb'"time":"[^"]*"')


def _answers(bodies) -> list[bytes]:
    return [_NOW.sub(b'"time":""', dumps(result)) for result in fix_results(bodies, "wire")]


@pytest.fixture(scope="module")
def mutations():
    return _mutations()


def test_every_body_gets_the_schema_paths_answer(mutations, monkeypatch):
    texts = [json.dumps(body).encode() for body in mutations]
    from_bytes = _answers([wire.decode_fix(text) or parse_json(text) for text in texts])
    from_dicts = _answers([parse_json(text) for text in texts])
    monkeypatch.setattr(wire, "as_fix_body", lambda body: None)
    from_schema = _answers([parse_json(text) for text in texts])
    assert len(mutations) > 1000
    solved = sum(b'"ok":true' in answer for answer in from_schema)
    assert 50 < solved < len(mutations) - 500  # both outcomes are exercised
    for k, body in enumerate(mutations):
        assert from_bytes[k] == from_dicts[k], body
        fast, schema = orjson.loads(from_dicts[k]), orjson.loads(from_schema[k])
        if schema["ok"] and fast["ok"]:
            assert_close(fast, schema)  # one frame built two ways: equal to round-off
        else:
            assert fast == schema, body


def test_many_bodies_decode_and_the_reader_takes_the_valid_ones(mutations):
    """The check above compares the fast path with the schema only where the fast path is taken: most changes
    are type errors, which do not decode, but hundreds of bodies do."""
    decoded = [wire.decode_fix(json.dumps(body).encode()) for body in mutations]
    assert sum(d is not None for d in decoded) > 400
    read = reader._read([d for d in decoded if d is not None])
    assert len(read.accepted) > 50


def test_a_nan_literal_sigma_is_refused_with_its_path(client):
    """``NaN`` (not JSON, but some clients write it) is not the absent azimuth sigma that NaN stands for inside
    the reader: it is a 422 naming the field, alone and in a batch."""
    body = copy.deepcopy(FULL)
    del body["formats"], body["origin"]
    body["method"] = "auto"
    body["measurements"][0]["sigma_azimuth_deg"] = float("nan")
    text = json.dumps(body).encode()
    single = client.post("/v1/fixes", content=text, headers={"content-type": "application/json"})
    assert single.status_code == 422
    assert single.json()["errors"][0]["loc"] == ["measurements", 0, "sigma_azimuth_deg"]
    batch = client.post("/v1/fixes/batch", content=b'{"problems": [' + text + b"]}",
                        headers={"content-type": "application/json"})
    error = batch.json()["results"][0]["error"]
    assert (error["detail"], error["errors"]) == (single.json()["detail"], single.json()["errors"])


def test_the_struct_positions_hold_both_position_models():
    assert set(wire.Position.__struct_fields__) == (READ_FIELDS[schemas.GeodeticPosition]
                                                     | READ_FIELDS[schemas.LocalPosition])


def test_a_batch_of_structs_reads_as_its_dicts(mutations):
    """A batch whose every problem decodes is read from the structs; its answers are those of the dicts."""
    from bench.scenarios import four_station_requests

    problems = four_station_requests(50, np.random.default_rng(3))
    text = json.dumps({"problems": problems}).encode()
    decoded = wire.decode_batch(text)
    assert decoded is not None and all(type(p) is wire.FixBody for p in decoded)
    assert _answers(decoded) == _answers(problems)
