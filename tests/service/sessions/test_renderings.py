"""A session's state as a CoT track and as GeoJSON (``GET /v1/sessions/{id}?formats=cot,geojson``)."""

from __future__ import annotations

import math

import geojson
import numpy as np
import pytest
from fastapi.testclient import TestClient
from shapely.geometry import LinearRing

from core import geodesy
from service.app import create_app
from service.schemas.sessions import SessionState
from service.settings import Settings
from tests.service.test_renderings import cot_event

from .helpers import api_epochs, create_body, paper_track


@pytest.fixture
def client(tmp_path):
    with TestClient(create_app(Settings(store=f"sqlite:///{tmp_path}/s.db"))) as c:
        yield c


@pytest.fixture(scope="module")
def epochs() -> list[dict]:
    return api_epochs(paper_track(seed=5, epochs=40))


def _session(client, epochs, **create) -> dict:
    body = create_body(frame="wgs84", **create.pop("changes", {}))
    body.update(create)
    session = client.post("/v1/sessions", json=body).json()
    response = client.post(f"/v1/sessions/{session['id']}/measurements", json={"measurements": epochs})
    assert response.status_code == 200, response.text
    return response.json()


def _at_emitter(state: dict) -> tuple[np.ndarray, np.ndarray]:
    o, p = state["observer"]["position"], state["position"]
    turn = geodesy.enu_to_enu_rotation(*np.radians([o["lat_deg"], o["lon_deg"], p["lat_deg"], p["lon_deg"]]))
    covariance = np.array(state["covariance_enu"])[:3, :3]
    return turn @ covariance @ turn.T, turn @ np.array(state["velocity_enu_mps"])


def test_session_as_a_cot_track_and_geojson(client, epochs):
    state = _session(client, epochs)
    assert state["initialized"]
    response = client.get(f"/v1/sessions/{state['id']}", params={"formats": "cot,geojson"})
    assert response.status_code == 200, response.text
    body = response.json()
    SessionState.model_validate(body)
    event = cot_event(body["cot"])
    assert event.get("uid") == f"passive-locator-session-{state['id']}" and event.get("how") == "m-p"
    covariance, velocity = _at_emitter(body)
    track = event.find("detail/track")
    assert float(track.get("speed")) == pytest.approx(math.hypot(velocity[0], velocity[1]), abs=1e-3)
    assert float(track.get("course")) == pytest.approx(math.degrees(math.atan2(velocity[0], velocity[1])) % 360,
                                                       abs=0.01)
    point = event.find("point")
    assert float(point.get("ce")) == pytest.approx(math.sqrt(np.trace(covariance[:2, :2]) / 2), abs=0.006)
    assert float(point.get("le")) == pytest.approx(math.sqrt(covariance[2, 2]), abs=0.006)

    collection = body["geojson"]
    assert geojson.loads(geojson.dumps(collection)).is_valid
    point_feature, ellipse = collection["features"]
    assert point_feature["properties"]["speed_mps"] == pytest.approx(float(track.get("speed")), abs=1e-3)
    ring = ellipse["geometry"]["coordinates"][0]
    assert ring[0] == ring[-1] and LinearRing(ring).is_ccw and len(ring) >= 65
    assert "cot" not in client.get(f"/v1/sessions/{state['id']}").json()  # only when asked for


def test_one_uid_per_session_across_updates_and_the_requested_uid(client, epochs):
    state = _session(client, epochs[:30], cot={"uid": "tracked-7", "type": "a-h-A", "stale_s": 30})
    first = cot_event(client.get(f"/v1/sessions/{state['id']}?formats=cot").json()["cot"])
    client.post(f"/v1/sessions/{state['id']}/measurements", json={"measurements": epochs[30:]})
    second = cot_event(client.get(f"/v1/sessions/{state['id']}?formats=cot").json()["cot"])
    assert first.get("uid") == second.get("uid") == "tracked-7"
    assert second.get("type") == "a-h-A"
    assert first.find("detail/passive_locator").get("version") != second.find("detail/passive_locator").get("version")


def test_no_rendering_before_the_filter_has_an_estimate_or_off_the_earth(client, epochs):
    session = client.post("/v1/sessions", json=create_body(frame="wgs84")).json()
    body = client.get(f"/v1/sessions/{session['id']}?formats=cot,geojson").json()
    assert body["cot"] is None and body["geojson"] == {"type": "FeatureCollection", "features": []}
    local = client.post("/v1/sessions", json=create_body(frame="local")).json()
    client.post(f"/v1/sessions/{local['id']}/measurements", json={"measurements": epochs})
    assert client.get(f"/v1/sessions/{local['id']}?formats=cot").json()["cot"] is None


@pytest.mark.parametrize("formats", ["kml", "cot,", "cot;geojson"])
def test_unknown_formats_are_422(client, formats):
    session = client.post("/v1/sessions", json=create_body(frame="wgs84")).json()
    response = client.get(f"/v1/sessions/{session['id']}", params={"formats": formats})
    assert response.status_code == 422
    assert response.json()["errors"][0]["loc"][-1] == "formats"


@pytest.mark.parametrize("cot, expected", [(None, None), ({"callsign": "Track Alpha"}, "Track Alpha"),
                                           ({"uid": "emitter-9"}, "emitter-9")])
def test_a_session_track_carries_a_contact_callsign_default_its_uid(client, epochs, cot, expected):
    state = _session(client, epochs, **({} if cot is None else {"cot": cot}))
    body = client.get(f"/v1/sessions/{state['id']}", params={"formats": "cot"}).json()
    event = cot_event(body["cot"])
    assert event.find("detail/contact").get("callsign") == (expected or event.get("uid"))
