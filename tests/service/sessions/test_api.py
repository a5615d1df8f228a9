"""The session API contract (API.md, Sessions), through the real app on each store."""

from __future__ import annotations

import hashlib
import math
import time

import numpy as np
import orjson
import pytest
from fastapi.testclient import TestClient

from core import geodesy
from service.app import create_app
from service.schemas.sessions import MeasurementResult, SessionList, SessionState
from service.settings import Settings

from .helpers import OBSERVER_WGS84, api_epochs, create_body, filter_view, paper_track

KEYS = ["key-alice", "key-bob"]
ALICE = {"Authorization": "Bearer key-alice"}
BOB = {"Authorization": "Bearer key-bob"}


@pytest.fixture
def client(store_url, clock):
    hashes = ",".join(hashlib.sha256(key.encode()).hexdigest() for key in KEYS)
    with TestClient(create_app(Settings(store=store_url, api_key_hashes=hashes))) as c:
        c.app.state.store.clock = clock
        c.headers.update(ALICE)
        yield c


@pytest.fixture(scope="module")
def epochs() -> list[dict]:
    return api_epochs(paper_track(seed=11, epochs=60))


def create(client, **changes) -> dict:
    response = client.post("/v1/sessions", json=create_body(**changes))
    assert response.status_code == 201, response.text
    return response.json()


def post(client, session_id: str, measurements: list[dict], **kwargs):
    return client.post(f"/v1/sessions/{session_id}/measurements", json={"measurements": measurements}, **kwargs)


def strict_json(response) -> dict:
    """The body, refusing NaN/Infinity (orjson rejects them: the contract says every float is finite)."""
    return orjson.loads(response.content)


def test_create_answers_201_with_location_etag_and_a_fresh_state(client):
    response = client.post("/v1/sessions", json=create_body(frame="wgs84"))
    assert response.status_code == 201
    body = strict_json(response)
    SessionState.model_validate(body)
    assert response.headers["location"] == f"/v1/sessions/{body['id']}"
    assert response.headers["etag"] == '"1"'
    assert body["version"] == 1 and body["updates"] == 0 and body["last_seq"] is None
    assert body["initialized"] is False and body["position"] is None and body["covariance_enu"] is None
    assert body["model"] == "velocity_kinematic" and body["frame"] == "wgs84"
    assert body["observer"] == {"position": OBSERVER_WGS84}
    assert body["pulse_period_s"] == create_body()["pulse"]["period_s"]  # the initial estimate, as given
    assert body["ttl_s"] == 3600.0
    assert client.get(response.headers["location"]).json() == body


@pytest.mark.parametrize("change, loc", [
    (lambda b: b.update(model="kalman"), ["model"]),
    (lambda b: b["noise"].update(sigma_azimuth_deg=-1.0), ["noise", "sigma_azimuth_deg"]),
    (lambda b: b["pulse"].update(pulses_per_observation=0), ["pulse", "pulses_per_observation"]),
    (lambda b: b["pulse"].pop("period_s"), ["pulse", "period_s"]),
    (lambda b: b.update(ttl_s=0), ["ttl_s"]),
    (lambda b: b.update(colour="red"), ["colour"]),
    (lambda b: b["observer"].update(position={"lat_deg": 91.0, "lon_deg": 0.0}), ["observer", "position", "lat_deg"]),
])
def test_create_rejects_bad_values_with_the_field_path(client, change, loc):
    body = create_body(frame="wgs84")
    change(body)
    response = client.post("/v1/sessions", json=body)
    assert response.status_code == 422
    assert response.headers["content-type"] == "application/problem+json"
    assert loc in [e["loc"] for e in response.json()["errors"]]


def test_create_rejects_an_observer_in_the_wrong_frame(client):
    body = create_body(frame="wgs84", observer={"east_m": 0.0, "north_m": 0.0})
    response = client.post("/v1/sessions", json=body)
    assert response.status_code == 422
    assert "frame" in response.json()["detail"]


