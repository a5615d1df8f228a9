"""Shared pieces of the session tests: the paper-001 scenario at the API, and real server processes."""

from __future__ import annotations

import math
import os
import pathlib
import signal
import socket
import subprocess
import sys
import threading
import time

import httpx
import numpy as np

from core.simulation.emitter import paper_001_scenario, simulate_emitter

REPO = pathlib.Path(__file__).resolve().parents[3]

#: Paper 001: 5 mrad angles, 0.2 mrad/s azimuth rate, 10 ns TOA; Tr = 1 ms, N = 1000.
PAPER_NOISE = {
    "sigma_azimuth_deg": math.degrees(5e-3),
    "sigma_elevation_deg": math.degrees(5e-3),
    "sigma_azimuth_rate_deg_s": math.degrees(2e-4),
    "sigma_toa_s": 1e-8,
}

OBSERVER_WGS84 = {"lat_deg": 34.25, "lon_deg": 108.95, "alt_m": 420.0}


#: The "unknown" period's initial estimate is this far off the truth (as in tests/core/tracking).
UNKNOWN_PERIOD_OFFSET_S = 20e-9


def create_body(model: str = "velocity_kinematic", period_known: bool = False, frame: str = "local",
                ttl_s: float = 3600.0, accel_sigma_mps2: float = 0.05, observer: dict | None = None,
                period_s: float | None = None) -> dict:
    """A create request for the paper-001 sensor (Tr = 1 ms, N = 1000); an unknown period starts 20 ns off."""
    if period_s is None:
        period_s = 1e-3 if period_known else 1e-3 + UNKNOWN_PERIOD_OFFSET_S
    if observer is None:
        observer = OBSERVER_WGS84 if frame == "wgs84" else {"east_m": 0.0, "north_m": 0.0, "up_m": 0.0}
    return {
        "frame": frame,
        "observer": {"position": observer},
        "model": model,
        "pulse": {"period_s": period_s, "period_known": period_known, "pulses_per_observation": 1000},
        "noise": dict(PAPER_NOISE),
        "process_noise": {"accel_sigma_mps2": accel_sigma_mps2},
        "ttl_s": ttl_s,
    }


def paper_track(seed: int, epochs: int = 201):
    """One paper-001 run (truth and noisy reports), seeded."""
    return simulate_emitter(paper_001_scenario(epochs=epochs), np.random.default_rng(seed))


def api_epochs(track, first_seq: int = 1) -> list[dict]:
    """The track's reports as API measurement epochs (degrees), seq from ``first_seq``."""
    return [{"seq": first_seq + i, "time_s": e.time_s, "azimuth_deg": math.degrees(e.azimuth_rad),
             "elevation_deg": math.degrees(e.elevation_rad), "azimuth_rate_deg_s": math.degrees(e.azimuth_rate_rad_s),
             "toa_s": e.toa_s} for i, e in enumerate(track.epochs)]


def batches(epochs: list[dict], size: int) -> list[list[dict]]:
    return [epochs[i:i + size] for i in range(0, len(epochs), size)]


#: Fields of a session body that depend only on the measurements applied (not on ids, clocks or versions).
FILTER_FIELDS = ("last_seq", "last_time_s", "updates", "initialized", "position", "position_local",
                 "velocity_enu_mps", "range_m", "range_sigma_m", "pulse_period_s", "covariance_enu")


def filter_view(body: dict) -> dict:
    return {name: body[name] for name in FILTER_FIELDS}


def assert_close_bodies(actual: dict, expected: dict, rtol: float = 1e-9) -> None:
    """Every filter field equal, numbers to ``rtol`` relative (of the largest magnitude in the field)."""
    for name in FILTER_FIELDS:
        a, e = actual[name], expected[name]
        if isinstance(e, dict):
            e, a = list(e.values()), [a[k] for k in e]
        if e is None or isinstance(e, bool):
            assert a == e, name
        elif isinstance(e, int) and not isinstance(e, bool) and name in ("last_seq", "updates"):
            assert a == e, name
        else:
            e_arr, a_arr = np.asarray(e, dtype=float), np.asarray(a, dtype=float)
            scale = max(float(np.max(np.abs(e_arr))), 1e-300)
            assert np.all(np.abs(a_arr - e_arr) <= rtol * scale), (name, a, e)


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def wait_until_answers(process: subprocess.Popen, url: str, timeout_s: float) -> bool:
    """Poll ``url`` of a starting server ``process`` until it answers 200 (True), or the process exits or
    ``timeout_s`` passes (False): a bound on a hang, not a speed."""
    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline:
        if process.poll() is not None:
            return False
        try:
            if httpx.get(url, timeout=1.0).status_code == 200:
                return True
        except httpx.HTTPError:
            pass
        time.sleep(0.05)
    return False


