"""Time and peak memory of the largest fix the schema allows (256 stations x 1024 bearings with elevation),
through the app in process: ``python scripts/measure_largest_fix.py [stations] [measurements]``.

Issue 10's budget: within 3 s and 300 MB above the idle process.
"""

from __future__ import annotations

import math
import pathlib
import resource
import sys
import time

import numpy as np

sys.path.insert(0, str(pathlib.Path(__file__).resolve().parents[1]))


def request(stations: int, measurements: int) -> dict:
    rng = np.random.default_rng(1)
    east_north = rng.uniform(-50_000.0, 50_000.0, (stations, 2))
    target = np.array([1000.0, 2000.0, 3000.0])
    body = {"frame": "local", "measurements": [],
            "stations": [{"id": f"s{i}", "position": {"east_m": x, "north_m": y, "up_m": 0.0}}
                         for i, (x, y) in enumerate(east_north.tolist())]}
    for j in range(measurements):
        d = target - np.array([*east_north[j % stations], 0.0])
        body["measurements"].append({"type": "bearing", "station_id": f"s{j % stations}",
                                     "azimuth_deg": math.degrees(math.atan2(d[0], d[1])),
                                     "elevation_deg": math.degrees(math.atan2(d[2], math.hypot(d[0], d[1]))),
                                     "sigma_azimuth_deg": 1.0, "sigma_elevation_deg": 1.0})
    return body


def main() -> None:
    from fastapi.testclient import TestClient

    from service.app import create_app
    from service.schemas import MAX_FIX_MEASUREMENTS
    from service.settings import Settings

    stations = int(sys.argv[1]) if len(sys.argv) > 1 else 256
    measurements = int(sys.argv[2]) if len(sys.argv) > 2 else MAX_FIX_MEASUREMENTS
    body = request(stations, measurements)
    with TestClient(create_app(Settings(store="sqlite:///:memory:", log_level="warning",
                                        max_fix_cost=stations * measurements))) as client:
        client.post("/v1/fixes", json=request(4, 8))  # warm: imports, first-call caches
        idle_kib = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss
        started = time.perf_counter()
        response = client.post("/v1/fixes", json=body)
        seconds = time.perf_counter() - started
        peak_mb = (resource.getrusage(resource.RUSAGE_SELF).ru_maxrss - idle_kib) / 1024
    print(f"{stations} stations x {measurements} bearings: HTTP {response.status_code}, {seconds:.2f} s, "
          f"peak +{peak_mb:.0f} MB")


if __name__ == "__main__":
    main()