def test_create_rejects_nan(client):
    raw = orjson.dumps(create_body()).replace(b'"sigma_toa_s":1e-8', b'"sigma_toa_s":NaN')
    response = client.post("/v1/sessions", content=raw, headers={"content-type": "application/json"})
    assert response.status_code in (400, 422)
    assert response.headers["content-type"] == "application/problem+json"


def test_post_applies_epochs_and_reports_the_state(client, epochs):
    session = create(client)
    response = post(client, session["id"], epochs[:30])
    assert response.status_code == 200
    body = strict_json(response)
    MeasurementResult.model_validate(body)
    assert response.headers["etag"] == '"2"'
    assert (body["version"], body["applied"], body["duplicates"]) == (2, 30, 0)
    assert (body["updates"], body["last_seq"], body["last_time_s"]) == (30, 30, epochs[29]["time_s"])
    assert body["initialized"] is True
    covariance = np.array(body["covariance_enu"])
    assert covariance.shape == (6, 6)
    assert np.allclose(covariance, covariance.T) and np.all(np.linalg.eigvalsh(covariance) > 0)
    p = body["position_local"]
    assert body["range_m"] == pytest.approx(math.hypot(p["east_m"], p["north_m"], p["up_m"]), rel=1e-12)
    assert len(body["velocity_enu_mps"]) == 3
    fetched = client.get(f"/v1/sessions/{session['id']}")
    assert fetched.headers["etag"] == '"2"'
    assert fetched.json() == {k: v for k, v in body.items() if k not in ("applied", "duplicates")}


def test_a_retried_batch_is_acknowledged_and_changes_nothing(client, epochs):
    session = create(client)
    first = post(client, session["id"], epochs[:20]).json()
    again = post(client, session["id"], epochs[:20])
    assert again.status_code == 200
    body = again.json()
    assert (body["applied"], body["duplicates"], body["version"]) == (0, 20, first["version"])
    assert {k: v for k, v in body.items() if k not in ("applied", "duplicates")} == \
           {k: v for k, v in first.items() if k not in ("applied", "duplicates")}


def test_an_overlapping_batch_applies_only_its_new_epochs(client, epochs):
    session = create(client)
    post(client, session["id"], epochs[:20])
    body = post(client, session["id"], epochs[15:30]).json()
    assert (body["applied"], body["duplicates"], body["updates"], body["last_seq"]) == (10, 5, 30, 30)
    # the same as posting 1..30 at once
    other = create(client)
    assert filter_view(post(client, other["id"], epochs[:30]).json()) == filter_view(body)


def test_gaps_in_seq_are_allowed(client, epochs):
    session = create(client)
    kept = [e for i, e in enumerate(epochs[:40]) if i % 3 != 1]
    body = post(client, session["id"], kept).json()
    assert (body["applied"], body["updates"], body["last_seq"]) == (len(kept), len(kept), kept[-1]["seq"])
    late = post(client, session["id"], [epochs[1]]).json()  # seq 2 was skipped: now below the mark
    assert (late["applied"], late["duplicates"], late["updates"]) == (0, 1, len(kept))


def test_time_going_back_is_409_and_nothing_of_the_batch_is_applied(client, epochs):
    session = create(client)
    before = post(client, session["id"], epochs[:20]).json()
    batch = [dict(e) for e in epochs[20:30]]
    batch[6]["time_s"] = batch[5]["time_s"]  # not after the previous epoch
    response = post(client, session["id"], batch)
    assert response.status_code == 409
    problem = response.json()
    assert problem["code"] == "time_not_increasing"
    assert problem["errors"][0]["loc"] == ["measurements", 6, "time_s"]
    after = client.get(f"/v1/sessions/{session['id']}")
    assert after.headers["etag"] == '"2"'
    assert filter_view(after.json()) == filter_view(before)
    back = dict(epochs[20], time_s=epochs[10]["time_s"])  # behind the last applied epoch
    response = post(client, session["id"], [back])
    assert response.status_code == 409 and response.json()["errors"][0]["loc"] == ["measurements", 0, "time_s"]
    assert post(client, session["id"], epochs[20:30]).json()["updates"] == 30


