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
from tests.service.sessions.helpers import REPO, free_port

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
        deadline = time.monotonic() + 120  # a cold numba cache compiles first
        while time.monotonic() < deadline:
            assert self.process.poll() is None, self.log.read_text()[-3000:]
            try:
                if httpx.get(f"{self.url}/healthz", timeout=1.0).status_code == 200:
                    return
            except httpx.HTTPError:
                pass
            time.sleep(0.05)  # polling a starting process
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
    time.sleep(1.0)  # the evaluation is under way (it takes far longer than this)
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
