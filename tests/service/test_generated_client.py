"""A client generated from openapi/openapi.json by openapi-python-client, used against a live uvicorn.

What a generated client gets wrong when the spec misleads it: an undeclared status parses as None, an
error declared with the wrong media type or an untyped body parses badly. So: generation must give no
warning, and every answer below (successes and errors) must parse into its declared model.
"""

from __future__ import annotations

import importlib
import importlib.metadata
import shutil
import subprocess
import sys

import pytest

from tests.service.conftest import STATIONS_300KM, TARGET, bearing_request
from tests.service.sessions.helpers import REPO, Server, api_epochs, create_body, paper_track

GENERATOR = shutil.which("openapi-python-client", path=str(REPO / ".venv" / "bin")) or \
    shutil.which("openapi-python-client")


@pytest.fixture(scope="module")
def generated(tmp_path_factory):
    """The generated package ``pl_client``, importable."""
    if GENERATOR is None:
        pytest.fail("openapi-python-client is not installed (it is a dev dependency: make install)")
    root = tmp_path_factory.mktemp("client")
    config = root / "config.yaml"
    config.write_text("post_hooks: []\nproject_name_override: pl_client\npackage_name_override: pl_client\n")
    result = subprocess.run([GENERATOR, "generate", "--path", str(REPO / "openapi" / "openapi.json"), "--meta", "none",
                             "--output-path", str(root / "pl_client"), "--config", str(config)],
                            capture_output=True, text=True, timeout=120)
    output = result.stdout + result.stderr
    assert result.returncode == 0, output
    assert "warning" not in output.lower(), output
    sys.path.insert(0, str(root))
    try:
        yield importlib.import_module("pl_client")
    finally:
        sys.path.remove(str(root))
        for name in [m for m in sys.modules if m == "pl_client" or m.startswith("pl_client.")]:
            del sys.modules[name]


@pytest.fixture(scope="module")
def server(tmp_path_factory):
    root = tmp_path_factory.mktemp("server")
    with Server(f"sqlite:///{root}/sessions.db", root / "server.log") as running:
        yield running


def test_generated_client_round_trips(generated, server):
    from pl_client import Client
    from pl_client.api.fixes import fixes_batch, fixes_create, fixes_crlb
    from pl_client.api.sessions import sessions_create, sessions_delete, sessions_get, sessions_post_measurements
    from pl_client.models import (BatchRequest, BatchResponse, CrlbRequest, CrlbResponse, FixRequest, FixResponse,
                                  MeasurementBatch, MeasurementResult, Problem, SessionCreate, SessionState)

    client = Client(base_url=server.url, timeout=60.0, raise_on_unexpected_status=True)
    request = bearing_request(STATIONS_300KM, TARGET, formats=["geojson", "cot"], cot={"uid": "gen-1"},
                              observed_at="2026-05-06T07:08:09Z")

    fix = fixes_create.sync(client=client, body=FixRequest.from_dict(request))
    assert isinstance(fix, FixResponse), fix
    assert fix.position.lat_deg == pytest.approx(TARGET["lat_deg"], abs=1e-6)
    assert fix.geojson.features[0].geometry.type_ == "Point"
    assert 'uid="gen-1"' in fix.cot

    unknown_station = bearing_request(STATIONS_300KM, TARGET)
    unknown_station["measurements"][0]["station_id"] = "rx-9"
    batch = fixes_batch.sync(client=client, body=BatchRequest.from_dict(
        {"problems": [bearing_request(STATIONS_300KM, TARGET), unknown_station], "formats": ["geojson"]}))
    assert isinstance(batch, BatchResponse), batch
    assert [r.ok for r in batch.results] == [True, False]
    error = batch.results[1].error
    assert isinstance(error, Problem) and error.status == 422 and error.errors[0].loc[0] == "measurements"
    assert len(batch.geojson.features) == 2

    sensors = [{"station_id": sid, "sigma_azimuth_deg": 1.0, "sigma_elevation_deg": 1.0} for sid in STATIONS_300KM]
    bound = fixes_crlb.sync(client=client, body=CrlbRequest.from_dict(
        {"stations": request["stations"], "sensors": sensors, "target": TARGET}))
    assert isinstance(bound, CrlbResponse), bound
    assert bound.error.ellipse95.semi_major_m > bound.error.ellipse95.semi_minor_m > 0

    created = sessions_create.sync_detailed(client=client, body=SessionCreate.from_dict(create_body(frame="wgs84")))
    assert created.status_code == 201 and isinstance(created.parsed, SessionState)
    session_id = created.parsed.id
    epochs = api_epochs(paper_track(seed=2, epochs=30))
    posted = sessions_post_measurements.sync(session_id=session_id, client=client,
                                             body=MeasurementBatch.from_dict({"measurements": epochs}))
    assert isinstance(posted, MeasurementResult) and posted.applied == 30
    state = sessions_get.sync(session_id=session_id, client=client, formats="cot,geojson")
    assert isinstance(state, SessionState) and state.version == 2 and "<track" in state.cot
    assert sessions_delete.sync_detailed(session_id=session_id, client=client).status_code == 204

    missing = sessions_get.sync(session_id=session_id, client=client)
    assert isinstance(missing, Problem) and missing.status == 404 and missing.code == "not_found"
    bad = dict(request, method="no-such-method")
    raw = client.get_httpx_client().post("/v1/fixes", json=bad)
    assert raw.status_code == 422 and raw.headers["content-type"].startswith("application/problem+json")
    problem = Problem.from_dict(raw.json())
    assert problem.errors[0].loc == ["method"] and problem.instance.endswith(problem.request_id)
    malformed = client.get_httpx_client().post("/v1/fixes", content=b"{", headers={"content-type": "application/json"})
    parsed = fixes_create._parse_response(client=client, response=malformed)
    assert isinstance(parsed, Problem) and parsed.status == 400