def test_if_match(client, epochs):
    session = create(client)
    post(client, session["id"], epochs[:10])
    stale = post(client, session["id"], epochs[10:20], headers={"If-Match": '"1"'})
    assert stale.status_code == 412 and stale.json()["code"] == "precondition_failed"
    assert client.get(f"/v1/sessions/{session['id']}").json()["updates"] == 10
    fresh = post(client, session["id"], epochs[10:20], headers={"If-Match": '"2"'})
    assert fresh.status_code == 200 and fresh.headers["etag"] == '"3"' and fresh.json()["updates"] == 20
    assert post(client, session["id"], epochs[20:21], headers={"If-Match": "*"}).status_code == 200


def test_bad_epochs_are_422_with_their_path(client, epochs):
    session = create(client)
    bad = [dict(epochs[0]), dict(epochs[1], elevation_deg=90.0)]
    response = post(client, session["id"], bad)
    assert response.status_code == 422
    assert ["measurements", 1, "elevation_deg"] in [e["loc"] for e in response.json()["errors"]]
    response = post(client, session["id"], [epochs[1], epochs[0]])
    assert response.status_code == 422 and "seq" in response.json()["detail"]
    response = post(client, session["id"], [])
    assert response.status_code == 422 and response.json()["errors"][0]["loc"] == ["measurements"]
    response = post(client, session["id"], [{k: v for k, v in epochs[0].items() if k != "toa_s"}])
    assert response.json()["errors"][0]["loc"] == ["measurements", 0, "toa_s"]
    assert client.get(f"/v1/sessions/{session['id']}").json()["updates"] == 0


def test_unknown_sessions_are_404(client, epochs):
    for session_id in ("0" * 32, "not-an-id"):
        for response in (client.get(f"/v1/sessions/{session_id}"), post(client, session_id, epochs[:1]),
                         client.delete(f"/v1/sessions/{session_id}")):
            assert response.status_code == 404
            assert response.json()["code"] == "not_found"


def test_sessions_belong_to_the_key_that_made_them(client, epochs):
    session = create(client)
    url = f"/v1/sessions/{session['id']}"
    assert client.get(url, headers=BOB).status_code == 404
    assert post(client, session["id"], epochs[:5], headers=BOB).status_code == 404
    assert client.delete(url, headers=BOB).status_code == 404
    assert client.get("/v1/sessions", headers=BOB).json()["sessions"] == []
    assert client.get(url, headers={"Authorization": ""}).status_code == 401
    assert client.get(url, headers={"Authorization": "Bearer nope"}).status_code == 401
    assert client.get(url).json()["updates"] == 0


def test_list_pages_through_every_session_once_in_creation_order(client, clock):
    created = []
    for _ in range(7):
        created.append(create(client)["id"])
        clock.advance(0.002)  # ids carry a millisecond time prefix
    other = client.post("/v1/sessions", json=create_body(), headers=BOB).json()["id"]
    seen, cursor, pages = [], None, 0
    while True:
        params = {"limit": 3} | ({"cursor": cursor} if cursor else {})
        response = client.get("/v1/sessions", params=params)
        assert response.status_code == 200
        body = SessionList.model_validate(response.json())
        pages += 1
        seen += [s.id for s in body.sessions]
        cursor = body.next_cursor
        if cursor is None:
            break
    assert seen == created and other not in seen
    assert pages == 3


@pytest.mark.parametrize("params, loc", [({"limit": 0}, ["query", "limit"]), ({"limit": 501}, ["query", "limit"]),
                                         ({"cursor": "!!!"}, ["query", "cursor"]),
                                         ({"cursor": "ZGVhZGJlZWY"}, ["query", "cursor"])])
def test_list_rejects_bad_paging(client, params, loc):
    response = client.get("/v1/sessions", params=params)
    assert response.status_code == 422
    assert response.json()["errors"][0]["loc"] == loc


def test_delete(client):
    session = create(client)
    url = f"/v1/sessions/{session['id']}"
    response = client.delete(url)
    assert response.status_code == 204 and response.content == b""
    assert client.get(url).status_code == 404
    assert client.delete(url).status_code == 404
    assert client.get("/v1/sessions").json()["sessions"] == []


