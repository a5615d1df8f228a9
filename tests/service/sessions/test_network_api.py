"""The network-session contract (API.md, "Network sessions") through the real app, on each store."""

from __future__ import annotations

import math

import geojson
import numpy as np
import orjson
import pytest
from fastapi.testclient import TestClient

from core import geodesy
from service.app import create_app
from service.schemas.sessions import NetworkSessionState, ReportResult, SessionList
from service.settings import Settings
from tests.service.test_metrics import sample
from tests.service.test_renderings import cot_event

from .helpers import create_body as observer_body
from .network_helpers import DF_STATIONS, START, bearing, create_body, df_reports, truth_at


@pytest.fixture
def client(store_url, clock):
    with TestClient(create_app(Settings(store=store_url))) as c:
        c.app.state.store.clock = clock
        yield c


def create(client, **changes) -> dict:
    response = client.post("/v1/sessions", json=create_body(**changes))
    assert response.status_code == 201, response.text
    return response.json()


def post(client, session_id: str, reports: list[dict], **kwargs):
    return client.post(f"/v1/sessions/{session_id}/reports", json={"reports": reports}, **kwargs)


def strict_json(response) -> dict:
    return orjson.loads(response.content)


def filter_view(body: dict) -> dict:
    """What the reports determine (not ids, clocks or versions)."""
    return {"last_seq": body["last_seq"], "last_time_s": body["last_time_s"], "updates": body["updates"],
            "tracks": body["tracks"], "stations": body["stations"], "ended_tracks": body["ended_tracks"]}


def test_create_answers_201_with_the_stations_and_no_track(client):
    response = client.post("/v1/sessions", json=create_body())
    assert response.status_code == 201, response.text
    body = strict_json(response)
    NetworkSessionState.model_validate(body)
    assert response.headers["location"] == f"/v1/sessions/{body['id']}" and response.headers["etag"] == '"1"'
    assert (body["model"], body["frame"], body["association"], body["reorder_window_s"]) == ("ukf", "wgs84",
                                                                                             "labelled", 2.0)
    assert [s["id"] for s in body["stations"]] == list(DF_STATIONS)
    assert all(s["moving"] is False and s["time_s"] is None for s in body["stations"])
    assert body["tracks"] == [] and body["last_seq"] is None and body["updates"] == 0
    # the frame's origin: the stations' centroid on the ellipsoid, as a fix places its frame
    assert 34.0 < body["origin"]["lat_deg"] < 34.27 and 108.9 < body["origin"]["lon_deg"] < 109.25
    assert client.get(response.headers["location"]).json() == body


@pytest.mark.parametrize("change, loc", [
    (lambda b: b.update(model="kalman"), ["model"]),
    (lambda b: b.update(reorder_window_s=-1.0), ["reorder_window_s"]),
    (lambda b: b["process_noise"].update(accel_sigma_mps2=0.0), ["process_noise", "accel_sigma_mps2"]),
    (lambda b: b["process_noise"].update(imm_accel_sigmas_mps2=[0.1]), ["process_noise", "imm_accel_sigmas_mps2"]),
    (lambda b: b.update(stations=[]), ["stations"]),
    (lambda b: b["stations"][1].update(position={"lat_deg": 91.0, "lon_deg": 0.0}),
     ["stations", 1, "position", "lat_deg"]),
    (lambda b: b["stations"][0].update(colour="red"), ["stations", 0, "colour"]),
    (lambda b: b.update(end_after_s=5.0), ["end_after_s"]),
])
def test_create_rejects_bad_values_with_the_field_path(client, change, loc):
    body = create_body()
    change(body)
    response = client.post("/v1/sessions", json=body)
    assert response.status_code == 422, response.text
    assert response.headers["content-type"] == "application/problem+json"
    assert loc in [e["loc"] for e in response.json()["errors"]]


def test_create_refuses_duplicate_station_ids_and_positions_of_the_wrong_frame(client):
    body = create_body()
    body["stations"][2]["id"] = body["stations"][0]["id"]
    assert client.post("/v1/sessions", json=body).status_code == 422
    body = create_body(frame="local")
    response = client.post("/v1/sessions", json=body)
    assert response.status_code == 422 and "LocalPosition" in response.json()["detail"]