class Server:
    """A real ``uvicorn service.main:app`` process on a free loopback port."""

    def __init__(self, store_url: str, log_path: pathlib.Path, extra_env: dict | None = None):
        self.store_url = store_url
        self.log_path = log_path
        self.extra_env = extra_env or {}
        self.process: subprocess.Popen | None = None
        self.port = 0

    @property
    def url(self) -> str:
        return f"http://127.0.0.1:{self.port}"

    def start(self, timeout_s: float = 180.0) -> "Server":
        env = {**os.environ, "PASSIVE_LOCATOR_STORE": self.store_url, "PASSIVE_LOCATOR_LOG_LEVEL": "warning",
               **self.extra_env}
        env.pop("PASSIVE_LOCATOR_API_KEYS", None)
        for attempt in range(3):  # a port picked free can be taken by another process before uvicorn binds it
            self.port = free_port()
            log = open(self.log_path, "ab")
            self.process = subprocess.Popen(
                [sys.executable, "-m", "uvicorn", "service.main:app", "--host", "127.0.0.1", "--port",
                 str(self.port), "--log-level", "warning", "--no-access-log"],
                cwd=REPO, env=env, stdout=log, stderr=subprocess.STDOUT)
            log.close()
            if self._wait_ready(timeout_s):
                return self
            self.kill()
        raise RuntimeError(f"uvicorn did not start; log:\n{self.log_path.read_text()[-4000:]}")

    def _wait_ready(self, timeout_s: float) -> bool:
        return wait_until_answers(self.process, f"{self.url}/readyz", timeout_s)

    def kill(self) -> None:
        """SIGKILL: no shutdown hook runs, nothing is flushed on the way out."""
        if self.process is not None and self.process.poll() is None:
            self.process.send_signal(signal.SIGKILL)
            self.process.wait(timeout=10)
        self.process = None

    def __enter__(self) -> "Server":
        return self.start()

    def __exit__(self, *exc) -> None:
        self.kill()


def reference_run(epochs: list[dict], batch_size: int, **create_changes) -> dict:
    """The final body of posting ``epochs`` sequentially in one process, no kill, no concurrency."""
    from fastapi.testclient import TestClient

    from service.app import create_app
    from service.settings import Settings

    with TestClient(create_app(Settings(store="sqlite:///:memory:"))) as client:
        session_id = client.post("/v1/sessions", json=create_body(**create_changes)).json()["id"]
        for batch in batches(epochs, batch_size):
            response = client.post(f"/v1/sessions/{session_id}/measurements", json={"measurements": batch})
            assert response.status_code == 200, response.text
        return client.get(f"/v1/sessions/{session_id}").json()


def post_batch(client: httpx.Client, base: str, session_id: str, route: str, batch: list[dict]) -> dict:
    """POST one batch to a session's ``route`` (``"measurements"`` or ``"reports"``); it must answer 200."""
    response = client.post(f"{base}/v1/sessions/{session_id}/{route}", json={route: batch})
    assert response.status_code == 200, response.text
    return response.json()


def post_from_clients(servers: list, session_id: str, route: str, stream: list[list[dict]], clients: int = 4,
                      join_timeout_s: float = 120.0) -> tuple[list[dict], list[str]]:
    """Each of ``clients`` threads posts every batch of ``stream``, the servers taken in turn: every batch
    arrives ``clients`` times, concurrently, so exactly one post of each may apply it.

    Returns the answers and the errors the threads met.
    """
    results, failures = [], []

    def run(i: int):
        try:
            with httpx.Client(timeout=60.0) as own:
                for j, batch in enumerate(stream):
                    results.append(post_batch(own, servers[(i + j) % len(servers)].url, session_id, route, batch))
        except Exception as error:  # reported to the caller
            failures.append(repr(error))

    threads = [threading.Thread(target=run, args=(i,)) for i in range(clients)]
    for t in threads:
        t.start()
    for t in threads:
        t.join(timeout=join_timeout_s)
    return results, failures
