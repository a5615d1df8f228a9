"""Seconds from ``passive-locator serve`` to its first ``GET /healthz`` 200, cold and warm.

Cold: an empty ``NUMBA_CACHE_DIR`` (every kernel compiles before the port opens, as in a container whose
image cache is hidden or was built on another CPU model). Warm: the same directory again, now filled (as in
the image). Each start is a fresh process; the figures depend on how many cores the machine gives it.

    .venv/bin/python scripts/measure_start.py [--runs 1]
"""

from __future__ import annotations

import argparse
import os
import pathlib
import socket
import subprocess
import sys
import tempfile
import time
import urllib.request

REPO = pathlib.Path(__file__).resolve().parents[1]


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def time_to_healthz(cache_dir: str, limit_s: float = 900.0) -> float:
    """Seconds from starting the server to its first /healthz 200 (the process is stopped after)."""
    port = _free_port()
    with tempfile.TemporaryDirectory() as store:
        env = {**os.environ, "NUMBA_CACHE_DIR": cache_dir, "PASSIVE_LOCATOR_STORE": f"sqlite:///{store}/s.db",
               "PYTHONPATH": str(REPO)}
        start = time.monotonic()
        server = subprocess.Popen([sys.executable, "-m", "service.cli", "serve", "--port", str(port),
                                   "--log-level", "warning"], cwd=REPO, env=env, stdout=subprocess.DEVNULL)
        try:
            while time.monotonic() - start < limit_s:
                if server.poll() is not None:
                    raise SystemExit(f"the server exited with status {server.returncode}")
                try:
                    with urllib.request.urlopen(f"http://127.0.0.1:{port}/healthz", timeout=1) as answer:
                        if answer.status == 200:
                            return time.monotonic() - start
                except OSError:
                    time.sleep(0.05)
            raise SystemExit(f"no /healthz 200 within {limit_s:.0f} s")
        finally:
            server.terminate()
            server.wait(timeout=30)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--runs", type=int, default=1, help="cold/warm pairs, each with a new empty cache")
    args = parser.parse_args()
    print(f"cores: {os.cpu_count()}, load average at start: {os.getloadavg()[0]:.2f}", flush=True)
    for run in range(args.runs):
        with tempfile.TemporaryDirectory(prefix="numba-cache-") as cache:
            cold = time_to_healthz(cache)
            warm = time_to_healthz(cache)
        print(f"run {run + 1}: cold {cold:.1f} s, warm {warm:.1f} s (load average {os.getloadavg()[0]:.2f})",
              flush=True)


if __name__ == "__main__":
    main()
