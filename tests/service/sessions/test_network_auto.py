"""Network sessions with ``"association": "auto"`` through the real app, on each store: unlabelled bearings of a
short multi-emitter scene in, tracks with service-made ids out, the same as core's association on the same
bearings; late reports within the window land where they belong; retries, If-Match, bad reports, store faults."""

from __future__ import annotations

import math
import sqlite3
from dataclasses import replace

import geojson
import numpy as np
import orjson
import pytest
import redis
from fastapi.testclient import TestClient

from core.simulation.multi_emitter import multi_emitter_scene, simulate_multi
from core.simulation.network import START_TIME_S
from core.tracking.association import AssociationConfig
from service.app import create_app
from service.schemas.sessions import NetworkSessionCreate, NetworkSessionState, ReportResult
from service.sessions import association as association_sessions
from service.settings import Settings
from tests.service.test_renderings import cot_event

from .multi_emitter_http import api_report, create_body, run_in_core, run_over_http, short_scene

SCENE = short_scene(multi_emitter_scene(0))
SEED = 21


@pytest.fixture(scope="module")
def run():
    return simulate_multi(SCENE, np.random.default_rng(SEED))


@pytest.fixture
def client(store_url, clock):
    with TestClient(create_app(Settings(store=store_url))) as c:
        c.app.state.store.clock = clock
        yield c


def _create(client, **changes) -> dict:
    response = client.post("/v1/sessions", json=create_body(SCENE, **changes))
    assert response.status_code == 201, response.text
    return response.json()


def _post(client, session_id: str, reports: list[dict], **kwargs):
    return client.post(f"/v1/sessions/{session_id}/reports", json={"reports": reports}, **kwargs)


def _reports(run) -> list[dict]:
    return [api_report(o, k + 1) for k, o in enumerate(run.observations)]


def _view(body: dict) -> dict:
    """What the reports determine (not versions or clocks)."""
    return {**{k: body[k] for k in ("last_time_s", "updates", "tracks")},
            "ended_tracks": [(e["id"], e["time_s"]) for e in body["ended_tracks"]]}


def test_the_api_carries_every_association_setting_of_the_scene():
    from service.sessions.network import association_config

    got = association_config(NetworkSessionCreate.model_validate(create_body(SCENE)))
    # the track filter's own coasting and end do not act under the association (it ends a track first): the
    # service sets them from the session's
    wanted = SCENE.config
    assert replace(got, network=replace(got.network, coast_after_s=wanted.network.coast_after_s,
                                        end_after_s=wanted.network.end_after_s)) == wanted
    assert got.network.end_after_s > got.end_after_s


def test_create_answers_201_with_the_settings_in_use(client):
    response = client.post("/v1/sessions", json={k: v for k, v in create_body(SCENE).items()
                                                  if k != "association_config"})
    assert response.status_code == 201, response.text
    body = response.json()
    NetworkSessionState.model_validate(body)
    assert body["association"] == "auto" and body["tracks"] == [] and body["ended_tracks"] == []
    defaults = AssociationConfig()
    assert body["association_config"] == {name: getattr(defaults, name) for name in body["association_config"]}
    labelled = client.post("/v1/sessions", json={k: v for k, v in create_body(SCENE).items()
                                                 if k not in ("association", "association_config")}).json()
    assert labelled["association_config"] is None


@pytest.mark.parametrize("change, loc", [
    (lambda b: b.update(association="labelled"), ["association_config"]),
    (lambda b: b["association_config"].update(method="nn"), ["association_config", "method"]),
    (lambda b: b["association_config"].update(detection_probability=1.0),
     ["association_config", "detection_probability"]),
    (lambda b: b["association_config"].update(false_density_per_rad2=0.0),
     ["association_config", "false_density_per_rad2"]),
    (lambda b: b["association_config"].update(gate_probability=1.0), ["association_config", "gate_probability"]),
    (lambda b: b["association_config"].update(confirm_hits=9), ["association_config", "confirm_hits"]),
    (lambda b: b["association_config"].update(frequency_tolerance_hz=-1.0),
     ["association_config", "frequency_tolerance_hz"]),
    (lambda b: b["association_config"].update(range_max_m=100.0), ["association_config", "range_max_m"]),
    (lambda b: b["association_config"].update(colour="red"), ["association_config", "colour"]),
    (lambda b: b.update(end_after_s=2.0), ["end_after_s"]),
])
def test_create_refuses_bad_settings_with_the_field_path(client, change, loc):
    body = create_body(SCENE)
    change(body)
    response = client.post("/v1/sessions", json=body)
    assert response.status_code == 422, response.text
    assert response.headers["content-type"] == "application/problem+json"
    assert loc in [e["loc"] for e in response.json()["errors"]], response.json()