def test_reports_are_applied_and_the_state_lists_the_track(client):
    session = create(client)
    response = post(client, session["id"], df_reports(12))
    assert response.status_code == 200, response.text
    body = strict_json(response)
    ReportResult.model_validate(body)
    assert response.headers["etag"] == '"2"'
    assert (body["applied"], body["duplicates"], body["late"], body["updates"], body["last_seq"]) == (12, 0, 0, 12, 12)
    assert body["last_time_s"] == 111.0
    (track,) = body["tracks"]
    assert track["id"] == "default" and track["updates"] == 12 and track["time_s"] == 111.0
    assert track["status"] in ("tentative", "confirmed", "coasting")
    covariance = np.array(track["covariance_enu"])
    assert covariance.shape == (6, 6) and np.allclose(covariance, covariance.T)
    assert np.all(np.linalg.eigvalsh(covariance) > 0)
    error = track["error"]
    assert error["gdop"] is None and error["sqrt_trace_m"] == pytest.approx(math.sqrt(np.trace(covariance[:3, :3])))
    fetched = client.get(f"/v1/sessions/{session['id']}")
    assert fetched.headers["etag"] == '"2"'
    assert fetched.json() == {k: v for k, v in body.items() if k not in ("applied", "duplicates", "late")}


def test_a_retried_post_is_acknowledged_and_changes_nothing(client):
    session = create(client)
    reports = df_reports(10)
    first = post(client, session["id"], reports).json()
    again = post(client, session["id"], reports)
    assert again.status_code == 200
    body = again.json()
    assert (body["applied"], body["duplicates"], body["late"], body["version"]) == (0, 10, 0, first["version"])
    assert filter_view(body) == filter_view(first)
    overlapping = post(client, session["id"], df_reports(15)[5:]).json()
    assert (overlapping["applied"], overlapping["duplicates"], overlapping["updates"]) == (5, 5, 15)


def test_reports_out_of_order_within_the_window_equal_the_time_order_and_older_ones_are_late(client):
    reports = df_reports(20)
    in_order = create(client)
    expected = post(client, in_order["id"], reports).json()
    shuffled = create(client)
    # seq is the sending order: renumber after swapping neighbours (each then arrives up to 1 s late)
    order = list(range(20))
    for i in range(0, 20, 4):
        order[i], order[i + 1] = order[i + 1], order[i]
    sent = [{**reports[j], "seq": k + 1} for k, j in enumerate(order)]
    got = post(client, shuffled["id"], sent[:10]).json()
    got = post(client, shuffled["id"], sent[10:]).json()
    assert got["applied"] == 10 and got["late"] == 0 and got["updates"] == 20
    assert got["tracks"] == expected["tracks"]
    late = {**df_reports(1)[0], "seq": 100, "time_s": reports[-1]["time_s"] - 2.5}
    body = post(client, shuffled["id"], [late]).json()
    assert (body["applied"], body["late"], body["duplicates"], body["updates"]) == (0, 1, 0, 20)
    assert body["tracks"] == got["tracks"]
    text = client.get("/metrics").text
    assert sample(text, "passive_locator_session_reports_late_total") == 1
    assert sample(text, "passive_locator_session_reports_applied_total") == 40


def _one(reports=None, **changes) -> list[dict]:
    report = {**df_reports(1)[0], **changes}
    return [report]


TOA = {"type": "toa", "station_id": "df-1", "toa_s": 0.001, "sigma_s": 2e-8}


