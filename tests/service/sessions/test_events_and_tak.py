"""Server-sent session events (live uvicorn, SQLite and Redis across two replicas) and the TAK feed."""

from __future__ import annotations

import queue
import socket
import threading
import time

import httpx
import orjson
import pytest
from fastapi.testclient import TestClient

from service.app import create_app
from service.sessions.events import HEARTBEAT_S
from service.settings import Settings
from tests.service.conftest import STATIONS_300KM, TARGET, bearing_request
from tests.service.sessions.helpers import Server, api_epochs, create_body, paper_track
from tests.service.test_metrics import sample
from tests.service.test_renderings import cot_event

EPOCHS = api_epochs(paper_track(seed=4, epochs=30))


class EventReader:
    """Reads server-sent events from a streaming response on a thread, into a queue."""

    def __init__(self, url: str, headers: dict | None = None):
        self.events: queue.Queue = queue.Queue()
        self.opened = threading.Event()
        self.status: int | None = None
        self._client = httpx.Client(timeout=httpx.Timeout(10.0, read=60.0))
        self._thread = threading.Thread(target=self._run, args=(url, headers or {}), daemon=True)
        self._thread.start()
        assert self.opened.wait(10.0), "the stream did not open"

    def _run(self, url, headers):
        try:
            with self._client.stream("GET", url, headers=headers) as response:
                self.status = response.status_code
                self.content_type = response.headers.get("content-type", "")
                self.opened.set()
                event: dict = {}
                for line in response.iter_lines():
                    if not line:
                        if event:
                            self.events.put(event)
                        event = {}
                    elif not line.startswith(":"):
                        field, _, value = line.partition(": ")
                        event[field] = value
        except httpx.HTTPError:
            pass
        finally:
            self.opened.set()

    def next(self, timeout_s: float) -> dict:
        return self.events.get(timeout=timeout_s)

    def close(self):
        self._client.close()


@pytest.fixture(scope="module")
def server(tmp_path_factory):
    root = tmp_path_factory.mktemp("sse")
    with Server(f"sqlite:///{root}/s.db", root / "server.log") as running:
        yield running


def _create(base: str, **extra) -> dict:
    response = httpx.post(f"{base}/v1/sessions", json={**create_body(frame="wgs84"), **extra}, timeout=30)
    assert response.status_code == 201, response.text
    return response.json()


@pytest.fixture(scope="module")
def pushed_server(tmp_path_factory):
    """A server whose streams poll the store only hourly: an event that arrives came by the push."""
    root = tmp_path_factory.mktemp("sse-push")
    with Server(f"sqlite:///{root}/s.db", root / "server.log", {"PASSIVE_LOCATOR_EVENTS_POLL_S": "3600"}) as running:
        yield running


def test_sse_pushes_each_update_and_the_deletion(pushed_server):
    server = pushed_server
    session = _create(server.url)
    reader = EventReader(f"{server.url}/v1/sessions/{session['id']}/events?formats=cot")
    try:
        assert reader.status == 200 and reader.content_type.startswith("text/event-stream")
        first = reader.next(10.0)
        assert first["event"] == "state" and first["id"] == "1"
        for version, part in ((2, EPOCHS[:20]), (3, EPOCHS[20:])):
            response = httpx.post(f"{server.url}/v1/sessions/{session['id']}/measurements",
                                  json={"measurements": part}, timeout=30)
            assert response.status_code == 200, response.text
            event = reader.next(60.0)  # a hang guard only: the next poll is an hour away
            assert event["id"] == str(version)
            state = orjson.loads(event["data"])
            assert state["version"] == version
            assert state["last_seq"] == part[-1]["seq"]
        assert cot_event(state["cot"]).get("uid") == f"passive-locator-session-{session['id']}"
        httpx.delete(f"{server.url}/v1/sessions/{session['id']}", timeout=30)
        assert reader.next(60.0)["event"] == "deleted"
    finally:
        reader.close()