def test_tracks_over_http_are_cores_on_the_same_bearings(client, run):
    got = run_over_http(client, SCENE, run.observations, step_s=2.0)
    core = run_in_core(SCENE, run.observations, got["epochs"])
    assert got["applied"] == len(run.observations) and got["late"] == got["duplicates"] == 0
    assert got["ids"] == core["ids"]
    # the same association on the same numbers: equal up to the API's degrees and the frame placement's rounding
    for mine, theirs in zip(got["positions"], core["positions"]):
        assert np.allclose(mine, theirs, rtol=0.0, atol=1e-3)
    last = got["last"]
    NetworkSessionState.model_validate(last)
    # e1, e2 and e4 transmitted: three confirmed tracks, with the service's ids; e4's track ended
    assert len(core["ids"][2]) == 3 and all(i.startswith("t") for i in core["ids"][2])
    assert len(last["ended_tracks"]) == 1 and last["ended_tracks"][0]["id"] in core["ids"][2]
    assert last["ended_tracks"][0]["id"] not in [t["id"] for t in last["tracks"]]


def test_a_track_keeps_its_id_while_it_lives(client, run):
    """Each confirmed track stays with one emitter (the nearest, within GOSPA's cutoff, at every epoch), and each
    emitter has one track id over the run: no renumbering, no identity switch."""
    got = run_over_http(client, SCENE, run.observations, step_s=1.0)
    emitters_of: dict[str, set] = {}
    ids_of: dict[str, set] = {}
    names = [e.id for e in SCENE.emitters]
    for t, ids, positions in zip(got["epochs"], got["ids"], got["positions"]):
        # every emitter's path, also after it fell silent (its track coasts on, then ends)
        truths = np.array([e.state_at(t - START_TIME_S) for e in SCENE.emitters])
        for track_id, position in zip(ids, positions):
            distances = np.linalg.norm(truths[:, :2] - position, axis=1)
            k = int(np.argmin(distances))
            assert distances[k] < SCENE.gospa_cutoff_m, (t, track_id)
            emitters_of.setdefault(track_id, set()).add(names[k])
            ids_of.setdefault(names[k], set()).add(track_id)
    assert sorted(ids_of) == ["e1", "e2", "e4"]
    assert all(len(v) == 1 for v in emitters_of.values()), emitters_of
    assert all(len(v) == 1 for v in ids_of.values()), ids_of


def test_reports_out_of_order_within_the_window_give_the_same_tracks_and_older_ones_are_late(client, run):
    reports = _reports(run)
    expected = _post(client, _create(client)["id"], reports).json()
    # every third scan held back by 1.5 s (under reorder_window_s 2): renumber seq in the sending order
    scans = sorted({(r["time_s"], r["measurements"][0]["station_id"]) for r in reports})
    held = set(scans[::3])
    arrival = [r["time_s"] + (1.5 if (r["time_s"], r["measurements"][0]["station_id"]) in held else 0.0)
               for r in reports]
    order = sorted(range(len(reports)), key=lambda k: (arrival[k], k))
    assert order != sorted(order)
    sent = [{**reports[k], "seq": n + 1} for n, k in enumerate(order)]
    session = _create(client)
    half = len(sent) // 2
    first = _post(client, session["id"], sent[:half]).json()
    got = _post(client, session["id"], sent[half:]).json()
    assert first["applied"] + got["applied"] == len(reports) and first["late"] == got["late"] == 0
    assert _view(got) == _view(expected)
    too_old = {**reports[-1], "seq": len(sent) + 1, "time_s": reports[-1]["time_s"] - 2.5}
    late = _post(client, session["id"], [too_old]).json()
    assert (late["applied"], late["late"], late["duplicates"]) == (0, 1, 0)
    assert late["tracks"] == got["tracks"]


def test_a_long_window_keeps_a_bounded_pending_set_and_the_same_tracks(client, run, monkeypatch):
    """Every post re-runs the pending reports, so their number is bounded whatever the window: the oldest settle
    early, the tracks are those of the same reports in time order, and a report older than the settled ones is
    late although the window would take it."""
    reports = _reports(run)
    span_s = reports[-1]["time_s"] - reports[0]["time_s"]
    expected = _post(client, _create(client, end_after_s=span_s + 10.0)["id"], reports).json()
    monkeypatch.setattr(association_sessions, "MAX_PENDING_REPORTS", 20)
    session = _create(client, reorder_window_s=span_s + 5.0, end_after_s=span_s + 10.0)
    half = len(reports) // 2
    _post(client, session["id"], reports[:half])
    got = _post(client, session["id"], reports[half:]).json()
    assert _view(got) == _view(expected)
    first = {**reports[0], "seq": len(reports) + 1}
    late = _post(client, session["id"], [first]).json()
    assert (late["applied"], late["late"]) == (0, 1)
    recent = {**reports[-1], "seq": len(reports) + 2}
    assert _post(client, session["id"], [recent]).json()["applied"] == 1