@pytest.mark.parametrize("report, code, loc", [
    ({"measurements": [{**bearing(DF_STATIONS["df-1"], START), "station_id": "rx-9"}]}, "unknown_station",
     ["reports", 0, "measurements", 0, "station_id"]),
    ({"measurements": [TOA]}, "toa_without_partner", ["reports", 0, "measurements", 0]),
    ({"measurements": [TOA, {**TOA, "toa_s": 0.0011}]}, "toa_without_partner", ["reports", 0, "measurements", 0]),
    ({"measurements": [{**bearing(DF_STATIONS["df-1"], START), "station_id": "df-1", "sigma_azimuth_deg": 0.0}]},
     "invalid_input", ["reports", 0, "measurements", 0, "sigma_azimuth_deg"]),
    ({"measurements": [{**bearing(DF_STATIONS["df-1"], START), "station_id": "df-1", "sigma_azimuth_deg": None}]},
     "invalid_input", ["reports", 0, "measurements", 0, "sigma_azimuth_deg"]),
    ({"measurements": [{**TOA, "sigma_s": 2.0}, {**TOA, "station_id": "df-2"}]}, "invalid_input",
     ["reports", 0, "measurements", 0, "sigma_s"]),
    ({"time_s": 1e12}, "invalid_input", ["reports", 0, "time_s"]),
    ({"stations": [{"id": "air-1", "position": {"east_m": 1.0, "north_m": 2.0}}],
      "measurements": [{**bearing(DF_STATIONS["df-1"], START), "station_id": "air-1"}]}, "invalid_input",
     ["reports", 0, "stations", 0, "position"]),
    ({"emitter_id": "has space"}, "invalid_input", ["reports", 0, "emitter_id"]),
])
def test_every_bad_report_is_a_422_with_its_field_path_and_nothing_is_applied(client, report, code, loc):
    session = create(client)
    good = df_reports(3)
    bad = {**df_reports(4)[3], **report}
    response = post(client, session["id"], [*good, bad])
    assert response.status_code == 422, response.text
    problem = response.json()
    assert response.headers["content-type"] == "application/problem+json"
    assert problem["code"] == code
    expected = [*loc[:1], 3, *loc[2:]]
    assert expected in [e["loc"] for e in problem["errors"]], problem
    state = client.get(f"/v1/sessions/{session['id']}").json()
    assert state["updates"] == 0 and state["version"] == 1


def test_a_non_finite_time_is_refused(client):
    session = create(client)
    raw = orjson.dumps({"reports": df_reports(1)}).replace(b'"time_s":100.0', b'"time_s":NaN')
    response = client.post(f"/v1/sessions/{session['id']}/reports", content=raw,
                           headers={"content-type": "application/json"})
    assert response.status_code in (400, 422)
    assert response.headers["content-type"] == "application/problem+json"
    if response.status_code == 422:
        assert ["reports", 0, "time_s"] in [e["loc"] for e in response.json()["errors"]]


def test_a_moving_station_needs_its_position_in_every_report(client):
    platform = {"id": "air-1", "position": {"lat_deg": 34.1, "lon_deg": 108.8, "alt_m": 8000.0}, "moving": True}
    session = create(client, stations=[*create_body()["stations"], platform])
    where = {"lat_deg": 34.11, "lon_deg": 108.82, "alt_m": 8000.0}
    measured = {**bearing(where, truth_at(0.0)), "station_id": "air-1"}
    missing = post(client, session["id"], [{"seq": 1, "time_s": 100.0, "measurements": [measured]}])
    assert missing.status_code == 422
    assert missing.json()["code"] == "station_position_missing"
    assert missing.json()["errors"][0]["loc"] == ["reports", 0, "measurements", 0, "station_id"]
    given = post(client, session["id"], [{"seq": 1, "time_s": 100.0, "measurements": [measured],
                                          "stations": [{"id": "air-1", "position": where}]}])
    assert given.status_code == 200, given.text
    (air,) = [s for s in given.json()["stations"] if s["id"] == "air-1"]
    assert air["position"] == where and air["time_s"] == 100.0 and air["moving"] is True
    # a station new to the session must come with its position, and then moves (every report gives it)
    new = {**bearing(DF_STATIONS["df-2"], truth_at(1.0)), "station_id": "df-9"}
    assert post(client, session["id"], [{"seq": 2, "time_s": 101.0, "measurements": [new]}]).json()["code"] == \
        "unknown_station"
    body = post(client, session["id"], [{"seq": 2, "time_s": 101.0, "measurements": [new],
                                         "stations": [{"id": "df-9", "position": DF_STATIONS["df-2"]}]}])
    assert body.status_code == 200
    assert post(client, session["id"], [{"seq": 3, "time_s": 102.0, "measurements": [new]}]).json()["code"] == \
        "station_position_missing"


