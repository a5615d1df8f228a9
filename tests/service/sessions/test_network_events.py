"""A network session's server-sent events (live uvicorn) and TAK feed: one CoT track per emitter, and a track
that ends is said so in both."""

from __future__ import annotations

import json

import httpx
import orjson
import pytest
from fastapi.testclient import TestClient

from service.app import create_app
from service.schemas.sessions import NetworkSessionState
from service.settings import Settings
from tests.service.test_metrics import sample
from tests.service.test_renderings import cot_event

from .helpers import REPO, Server
from .network_helpers import create_body, df_reports
from .test_events_and_tak import EventReader, Listener

#: Tracks coast after 1 s without a report and end after 3 s.
SHORT_LIVED = {"coast_after_s": 1.0, "end_after_s": 3.0, "reorder_window_s": 0.5}


def _two_emitters_then_one() -> tuple[list[dict], list[dict]]:
    """Reports of the default emitter and e2 over 100..109 s; then the default alone over 110..119 s (e2 ends)."""
    first = df_reports(10) + [{**r, "seq": 100 + i, "emitter_id": "e2", "time_s": r["time_s"] + 0.5}
                              for i, r in enumerate(df_reports(10, seed=2))]
    first.sort(key=lambda r: r["seq"])
    later = [{**r, "seq": 200 + i} for i, r in enumerate(df_reports(20)[10:])]
    return first, later


def test_tak_feed_sends_one_track_per_emitter_and_a_delete_when_a_track_ends(monkeypatch, tmp_path):
    listener = Listener()
    monkeypatch.setenv("PASSIVE_LOCATOR_TAK_URL", f"tcp://127.0.0.1:{listener.port}")
    first, later = _two_emitters_then_one()
    try:
        with TestClient(create_app(Settings(store=f"sqlite:///{tmp_path}/s.db"))) as client:
            session = client.post("/v1/sessions", json=create_body(cot={"uid": "net"}, **SHORT_LIVED)).json()
            response = client.post(f"/v1/sessions/{session['id']}/reports", json={"reports": first})
            assert [t["id"] for t in response.json()["tracks"]] == ["default", "e2"]
            events = [cot_event(text) for text in listener.events(2)]
            assert sorted(e.get("uid") for e in events) == ["net", "net-e2"]
            assert all(e.get("type") == "a-u-G" and e.find("detail/track") is not None for e in events)
            body = client.post(f"/v1/sessions/{session['id']}/reports", json={"reports": later}).json()
            assert [t["id"] for t in body["tracks"]] == ["default"]
            assert [(e["id"], e["version"]) for e in body["ended_tracks"]] == [("e2", 3)]
            events = [cot_event(text) for text in listener.events(4)][2:]
            assert [e.get("uid") for e in events[:1]] == ["net"]
            deleted = events[1]
            assert deleted.get("type") == "t-x-d-d" and deleted.find("detail/link").get("uid") == "net-e2"
            text = client.get("/metrics").text
            assert sample(text, "passive_locator_session_report_posts_total") == 2
    finally:
        listener.close()


@pytest.fixture(scope="module")
def server(tmp_path_factory):
    root = tmp_path_factory.mktemp("network-sse")
    with Server(f"sqlite:///{root}/s.db", root / "server.log") as running:
        yield running


def test_sse_streams_states_and_track_ended_as_the_spec_declares(server):
    spec = json.loads((REPO / "openapi" / "openapi.json").read_text())
    item = spec["paths"]["/v1/sessions/{session_id}/events"]["get"]["responses"]["200"]["content"][
        "text/event-stream"]["itemSchema"]
    schema = spec["components"]["schemas"][item["$ref"].rsplit("/", 1)[-1]]
    first, later = _two_emitters_then_one()
    session = httpx.post(f"{server.url}/v1/sessions", json=create_body(**SHORT_LIVED), timeout=30).json()
    base = f"{server.url}/v1/sessions/{session['id']}"
    reader = EventReader(f"{base}/events?formats=cot,geojson")
    try:
        events = [reader.next(10.0)]
        assert httpx.post(f"{base}/reports", json={"reports": first}, timeout=30).status_code == 200
        events.append(reader.next(5.0))
        assert httpx.post(f"{base}/reports", json={"reports": later}, timeout=30).status_code == 200
        events += [reader.next(5.0), reader.next(5.0)]
        httpx.delete(base, timeout=30)
        events.append(reader.next(5.0))
    finally:
        reader.close()
    assert [e["event"] for e in events] == ["state", "state", "track_ended", "state", "deleted"]
    for event in events:
        assert set(schema["required"]) <= event.keys() <= schema["properties"].keys(), event
        assert event["event"] in schema["properties"]["event"]["enum"]
        data = orjson.loads(event["data"])
        if event["event"] == "state":
            state = NetworkSessionState.model_validate(data)
            assert event["id"] == str(state.version)
    second = orjson.loads(events[1]["data"])
    assert [t["id"] for t in second["tracks"]] == ["default", "e2"]
    assert all(cot_event(t["cot"]) is not None for t in second["tracks"]) and second["geojson"]["features"]
    assert orjson.loads(events[2]["data"]) == {"id": session["id"], "track_id": "e2",
                                               "time_s": orjson.loads(events[3]["data"])["ended_tracks"][0]["time_s"],
                                               "version": 3}
    assert [t["id"] for t in orjson.loads(events[3]["data"])["tracks"]] == ["default"]