def test_a_retried_post_is_acknowledged_and_changes_nothing(client, run):
    reports = _reports(run)
    session = _create(client)
    first = _post(client, session["id"], reports[:200]).json()
    again = _post(client, session["id"], reports[:200])
    assert again.status_code == 200
    body = again.json()
    ReportResult.model_validate(body)
    assert (body["applied"], body["duplicates"], body["late"], body["version"]) == (0, 200, 0, first["version"])
    assert _view(body) == _view(first)
    overlapping = _post(client, session["id"], reports[150:300]).json()
    assert (overlapping["applied"], overlapping["duplicates"]) == (100, 50)
    straight = _post(client, _create(client)["id"], reports[:300]).json()
    assert _view(overlapping) == _view(straight)


def test_if_match_is_checked_against_the_current_version(client, run):
    reports = _reports(run)
    session = _create(client)
    stale = _post(client, session["id"], reports[:5], headers={"If-Match": '"7"'})
    assert stale.status_code == 412 and stale.json()["code"] == "precondition_failed"
    ok = _post(client, session["id"], reports[:5], headers={"If-Match": '"1"'})
    assert ok.status_code == 200 and ok.headers["etag"] == '"2"'


BEARING = {"type": "bearing", "station_id": "df-west", "azimuth_deg": 40.0, "elevation_deg": 0.5,
           "sigma_azimuth_deg": 1.0, "sigma_elevation_deg": 1.0}


@pytest.mark.parametrize("report, code, loc", [
    ({"emitter_id": "e1"}, "invalid_input", ["reports", 0, "emitter_id"]),
    ({"measurements": [{"type": "range", "station_id": "df-west", "range_m": 5e3, "sigma_m": 50.0}]},
     "invalid_input", ["reports", 0, "measurements", 0]),
    ({"measurements": [BEARING, {**BEARING, "azimuth_deg": 41.0}]}, "invalid_input", ["reports", 0, "measurements", 0]),
    ({"measurements": [{**BEARING, "station_id": "df-9"}]}, "unknown_station",
     ["reports", 0, "measurements", 0, "station_id"]),
    ({"measurements": [{**BEARING, "sigma_azimuth_deg": 0.0}]}, "invalid_input",
     ["reports", 0, "measurements", 0, "sigma_azimuth_deg"]),
    ({"frequency_hz": -5.0}, "invalid_input", ["reports", 0, "frequency_hz"]),
])
def test_every_bad_report_is_a_422_with_its_field_path_and_nothing_is_applied(client, run, report, code, loc):
    reports = _reports(run)
    session = _create(client)
    bad = {**reports[3], **report}
    response = _post(client, session["id"], [*reports[:3], bad])
    assert response.status_code == 422, response.text
    problem = response.json()
    assert response.headers["content-type"] == "application/problem+json"
    assert problem["code"] == code
    assert [*loc[:1], 3, *loc[2:]] in [e["loc"] for e in problem["errors"]], problem
    state = client.get(f"/v1/sessions/{session['id']}").json()
    assert state["updates"] == 0 and state["version"] == 1


def test_a_store_reload_continues_exactly(store_url, clock, run):
    reports = _reports(run)
    with TestClient(create_app(Settings(store=store_url))) as first:
        first.app.state.store.clock = clock
        session = _create(first)
        _post(first, session["id"], reports[:250])
    with TestClient(create_app(Settings(store=store_url))) as second:  # a new process's view of the same store
        second.app.state.store.clock = clock
        resumed = _post(second, session["id"], reports[250:]).json()
        once = _post(second, _create(second)["id"], reports).json()
    assert _view(resumed) == _view(once) and resumed["updates"] == len(reports)


def test_a_store_fault_is_a_503_and_applies_nothing(client, store_url, run, monkeypatch):
    reports = _reports(run)
    session = _create(client)
    backend = client.app.state.store.backend()
    error = sqlite3.OperationalError("disk I/O error") if store_url.startswith("sqlite") else \
        redis.ConnectionError("connection refused")

    def broken(*args, **kwargs):
        raise error

    monkeypatch.setattr(backend, "_swap", broken)
    response = _post(client, session["id"], reports[:100])
    assert response.status_code == 503, response.text
    assert response.headers["content-type"] == "application/problem+json"
    monkeypatch.undo()
    state = client.get(f"/v1/sessions/{session['id']}").json()
    assert (state["version"], state["updates"], state["tracks"]) == (1, 0, [])
    assert _post(client, session["id"], reports[:100]).json()["applied"] == 100


