"""Faults on real processes: a killed or stopped Redis, a read-only, full or damaged SQLite, heavy and abandoned
evaluations, SIGTERM, the largest allowed fix. The service answers 503 with Retry-After within 3 s (never 500),
keeps its probes fast, recovers without a restart, stops computing what nobody waits for, and holds the largest
fix within its memory bound.
"""

from __future__ import annotations

import os
import pathlib
import shutil
import signal
import socket
import sqlite3
import subprocess
import sys
import threading
import time

import httpx
import orjson
import pytest
from prometheus_client.parser import text_string_to_metric_families

from tests.service.conftest import STATIONS_300KM, TARGET
from tests.service.sessions.helpers import REPO, create_body, free_port, wait_until_answers

pytestmark = pytest.mark.slow  # real processes and timed faults: ~3 min together


class App:
    """``uvicorn service.main:app`` on a free port, with its own environment; waits for /healthz only."""

    def __init__(self, tmp_path: pathlib.Path, store: str, **env):
        self.port = free_port()
        self.log = tmp_path / f"app-{self.port}.log"
        environment = {**os.environ, "PASSIVE_LOCATOR_STORE": store, "PASSIVE_LOCATOR_LOG_LEVEL": "warning",
                       **{f"PASSIVE_LOCATOR_{k.upper()}": str(v) for k, v in env.items()}}
        with open(self.log, "ab") as log:
            self.process = subprocess.Popen(
                [sys.executable, "-m", "uvicorn", "service.main:app", "--host", "127.0.0.1", "--port", str(self.port),
                 "--log-level", "warning", "--no-access-log", "--timeout-graceful-shutdown", "2"],
                cwd=REPO, env=environment, stdout=log, stderr=subprocess.STDOUT)
        self.url = f"http://127.0.0.1:{self.port}"
        if not wait_until_answers(self.process, f"{self.url}/healthz", 180):
            raise RuntimeError(f"the app did not start: {self.log.read_text()[-3000:]}")

    def stop(self) -> None:
        if self.process.poll() is None:
            self.process.kill()
            self.process.wait(timeout=10)


@pytest.fixture
def app_factory(tmp_path):
    apps = []

    def make(store: str, **env) -> App:
        app = App(tmp_path, store, **env)
        apps.append(app)
        return app

    yield make
    for app in apps:
        app.stop()


