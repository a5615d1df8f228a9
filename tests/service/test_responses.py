"""Responses written ahead: a JsonObject is written as its bytes and read as the mapping they hold."""

from __future__ import annotations

import numpy as np
import orjson

from bench.scenarios import four_station_requests
from service.web.responses import JsonObject, dumps
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


def test_the_writer_writes_every_field_of_the_fix_response_schema():
    """A field added to a fix's response models fails here until the writer (service.fixes.write) writes it."""
    from service import schemas

    requests = [{**r, "formats": ["geojson", "cot"]} for r in four_station_requests(2, np.random.default_rng(6))] + [
        four_station_requests(1, np.random.default_rng(7), with_range=True, method="angle_range")[0],
        four_station_requests(1, np.random.default_rng(8), method="taylor_wls")[0]]
    for m in requests[3]["measurements"]:
        m.pop("sigma_azimuth_deg", None)  # taylor_wls then estimates each bearing's error
    fixes = [r["fix"] for r in fix_results(requests) if r["ok"]]
    assert len(fixes) == len(requests)
    models = {None: schemas.FixResponse, "error": schemas.ErrorSummary, "ellipse95": schemas.Ellipse,
              "fit": schemas.Fit, "residuals": schemas.Residual, "position": schemas.GeodeticPositionResult,
              "position_local": schemas.LocalPositionResult, "stages": schemas.Stages}
    written: dict = {name: set() for name in models}

    def walk(name, value):
        if name in models and isinstance(value, dict):
            written[name] |= set(value)
            for key, inner in value.items():
                walk(key, inner)
        elif name in models and isinstance(value, list):
            for item in value:
                walk(name, item)

    for fix in fixes:
        walk(None, orjson.loads(dumps(fix)))
    for name, model in models.items():
        assert written[name] == set(model.model_fields), (model.__name__, set(model.model_fields) ^ written[name])