def test_maps_show_confirmed_tracks_only_one_valid_cot_uid_each(client, run):
    reports = _reports(run)
    session = _create(client, cot={"uid": "net", "stale_s": 30.0})
    # the first scans: tracks start tentative (M of N not reached yet)
    early = [r for r in reports if r["time_s"] <= reports[0]["time_s"] + 1.5]
    _post(client, session["id"], early)
    body = client.get(f"/v1/sessions/{session['id']}", params={"formats": "cot,geojson"}).json()
    assert body["tracks"] and {t["status"] for t in body["tracks"]} == {"tentative"}
    assert all(t["cot"] is None for t in body["tracks"]) and body["geojson"]["features"] == []
    _post(client, session["id"], [r for r in reports if r not in early])
    response = client.get(f"/v1/sessions/{session['id']}", params={"formats": "cot,geojson"})
    body = response.json()
    NetworkSessionState.model_validate(body)
    shown = [t for t in body["tracks"] if t["status"] != "tentative"]
    assert len(shown) >= 2
    uids = []
    for track in body["tracks"]:
        if track["status"] == "tentative":
            assert track["cot"] is None
            continue
        event = cot_event(track["cot"])
        assert event.get("how") == "m-p" and event.find("detail/contact").get("callsign") == track["id"]
        assert float(event.find("point").get("lat")) == pytest.approx(track["position"]["lat_deg"], abs=1e-7)
        uids.append(event.get("uid"))
    assert sorted(uids) == sorted(f"net-{t['id']}" for t in shown) and len(set(uids)) == len(uids)
    collection = geojson.loads(orjson.dumps(body["geojson"]).decode())
    assert collection.is_valid, collection.errors()
    points = [f for f in collection["features"] if f["properties"]["kind"] == "track"]
    assert sorted(p["properties"]["uid"] for p in points) == sorted(uids)


def test_frequency_hz_is_the_frequency_gate_and_without_it_there_is_none(client, run):
    """A station whose bearings all come 1 MHz off (more than frequency_tolerance_hz) joins no track of the
    others: the service gives core's answer on those frequencies, and it differs from the true frequencies' (the
    gate acted); without frequency_hz there is no gate, as in core with no frequency."""
    end = [run.observations[-1].time_s]

    def shifted(o):
        return replace(o, frequency_hz=o.frequency_hz + 1e6) if o.station_id == "df-west" else o

    cases = {"true": run.observations, "shifted": [shifted(o) for o in run.observations],
             "none": [replace(o, frequency_hz=math.nan) for o in run.observations]}
    states = {}
    for name, observations in cases.items():
        reports = [api_report(o, k + 1) for k, o in enumerate(observations)]
        if name == "none":
            reports = [{k: v for k, v in r.items() if k != "frequency_hz"} for r in reports]
        body = _post(client, _create(client)["id"], reports).json()
        core = run_in_core(SCENE, observations, end)
        ids, positions = _confirmed_at(client, body, end[0])
        assert ids == core["ids"][0], name
        assert np.allclose(positions, core["positions"][0], rtol=0.0, atol=1e-3), name
        states[name] = body
    updates = {name: sum(t["updates"] for t in body["tracks"]) for name, body in states.items()}
    assert updates["shifted"] < 0.9 * updates["true"], updates


def _confirmed_at(client, body: dict, time_s: float):
    from .multi_emitter_http import confirmed_positions

    state = client.get(f"/v1/sessions/{body['id']}", params={"at_time_s": time_s}).json()
    return confirmed_positions(state["tracks"])


def test_an_auto_post_is_decided_on_a_worker_thread_not_within_the_store_call(client, run, monkeypatch):
    """An auto post re-runs the reorder window: its cost follows the session, not the post's size, so even a
    one-report post is prepared off the store's threads (whose calls have a deadline of their own)."""
    import threading

    from service.sessions.network import ReportsChange

    threads = []
    original = ReportsChange._change

    def spy(self, record):
        threads.append(threading.current_thread().name)
        return original(self, record)

    monkeypatch.setattr(ReportsChange, "_change", spy)
    session = _create(client)
    response = _post(client, session["id"], _reports(run)[:1])
    assert response.status_code == 200, response.text
    assert response.json()["applied"] == 1
    assert threads and not any(name.startswith("store") for name in threads), threads
