"""A uvicorn process (one worker) serving the benchmark app on a free loopback port."""

from __future__ import annotations

import http.client
import os
import socket
import subprocess
import sys
import tempfile
import time
from contextlib import contextmanager


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


@contextmanager
def serve(store: str | None = None, extra_env: dict | None = None):
    """Run ``bench.app`` under uvicorn (1 worker, loopback) and yield its base URL.

    Parameters
    ----------
    store : str, optional
        Session store URL; default a fresh SQLite file in a temporary directory.
    extra_env : dict, optional
    """
    with tempfile.TemporaryDirectory() as tmp:
        port = _free_port()
        env = {**os.environ, "PASSIVE_LOCATOR_STORE": store or f"sqlite:///{tmp}/sessions.db",
               "PASSIVE_LOCATOR_LOG_LEVEL": "warning", **(extra_env or {})}
        root = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
        command = [sys.executable, "-m", "uvicorn", "--factory", "bench.app:app_from_environment",
                   "--host", "127.0.0.1", "--port", str(port), "--workers", "1",
                   "--log-level", "warning", "--no-access-log"]
        log = open(os.path.join(tmp, "server.log"), "w+")
        process = subprocess.Popen(command, cwd=root, env=env, stdout=log, stderr=subprocess.STDOUT)
        try:
            deadline = time.monotonic() + 60
            while True:
                if process.poll() is not None:
                    log.seek(0)
                    raise RuntimeError(f"the server exited: {log.read()[-2000:]}")
                try:
                    connection = http.client.HTTPConnection("127.0.0.1", port, timeout=5)
                    connection.request("GET", "/healthz")
                    if connection.getresponse().status == 200:
                        connection.close()
                        break
                except OSError:
                    if time.monotonic() > deadline:
                        raise
                    time.sleep(0.2)
            yield f"http://127.0.0.1:{port}"
        finally:
            process.terminate()
            try:
                process.wait(timeout=15)
            except subprocess.TimeoutExpired:
                process.kill()
                process.wait()
            log.close()
