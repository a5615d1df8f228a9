"""``python -m bench.inline_threshold``: what one fix costs the thread that solves it, by its cost estimate.

``POST /v1/fixes`` solves a fix on the event loop when its cost estimate
(:func:`service.limits.body_fix_cost`) is at most ``inline_fix_cost``, and in
the worker pool above it. This prints, for fixes of growing size (stations on
a ring, bearings with elevation, methods ``ml``, ``los_intersection`` and
``ml`` with outlier exclusion), the cost estimate and the thread CPU time of
:func:`service.fixes.pipeline.fix_results` on the body alone (read, solve, write:
what the loop would run), median of ``--repeat`` calls after a warm-up, so
the threshold can be set where a fix holds the loop for a few hundred
microseconds.

Usage: ``python -m bench.inline_threshold [--repeat N]``.
"""

from __future__ import annotations

import argparse
import time

import numpy as np

from bench.scenarios import largest_fix_request
from service.limits import body_fix_cost
from service.fixes.pipeline import fix_results

#: (stations, bearings per station) of the fixes measured.
SHAPES = ((2, 1), (3, 1), (4, 1), (4, 2), (6, 2), (8, 2), (8, 4), (12, 4), (16, 4), (24, 4), (32, 4), (48, 4))


def sized_request(stations: int, per_station: int, method: str = "ml", exclude: bool = False) -> dict:
    """``stations`` of :func:`bench.scenarios.largest_fix_request`'s ring (evenly spaced), ``per_station``
    bearings each."""
    full = largest_fix_request(method)
    picked = [full["stations"][i] for i in np.linspace(0, 255, stations).astype(int)]
    ids = {s["id"] for s in picked}
    taken: dict[str, int] = {}
    measurements = []
    for m in full["measurements"]:
        if m["station_id"] in ids and taken.get(m["station_id"], 0) < per_station:
            taken[m["station_id"]] = taken.get(m["station_id"], 0) + 1
            measurements.append(m)
    body = {**full, "stations": picked, "measurements": measurements}
    if exclude:
        body["options"] = {"outliers": "exclude"}
    return body


def thread_us(body: dict, repeat: int) -> float:
    """Median thread CPU time (us) of ``fix_results([body])``, after a warm-up."""
    for _ in range(5):
        fix_results([body])
    times = []
    for _ in range(repeat):
        t = time.thread_time()
        fix_results([body])
        times.append(time.thread_time() - t)
    return float(np.median(times)) * 1e6


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(prog="python -m bench.inline_threshold", description=__doc__.splitlines()[0])
    parser.add_argument("--repeat", type=int, default=200)
    args = parser.parse_args(argv)
    print("| method | stations x bearings | cost estimate | thread CPU us | us per unit |")
    print("|---|---|---|---|---|")
    for method, exclude in (("ml", False), ("los_intersection", False), ("ml", True)):
        for stations, per_station in SHAPES:
            body = sized_request(stations, per_station, method, exclude)
            cost = body_fix_cost(body)
            us = thread_us(body, max(10, args.repeat // max(1, cost // 64)))
            name = method + (" exclude" if exclude else "")
            print(f"| {name} | {stations} x {stations * per_station} | {cost:,} | {us:,.0f} | {us / cost:.2f} |",
                  flush=True)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