def test_last_event_id_resumes_after_that_version(server):
    session = _create(server.url)
    reader = EventReader(f"{server.url}/v1/sessions/{session['id']}/events", headers={"Last-Event-ID": "1"})
    try:
        with pytest.raises(queue.Empty):
            reader.next(0.5)  # version 1 is what the client already has
        httpx.post(f"{server.url}/v1/sessions/{session['id']}/measurements", json={"measurements": EPOCHS[:5]},
                   timeout=30)
        assert reader.next(5.0)["id"] == "2"
    finally:
        reader.close()


def test_sse_of_an_unknown_session_is_404(server):
    response = httpx.get(f"{server.url}/v1/sessions/{'0' * 32}/events", timeout=10)
    assert response.status_code == 404
    assert response.headers["content-type"].startswith("application/problem+json")


@pytest.mark.redis
@pytest.mark.slow  # two server processes: 10-35 s on a loaded 2-core machine
def test_sse_across_replicas_sharing_redis(redis_url, tmp_path):
    with Server(redis_url, tmp_path / "a.log") as a, Server(redis_url, tmp_path / "b.log") as b:
        session = _create(a.url)
        reader = EventReader(f"{a.url}/v1/sessions/{session['id']}/events")
        try:
            assert reader.next(10.0)["id"] == "1"
            first_seen = time.monotonic()
            response = httpx.post(f"{b.url}/v1/sessions/{session['id']}/measurements",
                                  json={"measurements": EPOCHS[:10]}, timeout=30)
            assert response.status_code == 200, response.text
            event = reader.next(2 * HEARTBEAT_S)
            # With Redis a stream has no poll: without the other replica's pub/sub notice it would learn of the
            # update only when its heartbeat wait, begun as it sent its last event, ends and it reads the store
            # again. Arriving within half of that after the last event (the post's own time included) is the push.
            assert time.monotonic() - first_seen < HEARTBEAT_S / 2
            assert event["id"] == "2" and orjson.loads(event["data"])["updates"] == 10
        finally:
            reader.close()


class Listener:
    """A TCP listener that collects CoT events (one connection at a time)."""

    def __init__(self):
        self.sock = socket.create_server(("127.0.0.1", 0))
        self.port = self.sock.getsockname()[1]
        self.received = bytearray()
        self.lock = threading.Lock()
        threading.Thread(target=self._serve, daemon=True).start()

    def _serve(self):
        while True:
            try:
                conn, _ = self.sock.accept()
            except OSError:
                return
            with conn:
                while chunk := conn.recv(65536):
                    with self.lock:
                        self.received += chunk

    def events(self, count: int, timeout_s: float = 5.0) -> list[str]:
        deadline = time.monotonic() + timeout_s
        while time.monotonic() < deadline:
            with self.lock:
                text = self.received.decode()
            found = [part + "</event>" for part in text.split("</event>")[:-1]]
            if len(found) >= count:
                return found
            time.sleep(0.02)
        raise AssertionError(f"received {len(found)} events, not {count}: {text[:500]}")

    def close(self):
        self.sock.close()


def test_tak_feed_sends_fixes_with_cot_options_and_session_updates(monkeypatch, tmp_path):
    listener = Listener()
    monkeypatch.setenv("PASSIVE_LOCATOR_TAK_URL", f"tcp://127.0.0.1:{listener.port}")
    try:
        with TestClient(create_app(Settings(store=f"sqlite:///{tmp_path}/s.db"))) as client:
            assert client.post("/v1/fixes", json=bearing_request(STATIONS_300KM, TARGET)).status_code == 200
            fix = bearing_request(STATIONS_300KM, TARGET, cot={"uid": "tak-1"})
            assert client.post("/v1/fixes", json=fix).status_code == 200
            batch = {"problems": [bearing_request(STATIONS_300KM, TARGET, cot={"uid": "tak-2"}),
                                  bearing_request(STATIONS_300KM, TARGET)]}
            assert client.post("/v1/fixes/batch", json=batch).status_code == 200
            session = client.post("/v1/sessions", json=create_body(frame="wgs84")).json()
            client.post(f"/v1/sessions/{session['id']}/measurements", json={"measurements": EPOCHS})
            events = [cot_event(text) for text in listener.events(3)]
            assert [e.get("uid") for e in events] == ["tak-1", "tak-2", f"passive-locator-session-{session['id']}"]
            assert events[2].find("detail/track") is not None
            time.sleep(0.2)
            assert sample(client.get("/metrics").text, "passive_locator_tak_events_total", outcome="sent") == 3
    finally:
        listener.close()


