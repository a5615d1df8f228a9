"""HTTP load on loopback: wrk when it is there (installed with apt-get when we are root), else asyncio.

Both generators keep ``connections`` keep-alive connections busy for a fixed
time and report requests/s, p50 and p99 latency. Every request goes to
127.0.0.1 only, and every run stops by itself.
"""

from __future__ import annotations

import asyncio
import os
import re
import shutil
import subprocess
import tempfile
import time
from dataclasses import dataclass
from urllib.parse import urlsplit

import numpy as np


@dataclass(frozen=True)
class LoadResult:
    """What one load run measured."""

    requests_per_s: float
    p50_ms: float
    p99_ms: float
    requests: int
    failures: int
    generator: str


def find_wrk(install: bool = True) -> tuple[str | None, str]:
    """The wrk binary (installing Debian's package when missing and we are root) and how it was found."""
    path = shutil.which("wrk")
    if path:
        return path, f"wrk ({path})"
    if not install or os.geteuid() != 0 or not shutil.which("apt-get"):
        return None, "wrk not found and not installable here (not root or no apt-get)"
    env = {**os.environ, "DEBIAN_FRONTEND": "noninteractive"}
    for command in (["apt-get", "install", "-y", "-qq", "wrk"], ["apt-get", "update", "-qq"],
                    ["apt-get", "install", "-y", "-qq", "wrk"]):
        try:
            subprocess.run(command, env=env, capture_output=True, timeout=300, check=False)
        except (OSError, subprocess.TimeoutExpired):
            break
        path = shutil.which("wrk")
        if path:
            return path, f"wrk ({path}, installed with apt-get)"
    return None, "wrk could not be installed with apt-get"


_UNITS_MS = {"us": 1e-3, "ms": 1.0, "s": 1e3, "m": 60e3}


def _duration_ms(text: str) -> float:
    match = re.fullmatch(r"([0-9.]+)(us|ms|s|m)", text.strip())
    if not match:
        raise ValueError(f"cannot read wrk duration {text!r}")
    return float(match.group(1)) * _UNITS_MS[match.group(2)]


def run_wrk(wrk: str, url: str, duration_s: float, connections: int, body: bytes | None = None) -> LoadResult:
    """One wrk run (one thread: the server has the other core), POSTing ``body`` when given."""
    with tempfile.TemporaryDirectory() as tmp:
        command = [wrk, "-t1", f"-c{connections}", f"-d{duration_s:g}s", "--latency", url]
        if body is not None:
            body_path = os.path.join(tmp, "body.json")
            with open(body_path, "wb") as f:
                f.write(body)
            script = os.path.join(tmp, "post.lua")
            with open(script, "w") as f:
                f.write('wrk.method = "POST"\nwrk.headers["Content-Type"] = "application/json"\n'
                        f'local f = io.open("{body_path}", "rb")\nwrk.body = f:read("*a")\nf:close()\n')
            command[1:1] = ["-s", script]
        out = subprocess.run(command, capture_output=True, text=True, timeout=duration_s + 60, check=True).stdout
    rps = float(re.search(r"Requests/sec:\s+([0-9.]+)", out).group(1))
    p50 = _duration_ms(re.search(r"^\s+50%\s+(\S+)", out, re.M).group(1))
    p99 = _duration_ms(re.search(r"^\s+99%\s+(\S+)", out, re.M).group(1))
    requests = int(re.search(r"(\d+) requests in", out).group(1))
    failures = 0
    non_2xx = re.search(r"Non-2xx or 3xx responses:\s+(\d+)", out)
    if non_2xx:
        failures += int(non_2xx.group(1))
    socket_errors = re.search(r"Socket errors: connect (\d+), read (\d+), write (\d+), timeout (\d+)", out)
    if socket_errors:
        failures += sum(int(g) for g in socket_errors.groups())
    return LoadResult(rps, p50, p99, requests, failures, "wrk")


async def _client(host, port, request: bytes, deadline: float, latencies: list, failures: list) -> None:
    reader, writer = await asyncio.open_connection(host, port)
    try:
        while time.perf_counter() < deadline:
            started = time.perf_counter()
            writer.write(request)
            head = await reader.readuntil(b"\r\n\r\n")
            status = int(head.split(b" ", 2)[1])
            length = re.search(rb"(?i)content-length:\s*(\d+)", head)
            await reader.readexactly(int(length.group(1)) if length else 0)
            latencies.append(time.perf_counter() - started)
            if not 200 <= status < 300:
                failures.append(status)
    finally:
        writer.close()


def run_python(url: str, duration_s: float, connections: int, body: bytes | None = None) -> LoadResult:
    """The asyncio fallback: raw HTTP/1.1 keep-alive clients (slower than wrk; the client shares a core)."""
    parts = urlsplit(url)
    host, port = parts.hostname, parts.port or 80
    method = "POST" if body is not None else "GET"
    head = (f"{method} {parts.path or '/'} HTTP/1.1\r\nHost: {host}:{port}\r\n"
            + (f"Content-Type: application/json\r\nContent-Length: {len(body)}\r\n" if body is not None else "")
            + "\r\n").encode()
    request = head + (body or b"")
    latencies: list[float] = []
    failures: list[int] = []

    async def run():
        deadline = time.perf_counter() + duration_s
        await asyncio.gather(*(_client(host, port, request, deadline, latencies, failures)
                               for _ in range(connections)))

    started = time.perf_counter()
    asyncio.run(run())
    elapsed = time.perf_counter() - started
    ms = np.array(latencies) * 1e3
    return LoadResult(len(latencies) / elapsed, float(np.percentile(ms, 50)), float(np.percentile(ms, 99)),
                      len(latencies), len(failures), "python-asyncio")


class LoadGenerator:
    """wrk when available, else the asyncio fallback; ``description`` says which and why."""

    def __init__(self, install: bool = True):
        self.wrk, self.description = find_wrk(install)
        if self.wrk is None:
            self.description += "; using the Python asyncio load generator instead"

    def run(self, url: str, duration_s: float, connections: int, body: bytes | None = None) -> LoadResult:
        if self.wrk:
            return run_wrk(self.wrk, url, duration_s, connections, body)
        return run_python(url, duration_s, connections, body)