def test_if_match_is_checked_against_the_current_version(client):
    session = create(client)
    stale = post(client, session["id"], df_reports(2), headers={"If-Match": '"7"'})
    assert stale.status_code == 412 and stale.json()["code"] == "precondition_failed"
    ok = post(client, session["id"], df_reports(2), headers={"If-Match": '"1"'})
    assert ok.status_code == 200 and ok.headers["etag"] == '"2"'
    assert post(client, session["id"], df_reports(3), headers={"If-Match": '"1"'}).status_code == 412


def test_the_kinds_of_session_take_only_their_own_posts(client):
    network = create(client)
    observer = client.post("/v1/sessions", json=observer_body()).json()
    wrong = client.post(f"/v1/sessions/{network['id']}/measurements",
                        json={"measurements": [{"seq": 1, "time_s": 0.0, "azimuth_deg": 1.0, "elevation_deg": 1.0,
                                                "azimuth_rate_deg_s": 0.0, "toa_s": 0.0}]})
    assert wrong.status_code == 422 and wrong.json()["code"] == "wrong_session_kind"
    wrong = post(client, observer["id"], df_reports(1))
    assert wrong.status_code == 422 and wrong.json()["code"] == "wrong_session_kind"
    assert client.get(f"/v1/sessions/{observer['id']}", params={"at_time_s": 5}).status_code == 422
    listed = client.get("/v1/sessions").json()
    SessionList.model_validate(listed)
    assert {s["id"] for s in listed["sessions"]} == {network["id"], observer["id"]}
    assert post(client, "0" * 32, df_reports(1)).status_code == 404


def test_at_time_s_predicts_every_track_at_constant_velocity(client):
    session = create(client)
    body = post(client, session["id"], df_reports(30)).json()
    (track,) = body["tracks"]
    later = client.get(f"/v1/sessions/{session['id']}", params={"at_time_s": track["time_s"] + 10.0}).json()
    NetworkSessionState.model_validate(later)
    (ahead,) = later["tracks"]
    assert later["at_time_s"] == track["time_s"] + 10.0 and ahead["time_s"] == track["time_s"] + 10.0
    moved = np.subtract([ahead["position_local"][k] for k in ("east_m", "north_m", "up_m")],
                        [track["position_local"][k] for k in ("east_m", "north_m", "up_m")])
    assert np.linalg.norm(moved - 10.0 * np.array(track["velocity_enu_mps"])) < 0.01 * np.linalg.norm(moved) + 1.0
    assert np.trace(np.array(ahead["covariance_enu"])[:3, :3]) > np.trace(np.array(track["covariance_enu"])[:3, :3])
    assert client.get(f"/v1/sessions/{session['id']}", params={"at_time_s": "nan"}).status_code == 422


def test_formats_give_one_valid_cot_track_event_per_track_and_geojson(client):
    session = create(client, cot={"uid": "net-7", "stale_s": 60.0})
    reports = df_reports(20) + [{**r, "seq": 100 + i, "time_s": r["time_s"] + 12.0, "emitter_id": "e2"}
                                for i, r in enumerate(df_reports(8, seed=2))]
    post(client, session["id"], reports)
    response = client.get(f"/v1/sessions/{session['id']}", params={"formats": "cot,geojson"})
    assert response.status_code == 200, response.text
    body = response.json()
    NetworkSessionState.model_validate(body)
    assert [t["id"] for t in body["tracks"]] == ["default", "e2"]
    for track, uid in zip(body["tracks"], ["net-7", "net-7-e2"]):
        event = cot_event(track["cot"])
        assert event.get("uid") == uid and event.get("how") == "m-p"
        assert event.find("detail/contact").get("callsign") == track["id"]
        velocity = track["velocity_enu_mps"]
        assert float(event.find("detail/track").get("speed")) == pytest.approx(math.hypot(*velocity[:2]), abs=1e-3)
        assert float(event.find("detail/track").get("course")) == \
            pytest.approx(math.degrees(math.atan2(velocity[0], velocity[1])) % 360.0, abs=0.01)
        covariance = np.array(track["covariance_enu"])
        point = event.find("point")
        assert float(point.get("ce")) == pytest.approx(math.sqrt(0.5 * (covariance[0, 0] + covariance[1, 1])), abs=0.01)
        assert float(point.get("le")) == pytest.approx(math.sqrt(covariance[2, 2]), abs=0.01)
        assert float(point.get("lat")) == pytest.approx(track["position"]["lat_deg"], abs=1e-7)
    collection = geojson.loads(orjson.dumps(body["geojson"]).decode())
    assert collection.is_valid, collection.errors()
    points = [f for f in collection["features"] if f["properties"]["kind"] == "track"]
    ellipses = [f for f in collection["features"] if f["properties"]["kind"] == "error_ellipse"]
    assert [p["properties"]["id"] for p in points] == ["default", "e2"] and len(ellipses) == 2
    assert all("course_deg" in p["properties"] and "speed_mps" in p["properties"] for p in points)
    courses = [f for f in collection["features"] if f["properties"]["kind"] == "course"]
    assert [c["properties"]["id"] for c in courses] == ["default", "e2"]
    for line, track in zip(courses, body["tracks"]):
        (lon0, lat0), (lon1, lat1) = line["geometry"]["coordinates"]
        assert (lon0, lat0) == pytest.approx((track["position"]["lon_deg"], track["position"]["lat_deg"]))
        step = geodesy.geodetic_to_enu(math.radians(lat1), math.radians(lon1), track["position"]["alt_m"],
                                       math.radians(lat0), math.radians(lon0), track["position"]["alt_m"])
        seconds = line["properties"]["seconds"]
        assert step[:2] == pytest.approx(np.array(track["velocity_enu_mps"][:2]) * seconds, rel=1e-3, abs=0.5)