def test_the_tak_sender_thread_stops_when_the_app_shuts_down(monkeypatch, tmp_path):
    listener = Listener()
    monkeypatch.setenv("PASSIVE_LOCATOR_TAK_URL", f"tcp://127.0.0.1:{listener.port}")
    try:
        with TestClient(create_app(Settings(store=f"sqlite:///{tmp_path}/s.db"))) as client:
            fix = bearing_request(STATIONS_300KM, TARGET, cot={"uid": "tak-1"})
            assert client.post("/v1/fixes", json=fix).status_code == 200
            listener.events(1)
            assert any(t.name == "tak-feed" and t.is_alive() for t in threading.enumerate())
        deadline = time.monotonic() + 3.0
        while any(t.name == "tak-feed" and t.is_alive() for t in threading.enumerate()):
            assert time.monotonic() < deadline, "the TAK sender thread outlived the app"
            time.sleep(0.02)
    finally:
        listener.close()


def test_tak_queue_drops_are_counted_and_never_block(monkeypatch, tmp_path):
    with socket.socket() as s:  # a port nobody listens on: every connection attempt fails
        s.bind(("127.0.0.1", 0))
        port = s.getsockname()[1]
    monkeypatch.setenv("PASSIVE_LOCATOR_TAK_URL", f"tcp://127.0.0.1:{port}")
    monkeypatch.setenv("PASSIVE_LOCATOR_TAK_QUEUE_SIZE", "2")
    with TestClient(create_app(Settings(store=f"sqlite:///{tmp_path}/s.db"))) as client:
        started = time.monotonic()
        for i in range(8):
            response = client.post("/v1/fixes", json=bearing_request(STATIONS_300KM, TARGET, cot={"uid": f"d-{i}"}))
            assert response.status_code == 200
        assert time.monotonic() - started < 20.0
        text = client.get("/metrics").text
        dropped = sample(text, "passive_locator_tak_queue_dropped_total")
        assert 8 - 2 - 1 <= dropped <= 8 - 2  # the queue holds 2, the sender at most 1 more
        assert sample(text, "passive_locator_tak_events_total", outcome="failed") >= 1
        client.app.state.tak_feed.close()


def test_tak_feed_over_udp_sends_one_datagram_per_event(monkeypatch, tmp_path):
    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as listener:
        listener.bind(("127.0.0.1", 0))
        listener.settimeout(5.0)
        monkeypatch.setenv("PASSIVE_LOCATOR_TAK_URL", f"udp://127.0.0.1:{listener.getsockname()[1]}")
        with TestClient(create_app(Settings(store=f"sqlite:///{tmp_path}/s.db"))) as client:
            for uid in ("u-1", "u-2"):
                body = bearing_request(STATIONS_300KM, TARGET, cot={"uid": uid})
                assert client.post("/v1/fixes", json=body).status_code == 200
            received = [cot_event(listener.recv(65536).decode()).get("uid") for _ in range(2)]
            assert received == ["u-1", "u-2"]
            client.app.state.tak_feed.close()


def test_a_bad_tak_url_is_refused():
    from pydantic import ValidationError

    from service.renderings.tak import TakSettings

    for url in ("http://tak:8087", "tcp://tak", "tak:8087"):
        with pytest.raises(ValidationError):
            TakSettings(url=url)
    assert TakSettings(url="tls://tak.example:8089").url == "tls://tak.example:8089"


