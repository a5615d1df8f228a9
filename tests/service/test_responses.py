"""Responses written ahead: a JsonObject is written as its bytes and read as the mapping they hold."""

from __future__ import annotations

import numpy as np
import orjson

from bench.scenarios import four_station_requests
from service.responses import JsonObject, dumps
from service.fixes.pipeline import fix_results


def test_a_json_object_is_written_as_its_bytes_and_reads_as_their_fields():
    text = b'{"method":"ml","x":[1.5,null],"y":{"z":true}}'
    value = JsonObject(text, {"method": "ml"})
    assert dumps({"fix": value, "n": np.arange(2)}) == b'{"fix":' + text + b',"n":[0,1]}'
    assert value["method"] == "ml" and value["x"] == [1.5, None] and value.get("w") is None
    assert dict(value) == orjson.loads(text) and list(value) == ["method", "x", "y"] and len(value) == 3
    assert value == JsonObject(text) and value == orjson.loads(text)


def test_a_fix_reads_as_the_body_it_writes():
    requests = four_station_requests(3, np.random.default_rng(4)) + [
        four_station_requests(1, np.random.default_rng(5), with_range=True, method="angle_range")[0]]
    for result in fix_results(requests):
        fix = result["fix"]
        written = orjson.loads(dumps(fix))
        assert dict(fix) == written and fix["method"] == written["method"]


def test_the_templates_of_large_fixes_are_not_kept():
    from service.fixes import write
    from tests.service.conftest import STATIONS_300KM, TARGET, bearing_request

    small = bearing_request(STATIONS_300KM, TARGET)
    large = bearing_request(STATIONS_300KM, TARGET)
    large["measurements"] = large["measurements"] * 12  # each bearing an azimuth and an elevation residual
    residuals = 2 * len(large["measurements"])
    assert residuals > write._KEPT_RESIDUALS
    write._kept_template.cache_clear()
    results = fix_results([small, large])
    assert all(r["ok"] for r in results) and len(results[1]["fix"]["residuals"]) == residuals
    assert write._kept_template.cache_info().currsize == 1
