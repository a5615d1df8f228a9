"""``python -m bench.largest_fix``: seconds per method for the largest allowed fix over HTTP (target: within 3 s).

One uvicorn worker on loopback (:func:`bench.server.serve`); per method one warm-up request, then the median
of ``--repeats`` requests of :func:`bench.scenarios.largest_fix_request` (256 stations x 1,024 bearings).
A small four-station fix is timed in the same run as the yardstick (the machine is shared: compare ratios).
Peak memory of the same request is a test (``tests/service/test_faults.py``).

Usage: ``python -m bench.largest_fix [--methods ml,eove] [--repeats 3]``.
"""

from __future__ import annotations

import argparse
import statistics
import time

import httpx
import numpy as np
import orjson

from bench.scenarios import four_station_requests, largest_fix_request
from bench.server import serve
from service.schemas import METHODS


def _seconds(client: httpx.Client, url: str, body: bytes, repeats: int) -> tuple[float, int]:
    client.post(url, content=body)
    times, status = [], 0
    for _ in range(repeats):
        started = time.perf_counter()
        status = client.post(url, content=body).status_code
        times.append(time.perf_counter() - started)
    return statistics.median(times), status


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(prog="python -m bench.largest_fix", description=__doc__.splitlines()[0])
    parser.add_argument("--methods", default=",".join(sorted(METHODS)))
    parser.add_argument("--repeats", type=int, default=3)
    args = parser.parse_args(argv)
    with serve() as base, httpx.Client(timeout=120, headers={"content-type": "application/json"}) as client:
        url = f"{base}/v1/fixes"
        small = orjson.dumps(four_station_requests(1, np.random.default_rng(1))[0])
        yardstick, _ = _seconds(client, url, small, args.repeats)
        print(f"four-station fix: {yardstick * 1e3:.1f} ms")
        print(f"{'method':<18} {'status':>6} {'seconds':>8} {'x small fix':>12}")
        for method in args.methods.split(","):
            seconds, status = _seconds(client, url, orjson.dumps(largest_fix_request(method)), args.repeats)
            print(f"{method:<18} {status:>6} {seconds:>8.2f} {seconds / yardstick:>12.0f}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
