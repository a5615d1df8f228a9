"""Fixtures: a real app per test through TestClient, and scene builders."""

from __future__ import annotations

import math

import numpy as np
import pytest
from fastapi.testclient import TestClient

from core import geodesy
from service.app import create_app
from service.settings import Settings


@pytest.fixture
def make_client(tmp_path):
    clients = []

    def make(**overrides) -> TestClient:
        settings = Settings(store=f"sqlite:///{tmp_path}/sessions-{len(clients)}.db", **overrides)
        client = TestClient(create_app(settings))
        client.__enter__()
        clients.append(client)
        return client

    yield make
    for client in clients:
        client.__exit__(None, None, None)


@pytest.fixture
def client(make_client) -> TestClient:
    return make_client()


def look_angles_deg(station: dict, target: dict) -> tuple[float, float, float]:
    """Exact azimuth, elevation (deg) and slant range (m) from a geodetic station to a geodetic target."""
    s = [math.radians(station["lat_deg"]), math.radians(station["lon_deg"]), station["alt_m"]]
    t = [math.radians(target["lat_deg"]), math.radians(target["lon_deg"]), target["alt_m"]]
    enu = geodesy.geodetic_to_enu(*t, *s)
    az = math.degrees(math.atan2(enu[0], enu[1])) % 360.0
    el = math.degrees(math.atan2(enu[2], math.hypot(enu[0], enu[1])))
    return az, el, float(np.linalg.norm(enu))


def bearing_request(stations: dict, target: dict, sigma_deg: float = 1.0, **extra) -> dict:
    measurements = []
    for sid, pos in stations.items():
        az, el, _ = look_angles_deg(pos, target)
        measurements.append({"type": "bearing", "station_id": sid, "azimuth_deg": az, "elevation_deg": el,
                             "sigma_azimuth_deg": sigma_deg, "sigma_elevation_deg": sigma_deg})
    return {"frame": "wgs84", "stations": [{"id": k, "position": dict(v)} for k, v in stations.items()],
            "measurements": measurements, **extra}


STATIONS_300KM = {
    "rx-1": {"lat_deg": 34.0, "lon_deg": 108.5, "alt_m": 300.0},
    "rx-2": {"lat_deg": 36.2, "lon_deg": 109.0, "alt_m": 500.0},
    "rx-3": {"lat_deg": 35.1, "lon_deg": 112.5, "alt_m": 100.0},
    "rx-4": {"lat_deg": 33.9, "lon_deg": 111.2, "alt_m": 800.0},
}
TARGET = {"lat_deg": 35.0, "lon_deg": 110.0, "alt_m": 9000.0}
