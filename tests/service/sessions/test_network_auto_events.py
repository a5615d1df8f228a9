"""An auto session's server-sent events (live uvicorn) and TAK feed: one CoT track per confirmed track, and a track
that ends is said so in both."""

from __future__ import annotations

import httpx
import numpy as np
import orjson
import pytest
from fastapi.testclient import TestClient

from core.simulation.multi_emitter import multi_emitter_scene, simulate_multi
from service.app import create_app
from service.schemas.sessions import NetworkSessionState
from service.settings import Settings
from tests.service.test_renderings import cot_event

from .helpers import Server
from .multi_emitter_http import api_report, create_body, short_scene
from .test_events_and_tak import EventReader, Listener

SCENE = short_scene(multi_emitter_scene(0))
#: Up to here e4 (silent after 10 s) has a confirmed track; in the rest its track coasts, then ends.
SPLIT_S = 1009.0


def _posts() -> tuple[list[dict], list[dict]]:
    run = simulate_multi(SCENE, np.random.default_rng(21))
    reports = [api_report(o, k + 1) for k, o in enumerate(run.observations)]
    return [r for r in reports if r["time_s"] <= SPLIT_S], [r for r in reports if r["time_s"] > SPLIT_S]


def test_tak_feed_sends_one_track_per_confirmed_track_and_a_delete_when_one_ends(monkeypatch, tmp_path):
    listener = Listener()
    monkeypatch.setenv("PASSIVE_LOCATOR_TAK_URL", f"tcp://127.0.0.1:{listener.port}")
    first, later = _posts()
    try:
        with TestClient(create_app(Settings(store=f"sqlite:///{tmp_path}/s.db"))) as client:
            session = client.post("/v1/sessions", json=create_body(SCENE, cot={"uid": "net"})).json()
            body = client.post(f"/v1/sessions/{session['id']}/reports", json={"reports": first}).json()
            shown = [t["id"] for t in body["tracks"] if t["status"] != "tentative"]
            assert len(shown) == 3
            events = [cot_event(text) for text in listener.events(len(shown))]
            assert sorted(e.get("uid") for e in events) == sorted(f"net-{i}" for i in shown)
            body = client.post(f"/v1/sessions/{session['id']}/reports", json={"reports": later}).json()
            (ended,) = body["ended_tracks"]
            assert ended["id"] in shown and ended["id"] not in [t["id"] for t in body["tracks"]]
            remaining = [t["id"] for t in body["tracks"] if t["status"] != "tentative"]
            events = [cot_event(text) for text in listener.events(len(shown) + len(remaining) + 1)][len(shown):]
            deletes = [e for e in events if e.get("type") == "t-x-d-d"]
            assert [d.find("detail/link").get("uid") for d in deletes] == [f"net-{ended['id']}"]
            assert sorted(e.get("uid") for e in events if e.get("type") != "t-x-d-d") == \
                sorted(f"net-{i}" for i in remaining)
    finally:
        listener.close()


@pytest.fixture(scope="module")
def server(tmp_path_factory):
    root = tmp_path_factory.mktemp("auto-sse")
    with Server(f"sqlite:///{root}/s.db", root / "server.log") as running:
        yield running


def test_sse_streams_states_and_track_ended(server):
    first, later = _posts()
    session = httpx.post(f"{server.url}/v1/sessions", json=create_body(SCENE), timeout=30).json()
    base = f"{server.url}/v1/sessions/{session['id']}"
    reader = EventReader(f"{base}/events?formats=cot")
    try:
        events = [reader.next(10.0)]
        assert httpx.post(f"{base}/reports", json={"reports": first}, timeout=60).status_code == 200
        events.append(reader.next(10.0))
        assert httpx.post(f"{base}/reports", json={"reports": later}, timeout=60).status_code == 200
        events += [reader.next(10.0), reader.next(10.0)]
    finally:
        reader.close()
    assert [e["event"] for e in events] == ["state", "state", "track_ended", "state"]
    states = [NetworkSessionState.model_validate(orjson.loads(events[k]["data"])) for k in (1, 3)]
    ended = orjson.loads(events[2]["data"])
    assert ended["id"] == session["id"] and ended["version"] == states[1].version
    assert ended["track_id"] in [t.id for t in states[0].tracks if t.status == "confirmed"]
    assert ended["track_id"] not in [t.id for t in states[1].tracks]
    assert [(e.id, e.time_s) for e in states[1].ended_tracks] == [(ended["track_id"], ended["time_s"])]
    assert all((t.cot is None) == (t.status == "tentative") for t in states[1].tracks)
