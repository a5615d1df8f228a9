"""The server as deployed (``passive-locator serve``, a real process on loopback): what a client gets when the
server stops under it, and what becomes of connections whose request never completes.
"""

from __future__ import annotations

import os
import pathlib
import signal
import socket
import subprocess
import sys
import threading
import time

import httpx
import orjson
import pytest

from tests.service.conftest import STATIONS_300KM, TARGET
from tests.service.sessions.helpers import REPO, free_port, wait_until_answers

pytestmark = pytest.mark.slow  # real processes


class Served:
    """``python -m service.cli serve`` on a free loopback port with its own settings; waits for /healthz."""

    def __init__(self, tmp_path: pathlib.Path, **settings):
        self.port = free_port()
        self.url = f"http://127.0.0.1:{self.port}"
        self.log = tmp_path / f"serve-{self.port}.log"
        environment = {**os.environ, "PASSIVE_LOCATOR_STORE": f"sqlite:///{tmp_path}/sessions-{self.port}.db",
                       "PASSIVE_LOCATOR_LOG_LEVEL": "warning",
                       **{f"PASSIVE_LOCATOR_{k.upper()}": str(v) for k, v in settings.items()}}
        with open(self.log, "ab") as log:
            self.process = subprocess.Popen([sys.executable, "-m", "service.cli", "serve", "--host", "127.0.0.1",
                                             "--port", str(self.port)],
                                            cwd=REPO, env=environment, stdout=log, stderr=subprocess.STDOUT)
        if not wait_until_answers(self.process, f"{self.url}/healthz", 120):
            raise RuntimeError(f"the server did not start: {self.log.read_text()[-3000:]}")

    def stop(self) -> None:
        if self.process.poll() is None:
            self.process.kill()
            self.process.wait(timeout=10)


@pytest.fixture
def serve(tmp_path):
    servers = []

    def make(**settings) -> Served:
        servers.append(Served(tmp_path, **settings))
        return servers[-1]

    yield make
    for server in servers:
        server.stop()


def _evaluation(trials: int, methods: list[str]) -> dict:
    return {"scenario": {"stations": [{"id": k, "position": v} for k, v in STATIONS_300KM.items()],
                         "sensors": [{"station_id": k, "sigma_azimuth_deg": 1.0, "sigma_elevation_deg": 1.0}
                                     for k in STATIONS_300KM],
                         "target": TARGET},
            "methods": methods, "trials": trials, "seed": 1}


def _in_flight(server: Served) -> float:
    """The server's requests-in-flight gauge (the scrape itself included)."""
    for line in httpx.get(f"{server.url}/metrics", timeout=10).text.splitlines():
        if line.startswith("passive_locator_requests_in_flight"):
            return float(line.split()[-1])
    return 0.0


def _wait_for(predicate, timeout_s: float = 60.0) -> bool:
    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline:
        if predicate():
            return True
        time.sleep(0.05)  # polling the server
    return False


def _answer_during_sigterm(server: Served, methods: list[str]) -> httpx.Response:
    """Start an evaluation, SIGTERM the server once it is under way, and return what the client got."""
    answers: list = []

    def client():
        try:
            answers.append(httpx.post(f"{server.url}/v1/evaluations", json=_evaluation(100_000, methods),
                                      timeout=120))
        except httpx.HTTPError as error:
            answers.append(error)

    thread = threading.Thread(target=client)
    thread.start()
    assert _wait_for(lambda: _in_flight(server) >= 2)  # the evaluation and this scrape: it is being answered
    time.sleep(0.5)  # under way (it takes seconds)
    assert thread.is_alive()
    server.process.send_signal(signal.SIGTERM)
    thread.join(timeout=120)
    assert server.process.wait(timeout=60) in (0, -signal.SIGTERM)  # uvicorn re-raises the signal it handled
    assert len(answers) == 1 and isinstance(answers[0], httpx.Response), answers
    return answers[0]


def test_a_request_cut_off_by_shutdown_gets_a_503_problem_telling_it_to_retry(serve):
    server = serve(graceful_timeout_s=1, request_deadline_s=600, max_evaluation_cost=10**9)
    answer = _answer_during_sigterm(server, ["ml", "eove", "ove", "tls"])  # about 9 s of work on an idle core
    assert answer.status_code == 503, answer.text
    assert answer.headers["content-type"] == "application/problem+json"
    assert answer.json()["code"] == "shutting_down"
    assert int(answer.headers["retry-after"]) >= 1