def test_a_local_frame_has_local_positions_and_no_cot(client):
    stations = [{"id": "a", "position": {"east_m": 0.0, "north_m": 0.0}},
                {"id": "b", "position": {"east_m": 30e3, "north_m": 0.0}}]
    session = create(client, frame="local", stations=stations)
    target = np.array([12e3, 20e3, 0.0])
    reports = []
    for k in range(10):
        sid, where = ("a", np.zeros(3)) if k % 2 == 0 else ("b", np.array([30e3, 0.0, 0.0]))
        d = target - where
        reports.append({"seq": k + 1, "time_s": float(k), "measurements": [
            {"type": "bearing", "station_id": sid, "azimuth_deg": math.degrees(math.atan2(d[0], d[1])),
             "sigma_azimuth_deg": 0.5}]})
    body = post(client, session["id"], reports).json()
    assert body["origin"] is None
    (track,) = body["tracks"]
    assert track["position"] is None and set(track["position_local"]) == {"east_m", "north_m", "up_m"}
    rendered = client.get(f"/v1/sessions/{session['id']}", params={"formats": "cot,geojson"}).json()
    assert rendered["tracks"][0]["cot"] is None and rendered["geojson"]["features"] == []


def test_a_store_reload_continues_exactly(store_url, clock):
    reports = df_reports(30)
    with TestClient(create_app(Settings(store=store_url))) as first:
        first.app.state.store.clock = clock
        session = first.post("/v1/sessions", json=create_body()).json()
        first.post(f"/v1/sessions/{session['id']}/reports", json={"reports": reports[:15]})
    with TestClient(create_app(Settings(store=store_url))) as second:  # a new process's view of the same store
        second.app.state.store.clock = clock
        resumed = second.post(f"/v1/sessions/{session['id']}/reports", json={"reports": reports[15:]}).json()
        straight = second.post("/v1/sessions", json=create_body()).json()
        once = second.post(f"/v1/sessions/{straight['id']}/reports", json={"reports": reports}).json()
    assert resumed["tracks"] == once["tracks"] and resumed["updates"] == once["updates"] == 30


def test_an_imm_session_reports_its_mode_probabilities(client):
    session = create(client, process_noise={"accel_sigma_mps2": 0.5, "imm_accel_sigmas_mps2": [0.1, 3.0]})
    body = post(client, session["id"], df_reports(40)).json()
    (track,) = body["tracks"]
    # once the start's mixture has settled to one Gaussian (40 reports here), the IMM runs
    assert len(track["mode_probabilities"]) == 2 and sum(track["mode_probabilities"]) == pytest.approx(1.0)
    plain = post(client, create(client)["id"], df_reports(40)).json()
    assert plain["tracks"][0]["mode_probabilities"] is None
    assert track["position_local"] != plain["tracks"][0]["position_local"]  # the IMM filtered differently