def test_expired_sessions_are_gone_and_writes_extend_the_lifetime(client, clock, epochs):
    kept = create(client, ttl_s=60.0)
    idle = create(client, ttl_s=60.0)
    clock.advance(50.0)
    assert post(client, kept["id"], epochs[:5]).status_code == 200  # expires 60 s from now
    clock.advance(15.0)
    assert client.get(f"/v1/sessions/{idle['id']}").status_code == 404
    assert post(client, idle["id"], epochs[:5]).status_code == 404
    assert client.delete(f"/v1/sessions/{idle['id']}").status_code == 404
    assert [s["id"] for s in client.get("/v1/sessions").json()["sessions"]] == [kept["id"]]
    assert client.get(f"/v1/sessions/{kept['id']}").status_code == 200
    clock.advance(45.0)
    assert client.get(f"/v1/sessions/{kept['id']}").status_code == 404
    assert client.get("/v1/sessions").json()["sessions"] == []


def test_a_retry_does_not_extend_the_lifetime(client, clock, epochs):
    session = create(client, ttl_s=60.0)
    post(client, session["id"], epochs[:5])
    clock.advance(40.0)
    assert post(client, session["id"], epochs[:5]).json()["duplicates"] == 5
    clock.advance(25.0)
    assert client.get(f"/v1/sessions/{session['id']}").status_code == 404


def test_wgs84_and_local_frames_agree(client, epochs):
    wgs84 = create(client, frame="wgs84")
    local = create(client, frame="local", observer={"east_m": 1000.0, "north_m": -2000.0, "up_m": 5.0})
    a = post(client, wgs84["id"], epochs[:40]).json()
    b = post(client, local["id"], epochs[:40]).json()
    assert a["velocity_enu_mps"] == b["velocity_enu_mps"] and a["covariance_enu"] == b["covariance_enu"]
    assert b["position"] is None
    enu = np.array([a["position_local"][k] for k in ("east_m", "north_m", "up_m")])
    shifted = np.array([b["position_local"][k] for k in ("east_m", "north_m", "up_m")]) - [1000.0, -2000.0, 5.0]
    assert np.allclose(enu, shifted, rtol=0, atol=1e-9)  # 1 nm
    p, o = a["position"], OBSERVER_WGS84
    back = geodesy.geodetic_to_enu(math.radians(p["lat_deg"]), math.radians(p["lon_deg"]), p["alt_m"],
                                   math.radians(o["lat_deg"]), math.radians(o["lon_deg"]), o["alt_m"])
    assert np.allclose(back, enu, rtol=0, atol=1e-6)  # 1 micrometre


def test_both_models_and_a_known_period(client, epochs):
    for model in ("velocity_kinematic", "joint_ukf"):
        for known in (False, True):
            session = create(client, model=model, period_known=known)
            body = post(client, session["id"], epochs).json()
            assert body["model"] == model and body["initialized"] and body["updates"] == len(epochs)
            if known:
                assert body["pulse_period_s"] == 1e-3
            assert body["range_m"] == pytest.approx(np.linalg.norm([120e3, 100e3, 8e3]), rel=0.3)


def test_the_routes_have_their_operation_ids(client):
    spec = client.get("/openapi.json").json()
    ids = {op["operationId"] for path in spec["paths"].values() for op in path.values()}
    assert {"sessions-create", "sessions-post-measurements", "sessions-get", "sessions-list",
            "sessions-delete"} <= ids


def test_metrics_count_applied_and_duplicate_epochs(client, epochs):
    session = create(client)
    post(client, session["id"], epochs[:10])
    post(client, session["id"], epochs[5:12])
    from tests.service.test_metrics import sample

    text = client.get("/metrics").text
    assert sample(text, "passive_locator_sessions_created_total") == 1
    assert sample(text, "passive_locator_session_epochs_applied_total") == 12
    assert sample(text, "passive_locator_session_epochs_duplicate_total") == 5
    assert sample(text, "passive_locator_session_updates_total") == 2