def test_a_request_that_finishes_within_the_grace_period_gets_its_answer(serve):
    server = serve(graceful_timeout_s=120, request_deadline_s=600, max_evaluation_cost=10**9)
    answer = _answer_during_sigterm(server, ["eove"])  # about 4 s of work on an idle core
    assert answer.status_code == 200, answer.text
    assert answer.json()["trials"] == 100_000


def _read_until_closed(connection: socket.socket, within_s: float) -> tuple[bytes, bool]:
    """What the server sent on ``connection`` and whether it closed it, within ``within_s`` seconds."""
    received, deadline = b"", time.monotonic() + within_s
    while (left := deadline - time.monotonic()) > 0:
        connection.settimeout(left)
        try:
            chunk = connection.recv(65536)
        except TimeoutError:
            break
        except ConnectionResetError:
            return received, True
        if not chunk:
            return received, True
        received += chunk
    return received, False


def _connect(server: Served, send: bytes = b"") -> socket.socket:
    connection = socket.create_connection(("127.0.0.1", server.port), timeout=5)
    if send:
        connection.sendall(send)
    return connection


def _status_and_problem(response: bytes) -> tuple[int, dict]:
    head, _, body = response.partition(b"\r\n\r\n")
    assert b"content-type: application/problem+json" in head.lower(), response[:300]
    return int(head.split(b" ", 2)[1]), orjson.loads(body)


PARTIAL_HEADERS = b"GET /healthz HTTP/1.1\r\nHost: x\r\nUser-Agent: slow"
PARTIAL_BODY = (b"POST /v1/fixes HTTP/1.1\r\nHost: x\r\nContent-Type: application/json\r\nContent-Length: 1000\r\n\r\n"
                b'{"stations"')

PARTIAL_CHUNKED = (b"POST /v1/sessions HTTP/1.1\r\nHost: x\r\nContent-Type: application/json\r\n"
                   b"Transfer-Encoding: chunked\r\n\r\n5\r\n{\"fr")


def test_requests_that_never_finish_are_closed_at_their_deadline_while_healthz_answers(serve):
    server = serve(header_timeout_s=1, body_timeout_s=1)
    held = {"nothing sent": [_connect(server) for _ in range(10)],
            "headers unfinished": [_connect(server, PARTIAL_HEADERS) for _ in range(20)],
            "body unfinished": [_connect(server, PARTIAL_BODY) for _ in range(20)],
            "chunked body unfinished": [_connect(server, PARTIAL_CHUNKED) for _ in range(10)],
            "request line unfinished": [_connect(server, b"POST /v1/fix") for _ in range(10)]}
    assert httpx.get(f"{server.url}/healthz", timeout=5).status_code == 200  # while all of them are held
    try:
        for kind, connections in held.items():
            for connection in connections:
                response, closed = _read_until_closed(connection, within_s=30)
                assert closed, (kind, response)
                status, problem = _status_and_problem(response)
                assert (status, problem["code"]) == (408, "request_timeout"), (kind, problem)
    finally:
        for connection in (c for connections in held.values() for c in connections):
            connection.close()
    assert httpx.get(f"{server.url}/healthz", timeout=5).status_code == 200


def test_a_header_trickling_in_byte_by_byte_is_closed_at_the_deadline(serve):
    server = serve(header_timeout_s=1)
    with _connect(server) as connection:
        closed = False
        for byte in PARTIAL_HEADERS * 10:  # far more bytes than arrive before the deadline, one per 50 ms
            try:
                connection.sendall(bytes([byte]))
            except (BrokenPipeError, ConnectionResetError):
                closed = True
                break
            time.sleep(0.05)  # a slow client, on purpose
            connection.settimeout(0.001)
            try:
                if connection.recv(65536, socket.MSG_PEEK):
                    closed = True
                    break
            except (TimeoutError, BlockingIOError):
                pass
        assert closed  # the server answered (408) or closed before the client finished trickling