class RedisServer:
    def __init__(self, tmp_path: pathlib.Path):
        if shutil.which("redis-server") is None:
            pytest.skip("no redis-server on this machine")
        self.port = free_port()
        self.tmp_path = tmp_path
        self.process: subprocess.Popen | None = None
        self.start()

    def start(self) -> None:
        self.process = subprocess.Popen(
            ["redis-server", "--port", str(self.port), "--bind", "127.0.0.1", "--save", "", "--appendonly", "no",
             "--dir", str(self.tmp_path)], stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
        import redis

        client = redis.Redis(port=self.port, socket_connect_timeout=0.5)
        deadline = time.monotonic() + 10
        while time.monotonic() < deadline:
            try:
                client.ping()
                return
            except redis.RedisError:
                time.sleep(0.05)  # polling a starting process
        raise RuntimeError("redis-server did not start")

    @property
    def url(self) -> str:
        return f"redis://127.0.0.1:{self.port}/0"

    def signal(self, sig) -> None:
        self.process.send_signal(sig)

    def kill(self) -> None:
        if self.process is not None and self.process.poll() is None:
            self.process.send_signal(signal.SIGCONT)
            self.process.kill()
            self.process.wait(timeout=10)


@pytest.fixture
def redis_server(tmp_path):
    server = RedisServer(tmp_path)
    yield server
    server.kill()


#: The store call timeout the servers of these tests run with (the setting's default) and the slack on top of
#: it within which a 503 counts as the guard's: a stopped, dead or hung store never answers by itself, so a
#: request answered 503 within the timeout plus the slack was answered by the guard, and one that hung would
#: run into CLIENT_TIMEOUT_S. The slack is wide so that a loaded machine's scheduling is not what is tested.
CALL_TIMEOUT_S = 2.0
SLACK_S = 10.0
CLIENT_TIMEOUT_S = 60.0


def assert_unavailable(response: httpx.Response, elapsed_s: float) -> None:
    assert response.status_code == 503, response.text
    assert response.headers["content-type"].startswith("application/problem+json")
    assert int(response.headers["retry-after"]) >= 1
    assert elapsed_s < CALL_TIMEOUT_S + SLACK_S, elapsed_s


def timed(call):
    started = time.monotonic()
    response = call()
    return response, time.monotonic() - started


def wait_until(predicate, timeout_s: float = 10.0) -> bool:
    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline:
        if predicate():
            return True
        time.sleep(0.1)  # polling a recovering store
    return False


def _ready(app: App) -> bool:
    try:
        return httpx.get(f"{app.url}/readyz", timeout=3.0).status_code == 200
    except httpx.HTTPError:
        return False


@pytest.mark.redis
def test_redis_killed_is_503_by_the_guard_and_recovers_without_restart(app_factory, redis_server):
    app = app_factory(redis_server.url, store_call_timeout_s=CALL_TIMEOUT_S)
    with httpx.Client(timeout=CLIENT_TIMEOUT_S) as client:
        created = client.post(f"{app.url}/v1/sessions", json=create_body())
        assert created.status_code == 201, created.text
        redis_server.kill()
        for call in (lambda: client.get(f"{app.url}/v1/sessions/{created.json()['id']}"),
                     lambda: client.post(f"{app.url}/v1/sessions", json=create_body()),
                     lambda: client.get(f"{app.url}/v1/sessions"),
                     lambda: client.get(f"{app.url}/readyz")):
            assert_unavailable(*timed(call))
        redis_server.start()
        assert wait_until(lambda: _ready(app))
        assert client.post(f"{app.url}/v1/sessions", json=create_body()).status_code == 201


@pytest.mark.redis
def test_redis_stopped_is_503_by_the_guard_and_healthz_does_not_wait_for_it(app_factory, redis_server):
    """A stopped Redis never answers: every call is answered 503 by the guard's call timeout, and /healthz,
    which does not touch the store, answers each time before a store call could have timed out (a longer call
    timeout than the others' here, so that this holds with room on a loaded machine)."""
    call_timeout_s = 8.0
    app = app_factory(redis_server.url, store_call_timeout_s=call_timeout_s)
    with httpx.Client(timeout=10.0) as client:
        session_id = client.post(f"{app.url}/v1/sessions", json=create_body()).json()["id"]
    redis_server.signal(signal.SIGSTOP)
    outcomes: list[tuple[int, float]] = []

    def stuck_call():
        with httpx.Client(timeout=CLIENT_TIMEOUT_S) as own:
            response, elapsed = timed(lambda: own.get(f"{app.url}/v1/sessions/{session_id}"))
            outcomes.append((response.status_code, elapsed))

    threads = [threading.Thread(target=stuck_call) for _ in range(50)]
    for thread in threads:
        thread.start()
    health = []
    with httpx.Client(timeout=CLIENT_TIMEOUT_S) as client:
        for _ in range(10):
            response, elapsed = timed(lambda: client.get(f"{app.url}/healthz"))
            assert response.status_code == 200
            health.append(elapsed)
    for thread in threads:
        thread.join(timeout=2 * CLIENT_TIMEOUT_S)  # a bound on a hang
    assert len(outcomes) == 50
    assert {status for status, _ in outcomes} == {503}
    assert max(e for _, e in outcomes) < call_timeout_s + SLACK_S, outcomes
    assert max(health) < call_timeout_s, health  # one that waited on the store would take the call timeout
    with httpx.Client(timeout=CLIENT_TIMEOUT_S) as client:
        assert_unavailable(*timed(lambda: client.get(f"{app.url}/readyz")))
        redis_server.signal(signal.SIGCONT)
        assert wait_until(lambda: _ready(app))
        assert client.get(f"{app.url}/v1/sessions/{session_id}").status_code == 200


@pytest.fixture
def tmpfs(tmp_path):
    """A small tmpfs of our own (for a full or read-only filesystem); skipped where mounting is not allowed."""
    where = tmp_path / "fs"
    where.mkdir()
    done = subprocess.run(["mount", "-t", "tmpfs", "-o", "size=1m", "tmpfs", str(where)], capture_output=True)
    if done.returncode != 0:
        pytest.skip(f"cannot mount a tmpfs here: {done.stderr.decode().strip()}")
    yield where
    subprocess.run(["umount", "-l", str(where)], capture_output=True)


def _fill(directory: pathlib.Path) -> None:
    """Write a file until the filesystem is full."""
    descriptor = os.open(directory / "filler", os.O_WRONLY | os.O_CREAT)
    try:
        while True:
            os.write(descriptor, b"\0" * 4096)
    except OSError:
        pass
    finally:
        os.close(descriptor)


def test_sqlite_on_a_full_filesystem_is_503_and_not_ready(app_factory, tmpfs):
    app = app_factory(f"sqlite:///{tmpfs}/sessions.db", sqlite_integrity_interval_s=0)
    with httpx.Client(timeout=10.0) as client:
        assert client.post(f"{app.url}/v1/sessions", json=create_body()).status_code == 201
        _fill(tmpfs)
        statuses = []
        for _ in range(200):
            response, elapsed = timed(lambda: client.post(f"{app.url}/v1/sessions", json=create_body()))
            statuses.append(response.status_code)
            if response.status_code != 201:
                assert_unavailable(response, elapsed)
                break
        assert statuses[-1] == 503, statuses
        assert_unavailable(*timed(lambda: client.get(f"{app.url}/readyz")))
        (tmpfs / "filler").unlink()
        assert wait_until(lambda: _ready(app))
        assert client.post(f"{app.url}/v1/sessions", json=create_body()).status_code == 201


def test_sqlite_on_a_read_only_filesystem_is_503_and_not_ready(app_factory, tmpfs):
    """Read-only from the start (a filesystem with open writers cannot be remounted): the app starts, answers
    503, and uses the store once it is writable again, without a restart."""
    from service.stores import open_store

    open_store(f"sqlite:///{tmpfs}/sessions.db").close()
    subprocess.run(["mount", "-o", "remount,ro", str(tmpfs)], check=True)
    app = app_factory(f"sqlite:///{tmpfs}/sessions.db")
    with httpx.Client(timeout=10.0) as client:
        assert_unavailable(*timed(lambda: client.post(f"{app.url}/v1/sessions", json=create_body())))
        assert_unavailable(*timed(lambda: client.get(f"{app.url}/readyz")))
        subprocess.run(["mount", "-o", "remount,rw", str(tmpfs)], check=True)
        assert wait_until(lambda: _ready(app))
        assert client.post(f"{app.url}/v1/sessions", json=create_body()).status_code == 201


def test_a_damaged_sqlite_file_is_503_and_not_ready(app_factory, tmp_path):
    from fastapi.testclient import TestClient

    from service.app import create_app
    from service.settings import Settings

    path = tmp_path / "damaged.db"
    with TestClient(create_app(Settings(store=f"sqlite:///{path}"))) as client:
        for _ in range(60):
            assert client.post("/v1/sessions", json=create_body()).status_code == 201
    sqlite3.connect(path).execute("PRAGMA wal_checkpoint(TRUNCATE)").close()
    with open(path, "r+b") as raw:  # page 2 onwards: leave the header readable, break the b-tree pages
        raw.seek(4096)
        raw.write(b"\xff" * (os.path.getsize(path) - 4096))
    app = app_factory(f"sqlite:///{path}")
    with httpx.Client(timeout=10.0) as client:
        assert_unavailable(*timed(lambda: client.get(f"{app.url}/readyz")))
        listing = client.get(f"{app.url}/v1/sessions")
        assert listing.status_code == 503, listing.text


def _evaluation(trials: int, methods: list[str]) -> dict:
    return {"scenario": {"stations": [{"id": k, "position": v} for k, v in STATIONS_300KM.items()],
                         "sensors": [{"station_id": k, "sigma_azimuth_deg": 1.0, "sigma_elevation_deg": 1.0}
                                     for k in STATIONS_300KM],
                         "target": TARGET},
            "methods": methods, "trials": trials, "seed": 1}


def _scraped(app: App, name: str) -> float:
    """One unlabelled sample of the server's /metrics."""
    text = httpx.get(f"{app.url}/metrics", timeout=10.0).text
    found = [s.value for f in text_string_to_metric_families(text) for s in f.samples if s.name == name]
    assert len(found) == 1, (name, found)
    return found[0]


def _wait_for(app: App, name: str, holds, timeout_s: float = 120.0) -> float:
    """The metric ``name`` once ``holds(value)``; fails after ``timeout_s`` (a bound on a hang, not a speed)."""
    deadline = time.monotonic() + timeout_s
    while True:
        value = _scraped(app, name)
        if holds(value):
            return value
        assert time.monotonic() < deadline, f"{name} stayed at {value}"
        time.sleep(0.05)  # polling the server's metrics


# What an evaluation did, not how much CPU the machine gave it: the chunks it ran (counted as each ends) and
# whether it still holds a worker of the CPU pool. A machine under load runs fewer chunks a second, but the
# evaluation must still stop at a chunk's end and let its worker go.
CHUNKS = "passive_locator_evaluation_chunks_total"
RUNNING = "passive_locator_evaluations_running"


def test_an_abandoned_evaluation_stops_and_releases_its_worker(app_factory, tmp_path):
    app = app_factory(f"sqlite:///{tmp_path}/s.db", max_evaluation_cost=10**9, request_deadline_s=600)
    body = orjson.dumps(_evaluation(100_000, ["ml", "eove", "ove"]))  # 400 chunks of 250 trials
    with socket.create_connection(("127.0.0.1", app.port)) as connection:
        connection.sendall(b"POST /v1/evaluations HTTP/1.1\r\nHost: x\r\nContent-Type: application/json\r\n"
                           b"Content-Length: " + str(len(body)).encode() + b"\r\n\r\n" + body)
        _wait_for(app, CHUNKS, lambda chunks: chunks >= 2)  # it is running
        assert _scraped(app, RUNNING) == 1
    _wait_for(app, RUNNING, lambda running: running == 0)  # the disconnect stopped it: its worker is free
    ran = _scraped(app, CHUNKS)
    assert ran < 200, ran  # it stopped, far from its 400 chunks
    # and nothing of it runs any more: one more evaluation's first chunks are the only ones counted
    with httpx.Client(timeout=60.0) as client:
        assert client.post(f"{app.url}/v1/evaluations", json=_evaluation(500, ["eove"])).status_code == 200
    assert _scraped(app, CHUNKS) == ran + 2 and _scraped(app, RUNNING) == 0


def test_an_over_budget_evaluation_is_refused_and_an_over_deadline_one_stops(app_factory, tmp_path):
    app = app_factory(f"sqlite:///{tmp_path}/s.db", request_deadline_s=1, max_evaluation_cost=2_000_000)
    with httpx.Client(timeout=60.0) as client:
        refused = client.post(f"{app.url}/v1/evaluations", json=_evaluation(100_000, ["ml", "eove", "ove", "tls",
                                                                                       "ple3d", "ws3d"]))
        assert refused.status_code == 422 and refused.json()["code"] == "over_limit", refused.text
        assert "max_evaluation_cost" in refused.json()["detail"]
        assert refused.json()["errors"][0]["loc"] == ["trials"]
        assert _scraped(app, CHUNKS) == 0  # refused before any work
        response = client.post(f"{app.url}/v1/evaluations", json=_evaluation(100_000, ["eove", "ove"]))
        assert response.status_code == 503 and response.json()["code"] == "deadline_exceeded", response.text
    _wait_for(app, RUNNING, lambda running: running == 0)
    ran = _scraped(app, CHUNKS)
    assert 0 < ran < 100_000 // 250, ran  # it started, and stopped at the deadline, not at its last chunk


def test_sigterm_stops_the_server_within_its_graceful_timeout(app_factory, tmp_path):
    app = app_factory(f"sqlite:///{tmp_path}/s.db", max_evaluation_cost=10**9, request_deadline_s=600)
    started = threading.Event()

    def long_evaluation():
        started.set()
        try:
            httpx.post(f"{app.url}/v1/evaluations", json=_evaluation(100_000, ["eove"]), timeout=30)
        except httpx.HTTPError:
            pass

    thread = threading.Thread(target=long_evaluation)
    thread.start()
    started.wait()
    time.sleep(1.0)  # let the evaluation get going
    sent = time.monotonic()
    app.process.send_signal(signal.SIGTERM)
    app.process.wait(timeout=15)
    assert time.monotonic() - sent < 2.0 + 2.0  # the 2 s graceful timeout, plus one chunk and the exit
    thread.join(timeout=30)


def _memory_kib(pid: int, field: str) -> int:
    """``VmRSS`` (resident now) or ``VmHWM`` (peak resident so far) of a process, KiB, from /proc."""
    for line in pathlib.Path(f"/proc/{pid}/status").read_text().splitlines():
        if line.startswith(field + ":"):
            return int(line.split()[1])
    raise KeyError(field)


def test_the_largest_allowed_fix_stays_within_300_mb_with_every_method(app_factory, tmp_path):
    """256 stations x 1,024 bearings (the schema's and max_fix_cost's largest) with each method: the server's
    peak resident memory grows by less than 300 MB over what it held before the first of them (time: bench)."""
    from bench.scenarios import largest_fix_request
    from service.schemas import METHODS

    app = app_factory(f"sqlite:///{tmp_path}/s.db")
    small = largest_fix_request("ml")
    small["stations"], small["measurements"] = small["stations"][:4], small["measurements"][:16]
    with httpx.Client(timeout=120.0) as client:
        assert client.post(f"{app.url}/v1/fixes", json=small).status_code == 200  # imports and caches warmed
        before_kib = _memory_kib(app.process.pid, "VmRSS")
        answered = {}
        for method in sorted(METHODS):
            response = client.post(f"{app.url}/v1/fixes", json=largest_fix_request(method))
            answered[method] = response.status_code
            assert response.status_code in (200, 422), response.text  # 422: a method that needs other kinds
            grown_mb = (_memory_kib(app.process.pid, "VmHWM") - before_kib) * 1024 / 1e6
            assert grown_mb < 300, (method, grown_mb)
    assert sum(status == 200 for status in answered.values()) >= 8, answered