def test_a_post_whose_filter_outlasts_the_store_call_deadline_is_applied(store_url, clock, epochs, monkeypatch):
    # The filter steps run before the store's read-modify-write, not inside its call deadline: a post whose
    # steps take longer than store_call_timeout_s is a 200, not a 503 store_unavailable on a healthy store.
    from service.sessions import observer as sessions

    real = sessions.step_many

    def slow_steps(*args):
        time.sleep(0.4)
        return real(*args)

    monkeypatch.setattr(sessions, "step_many", slow_steps)
    with TestClient(create_app(Settings(store=store_url, store_call_timeout_s=0.1))) as c:
        c.app.state.store.clock = clock
        session = create(c)
        count = sessions.INLINE_EPOCHS + 1
        response = post(c, session["id"], epochs[:count])
        assert response.status_code == 200, response.text
        assert (response.json()["applied"], response.json()["version"]) == (count, 2)


def test_a_post_past_the_request_deadline_is_503_and_applies_nothing(store_url, clock, epochs, monkeypatch):
    from service.sessions import observer as sessions

    real = sessions.tracker_epoch
    stepped = []

    def slow_epoch(epoch):
        stepped.append(epoch)
        time.sleep(0.02)
        return real(epoch)

    monkeypatch.setattr(sessions, "tracker_epoch", slow_epoch)
    monkeypatch.setattr(sessions, "STOP_CHECK_EPOCHS", 4)
    with TestClient(create_app(Settings(store=store_url, request_deadline_s=0.2))) as c:
        c.app.state.store.clock = clock
        session = create(c)
        response = post(c, session["id"], epochs)
        assert response.status_code == 503 and response.json()["code"] == "deadline_exceeded", response.text
        assert len(stepped) < len(epochs), len(stepped)  # the steps stopped at a check, before all of them ran
        time.sleep(0.2)
        state = c.get(f"/v1/sessions/{session['id']}").json()
        assert (state["version"], state["updates"]) == (1, 0)


def test_a_post_overtaken_by_another_is_decided_again_against_the_latest_record(store, clock, epochs):
    # A change prepared for version 1 while another post wrote version 2: the store reads again, and the
    # change is decided against version 2 (its overlapping epochs are duplicates there), never written over it.
    from service.schemas import sessions as schemas
    from service.sessions import observer as sessions

    request = schemas.SessionCreate.model_validate(create_body())
    first = sessions.create(store, "alice", request)
    late = sessions.MeasurementsChange(schemas.MeasurementBatch.model_validate({"measurements": epochs[:8]}), None,
                                       clock=store.now)
    late.prepare(first)
    assert late.applied == 8
    early = sessions.MeasurementsChange(schemas.MeasurementBatch.model_validate({"measurements": epochs[:5]}), None,
                                        clock=store.now)
    assert sessions.post_measurements(store, "alice", first.id, early).record.version == 2
    outcome = sessions.post_measurements(store, "alice", first.id, late, first)
    assert (outcome.record.version, outcome.applied, outcome.duplicates) == (3, 3, 5)
    assert (outcome.record.updates, outcome.record.last_seq) == (8, epochs[7]["seq"])


def test_a_long_post_prepared_off_the_store_call_answers_as_a_short_one(client, epochs):
    from service.sessions import observer as sessions

    long = sessions.INLINE_EPOCHS + 1
    session = create(client)
    assert post(client, "0" * 32, epochs[:long]).status_code == 404
    stale = post(client, session["id"], epochs[:long], headers={"If-Match": '"7"'})
    assert stale.status_code == 412 and stale.json()["code"] == "precondition_failed"
    backwards = [dict(e) for e in epochs[:long]]
    backwards[long - 1]["time_s"] = backwards[long - 2]["time_s"]
    response = post(client, session["id"], backwards)
    assert response.status_code == 409 and response.json()["errors"][0]["loc"] == ["measurements", long - 1, "time_s"]
    assert client.get(f"/v1/sessions/{session['id']}").json()["updates"] == 0
    first = post(client, session["id"], epochs[:long]).json()
    assert (first["applied"], first["duplicates"], first["version"]) == (long, 0, 2)
    overlapping = post(client, session["id"], epochs[long - 10:2 * long - 10]).json()
    assert (overlapping["applied"], overlapping["duplicates"], overlapping["version"]) == (long - 10, 10, 3)