def test_headers_over_their_bound_are_a_431(serve):
    server = serve()
    from service.ops.server import MAX_HEADER_BYTES

    with _connect(server, b"GET /healthz HTTP/1.1\r\nHost: x\r\n") as connection:
        try:
            for _ in range(MAX_HEADER_BYTES // 1000 + 2):
                connection.sendall(b"X-Padding: " + b"a" * 987 + b"\r\n")
        except (BrokenPipeError, ConnectionResetError):
            pass
        response, closed = _read_until_closed(connection, within_s=30)
    assert closed
    assert _status_and_problem(response)[0] == 431


def test_the_connection_bound_makes_room_for_a_new_client(serve):
    server = serve(header_timeout_s=120, max_connections=10)
    slow = []
    for _ in range(30):
        slow.append(_connect(server, PARTIAL_HEADERS))
        time.sleep(0.01)  # connections in a known order: the oldest go first
    try:
        for _ in range(3):
            assert httpx.get(f"{server.url}/healthz", timeout=5).status_code == 200
        outcomes = [_read_until_closed(connection, within_s=0.5 if i >= 20 else 10) for i, connection in
                    enumerate(slow)]
        evicted = [i for i, (response, closed) in enumerate(outcomes) if closed]
        assert len(evicted) >= 20, evicted  # 30 slow connections and the probes' held within 10
        assert set(range(20)) <= set(evicted)  # the longest waiting went first
        for i in evicted:
            status, problem = _status_and_problem(outcomes[i][0])
            assert (status, problem["code"]) == (503, "too_many_connections")
    finally:
        for connection in slow:
            connection.close()


def test_serve_runs_the_bounded_protocol_and_the_defaults_are_at_most_30_s(monkeypatch):
    from service import cli
    from service.settings import Settings

    ran = []
    monkeypatch.setattr("uvicorn.run", lambda *args, **kwargs: ran.append(kwargs))
    cli.main(["serve", "--host", "127.0.0.1"])
    assert ran[0]["http"] == "service.ops.server:BoundedHttpToolsProtocol"
    assert ran[0]["ws"] == "none"  # the deadlines are the HTTP protocol's: no connection leaves it for another
    defaults = Settings(_env_file=None)
    assert 0 < defaults.header_timeout_s <= 30 and 0 < defaults.body_timeout_s <= 30
    assert defaults.max_connections >= 1


@pytest.mark.parametrize("request_bytes", [
    b"POST /v1/fixes HTTP/1.1\r\nHost: x\r\nContent-Length: \xb2\r\n\r\n",
    b"POST /v1/fixes HTTP/1.1\r\nHost: x\r\nContent-Length: 2\r\nContent-Length: 3\r\n\r\n{}",
    b"GET /healthz HTTP/1.1\r\nHost: x\r\nBad Header: 1\r\n\r\n",
], ids=["content-length-superscript", "content-length-twice", "space-in-a-field-name"])
def test_a_request_the_http_parser_refuses_is_a_400_problem(serve, request_bytes):
    server = serve()
    with _connect(server, request_bytes) as connection:
        response, closed = _read_until_closed(connection, within_s=30)
    assert closed
    status, problem = _status_and_problem(response)
    assert (status, problem["code"]) == (400, "malformed_request")


def test_an_upgrade_request_stays_under_the_deadlines(serve):
    server = serve(body_timeout_s=1)
    upgrade = (b"GET /healthz HTTP/1.1\r\nHost: x\r\nConnection: Upgrade\r\nUpgrade: websocket\r\n"
               b"Sec-WebSocket-Version: 13\r\nSec-WebSocket-Key: dGhlIHNhbXBsZSBub25jZQ==\r\n\r\n")
    with _connect(server, upgrade) as connection:
        response, _ = _read_until_closed(connection, within_s=3)
    assert response.startswith(b"HTTP/1.1 200"), response[:200]  # answered as the plain GET it also is


def test_when_every_connection_is_being_served_a_new_one_is_refused_with_a_503(serve):
    from tests.service.sessions.helpers import create_body

    server = serve(max_connections=3)
    session = httpx.post(f"{server.url}/v1/sessions", json=create_body()).json()["id"]
    streams = []
    try:
        for _ in range(3):  # event streams: each connection busy with a response that lasts
            stream = _connect(server, f"GET /v1/sessions/{session}/events HTTP/1.1\r\nHost: x\r\n\r\n".encode())
            stream.settimeout(30)
            assert stream.recv(65536).startswith(b"HTTP/1.1 200")
            streams.append(stream)
        with _connect(server) as refused:
            response, closed = _read_until_closed(refused, within_s=30)
        assert closed
        status, problem = _status_and_problem(response)
        assert (status, problem["code"]) == (503, "too_many_connections")
    finally:
        for stream in streams:
            stream.close()
    assert _wait_for(lambda: _healthy(server))  # the streams' connections are free again


def _healthy(server: Served) -> bool:
    try:
        return httpx.get(f"{server.url}/healthz", timeout=5).status_code == 200
    except httpx.HTTPError:
        return False