def test_every_error_is_problem_json_and_no_fastapi_validation_model():
    import json

    spec = json.loads((REPO / "openapi" / "openapi.json").read_text())
    assert spec["info"]["version"] == importlib.metadata.version("passive-locator")
    assert spec["components"]["securitySchemes"]["bearer"] == {**spec["components"]["securitySchemes"]["bearer"],
                                                                "type": "http", "scheme": "bearer"}
    assert not {"HTTPValidationError", "ValidationError"} & set(spec["components"]["schemas"])
    for path, operations in spec["paths"].items():
        for method, operation in operations.items():
            codes = {int(c) for c in operation["responses"]}
            assert {429, 500} <= codes, (path, method)
            if "requestBody" in operation:
                assert {400, 413, 415, 422} <= codes, (path, method)
            if path.startswith("/v1/"):
                assert {401, 403} <= codes and operation["security"] == [{"bearer": []}, {}], (path, method)
            if "{session_id}" in path:
                assert 404 in codes, (path, method)
            for code, response in operation["responses"].items():
                if int(code) >= 400:
                    assert response["content"] == {"application/problem+json": {
                        "schema": {"$ref": "#/components/schemas/Problem"}}}, (path, method, code)
    names = set(spec["components"]["schemas"])
    assert {"BatchRequest", "Problem", "ProblemError", "FeatureCollection", "Health", "Readiness"} <= names


def test_generated_names_come_from_the_schemas(generated):
    """Every model is named after a schema (a title or a component), not after where an anonymous schema sat
    (``OptionsVariantType0``, ``SessionsEventsResponse200Event``)."""
    import pl_client.models as models

    names = [name for name in dir(models) if not name.startswith("_")]
    assert {"FixResponse", "SessionEvent", "CrlbGridResponse"} <= set(names)
    assert not [n for n in names if any(part in n for part in ("Variant", "Type0", "Type1", "Response200"))], names


def test_the_event_stream_and_the_map_files_reach_a_generated_client_as_they_were_sent(generated, server):
    import threading
    import time

    import httpx
    from pl_client import Client
    from pl_client.api.fixes import fixes_crlb_grid, fixes_crlb_grid_map
    from pl_client.api.sessions import sessions_create, sessions_events, sessions_post_measurements
    from pl_client.models import CrlbGridRequest, CrlbGridResponse, MeasurementBatch, SessionCreate
    from pl_client.types import File

    client = Client(base_url=server.url, timeout=60.0, raise_on_unexpected_status=True)
    session = sessions_create.sync(client=client, body=SessionCreate.from_dict(create_body(frame="wgs84")))
    sessions_post_measurements.sync(session_id=session.id, client=client, body=MeasurementBatch.from_dict(
        {"measurements": api_epochs(paper_track(seed=3, epochs=12))}))
    # The stream lasts while the session lives: end it from outside, then the generated call returns the text.
    ender = threading.Timer(2.0, lambda: httpx.delete(f"{server.url}/v1/sessions/{session.id}", timeout=30))
    ender.start()
    started = time.monotonic()
    try:
        answer = sessions_events.sync_detailed(session_id=session.id, client=client)
    finally:
        ender.join()
    assert answer.status_code == 200 and time.monotonic() - started < 50
    assert isinstance(answer.parsed, str) and answer.parsed == answer.content.decode()
    events = [dict(line.split(": ", 1) for line in block.splitlines() if not line.startswith(":"))
              for block in answer.parsed.split("\n\n") if block.strip() and not block.startswith(":")]
    assert [(e["event"], e.get("id")) for e in events] == [("state", "2"), ("deleted", None)], events

    stations = [{"id": "rx-1", "position": {"lat_deg": 34.0, "lon_deg": 108.0, "alt_m": 100.0}},
                {"id": "rx-2", "position": {"lat_deg": 34.0, "lon_deg": 108.6, "alt_m": 100.0}}]
    request = {"stations": stations,
               "sensors": [{"station_id": s["id"], "sigma_azimuth_deg": 0.5, "sigma_elevation_deg": 0.5}
                           for s in stations],
               "grid": {"centre": {"lat_deg": 34.3, "lon_deg": 108.3}, "half_width_m": 30_000.0, "step_m": 10_000.0,
                        "altitude_m": 8000.0}}
    geojson = fixes_crlb_grid.sync(client=client, body=CrlbGridRequest.from_dict(request))
    assert isinstance(geojson, CrlbGridResponse) and len(geojson.features) == 49 + 2
    from pl_client.models import FixesCrlbGridMapFormat

    for format_, accept, signature in ((FixesCrlbGridMapFormat.PNG, "image/png", b"\x89PNG\r\n\x1a\n"),
                                       (FixesCrlbGridMapFormat.KMZ, "application/vnd.google-earth.kmz", b"PK\x03\x04"),
                                       (FixesCrlbGridMapFormat.TIFF, "image/tiff", b"II*\x00")):
        picture = fixes_crlb_grid_map.sync(client=client, body=CrlbGridRequest.from_dict(request), format_=format_)
        assert isinstance(picture, File)
        data = picture.payload.read()
        assert data.startswith(signature)
        sent = httpx.post(f"{server.url}/v1/crlb/grid", json=request, headers={"Accept": accept}, timeout=60)
        assert sent.status_code == 200 and data == sent.content