def _self_signed(directory) -> tuple[str, str]:
    """A certificate and key for 127.0.0.1 (openssl CLI), to stand for a TAK server's."""
    import shutil
    import subprocess

    if shutil.which("openssl") is None:
        pytest.skip("openssl is needed to make a test certificate")
    cert, key = str(directory / "tak.pem"), str(directory / "tak.key")
    subprocess.run(["openssl", "req", "-x509", "-newkey", "rsa:2048", "-nodes", "-days", "1", "-subj", "/CN=127.0.0.1",
                    "-addext", "subjectAltName=IP:127.0.0.1", "-keyout", key, "-out", cert],
                   check=True, capture_output=True, timeout=60)
    return cert, key


def test_tak_feed_over_tls_verifies_the_server(monkeypatch, tmp_path):
    import ssl

    cert, key = _self_signed(tmp_path)
    context = ssl.SSLContext(ssl.PROTOCOL_TLS_SERVER)
    context.load_cert_chain(cert, key)
    server = socket.create_server(("127.0.0.1", 0))
    received = queue.Queue()

    def serve():
        conn, _ = server.accept()
        with context.wrap_socket(conn, server_side=True) as tls:
            data = b""
            while b"</event>" not in data:
                data += tls.recv(65536)
            received.put(data.decode())

    threading.Thread(target=serve, daemon=True).start()
    monkeypatch.setenv("PASSIVE_LOCATOR_TAK_URL", f"tls://127.0.0.1:{server.getsockname()[1]}")
    monkeypatch.setenv("PASSIVE_LOCATOR_TAK_CA_FILE", cert)
    try:
        with TestClient(create_app(Settings(store=f"sqlite:///{tmp_path}/s.db"))) as client:
            body = bearing_request(STATIONS_300KM, TARGET, cot={"uid": "tls-1"})
            assert client.post("/v1/fixes", json=body).status_code == 200
            assert cot_event(received.get(timeout=10)).get("uid") == "tls-1"
            client.app.state.tak_feed.close()
    finally:
        server.close()


def test_every_event_is_what_the_spec_declares(server):
    """Each event as a client parses it (event, id, data) matches the event schema (the stream's itemSchema) of
    the committed spec:
    its required fields, its event names, a numeric id, and data that is a SessionState or ``{"id"}``."""
    import json
    import re

    from service.schemas.sessions import SessionState
    from tests.service.sessions.helpers import REPO

    spec = json.loads((REPO / "openapi" / "openapi.json").read_text())
    item = spec["paths"]["/v1/sessions/{session_id}/events"]["get"]["responses"]["200"]["content"][
        "text/event-stream"]["itemSchema"]
    schema = spec["components"]["schemas"][item["$ref"].rsplit("/", 1)[-1]]
    session = _create(server.url)
    reader = EventReader(f"{server.url}/v1/sessions/{session['id']}/events?formats=cot,geojson")
    try:
        events = [reader.next(10.0)]
        httpx.post(f"{server.url}/v1/sessions/{session['id']}/measurements", json={"measurements": EPOCHS[:5]},
                   timeout=30)
        events.append(reader.next(5.0))
        httpx.delete(f"{server.url}/v1/sessions/{session['id']}", timeout=30)
        events.append(reader.next(5.0))
    finally:
        reader.close()
    assert [e["event"] for e in events] == ["state", "state", "deleted"]
    for event in events:
        assert set(schema["required"]) <= event.keys() <= schema["properties"].keys(), event
        assert event["event"] in schema["properties"]["event"]["enum"]
        data = orjson.loads(event["data"])
        if event["event"] == "state":
            assert re.fullmatch(schema["properties"]["id"]["pattern"], event["id"])
            SessionState.model_validate(data)
        else:
            assert data == {"id": session["id"]}
