"""Network sessions at the API: create bodies and reports of a small direction-finding network."""

from __future__ import annotations

import math

import numpy as np

from core import geodesy

#: Three direction finders about 30 km apart (geodetic), and the vehicle's start.
DF_STATIONS = {
    "df-1": {"lat_deg": 34.00, "lon_deg": 108.90, "alt_m": 400.0},
    "df-2": {"lat_deg": 34.27, "lon_deg": 108.95, "alt_m": 450.0},
    "df-3": {"lat_deg": 34.12, "lon_deg": 109.25, "alt_m": 500.0},
}
START = {"lat_deg": 34.13, "lon_deg": 109.03, "alt_m": 420.0}
SIGMA_DEG = 1.0


def create_body(**changes) -> dict:
    body = {"frame": "wgs84", "stations": [{"id": k, "position": dict(v)} for k, v in DF_STATIONS.items()],
            "process_noise": {"accel_sigma_mps2": 0.5}, "reorder_window_s": 2.0, "ttl_s": 3600.0}
    body.update(changes)
    return body


def truth_at(time_s: float, velocity_enu_mps=(15.0, 10.0, 0.0)) -> dict:
    """The vehicle's geodetic position at ``time_s``: constant velocity in the ENU axes at its start."""
    lat0, lon0 = math.radians(START["lat_deg"]), math.radians(START["lon_deg"])
    enu = np.asarray(velocity_enu_mps, dtype=float) * time_s
    lat, lon, alt = geodesy.enu_to_geodetic(enu, lat0, lon0, START["alt_m"])
    return {"lat_deg": math.degrees(float(lat)), "lon_deg": math.degrees(float(lon)), "alt_m": float(alt)}


def bearing(station: dict, target: dict, rng: np.random.Generator | None = None) -> dict:
    """A bearing (azimuth and elevation, 1 deg) from a geodetic station to a geodetic target, noisy with ``rng``."""
    s = np.radians([station["lat_deg"], station["lon_deg"]])
    t = np.radians([target["lat_deg"], target["lon_deg"]])
    enu = geodesy.geodetic_to_enu(t[0], t[1], target["alt_m"], s[0], s[1], station["alt_m"])
    az = math.degrees(math.atan2(enu[0], enu[1]))
    el = math.degrees(math.atan2(enu[2], math.hypot(enu[0], enu[1])))
    if rng is not None:
        az, el = az + SIGMA_DEG * rng.standard_normal(), el + SIGMA_DEG * rng.standard_normal()
    return {"type": "bearing", "azimuth_deg": az % 360.0, "elevation_deg": el, "sigma_azimuth_deg": SIGMA_DEG,
            "sigma_elevation_deg": SIGMA_DEG}


def df_reports(count: int, seed: int = 1, first_seq: int = 1, interval_s: float = 1.0) -> list[dict]:
    """``count`` reports, one station at a time in turn, ``interval_s`` apart, each a bearing with its noise."""
    rng = np.random.default_rng(seed)
    names = list(DF_STATIONS)
    reports = []
    for k in range(count):
        time_s = 100.0 + k * interval_s
        station = names[k % len(names)]
        measurement = {**bearing(DF_STATIONS[station], truth_at(time_s - 100.0), rng), "station_id": station}
        reports.append({"seq": first_seq + k, "time_s": time_s, "measurements": [measurement]})
    return reports
