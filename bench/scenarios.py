"""Request bodies for the benchmarks: four-station bearing fixes around a target.

Everything is generated from a seeded ``numpy.random.Generator`` so a run is
repeatable; values are exact bearings of a known target plus Gaussian noise.
"""

from __future__ import annotations

import math

import numpy as np

from core import geodesy

#: Angle noise of every generated bearing (degrees).
SIGMA_DEG = 0.5


#: Relative sigma of the range a request carries with ``with_range``.
RANGE_SIGMA = 0.01
#: The methods that need a range beside the bearings, and those that locate from azimuths only (their
#: problems carry the target altitude).
NEEDS_RANGE = ("angle_range",)
AZIMUTH_ONLY = ("tls", "ctls")


def four_station_requests(count: int, rng: np.random.Generator, method: str = "ml",
                          with_range: bool | None = None, with_altitude: bool | None = None,
                          stated_sigma_deg: float = SIGMA_DEG) -> list[dict]:
    """``count`` FixRequest bodies: four stations within ~40 km, a target 20-60 km away.

    Parameters
    ----------
    count : int
    rng : numpy.random.Generator
    method : str
    with_range : bool, optional
        Add a range from the first station (sigma ``RANGE_SIGMA`` of it); default: when ``method`` needs one
        (:data:`NEEDS_RANGE`).
    with_altitude : bool, optional
        Give the target's true altitude (``constraints.altitude_m``); default: for the azimuth-only methods
        (:data:`AZIMUTH_ONLY`).
    stated_sigma_deg : float
        The bearings' sigmas as the requests state them (the noise drawn is :data:`SIGMA_DEG` whatever this
        says: a smaller value makes every fit's chi-square implausible, as misstated sigmas do).

    Returns
    -------
    list of dict
        JSON-ready FixRequest bodies (frame ``wgs84``, bearings with elevation).
    """
    with_range = method in NEEDS_RANGE if with_range is None else with_range
    with_altitude = method in AZIMUTH_ONLY if with_altitude is None else with_altitude
    base_lat = np.radians(34.0 + rng.uniform(-1.0, 1.0, count))
    base_lon = np.radians(108.0 + rng.uniform(-1.0, 1.0, count))
    offsets = rng.uniform(-0.2, 0.2, (count, 4, 2))
    station_lat = base_lat[:, None] + np.radians(offsets[..., 0])
    station_lon = base_lon[:, None] + np.radians(offsets[..., 1])
    station_alt = rng.uniform(0.0, 500.0, (count, 4))
    bearing = rng.uniform(0.0, 2 * np.pi, count)
    distance = rng.uniform(20e3, 60e3, count)
    target_lat = base_lat + distance * np.cos(bearing) / 6.371e6
    target_lon = base_lon + distance * np.sin(bearing) / (6.371e6 * np.cos(base_lat))
    target_alt = rng.uniform(1e3, 10e3, count)
    seen = geodesy.geodetic_to_enu(target_lat[:, None], target_lon[:, None], target_alt[:, None],
                                   station_lat, station_lon, station_alt)
    sigma = np.radians(SIGMA_DEG)
    azimuth = np.degrees(np.mod(np.arctan2(seen[..., 0], seen[..., 1]) + sigma * rng.standard_normal((count, 4)),
                                2 * np.pi))
    elevation = np.degrees(np.arctan2(seen[..., 2], np.hypot(seen[..., 0], seen[..., 1]))
                           + sigma * rng.standard_normal((count, 4)))
    ranges = np.linalg.norm(seen[:, 0], axis=-1)
    ranges = ranges * (1 + RANGE_SIGMA * rng.standard_normal(count)) if with_range else ranges
    requests = []
    for b in range(count):
        stations, measurements = [], []
        for s in range(4):
            sid = f"rx-{s + 1}"
            stations.append({"id": sid, "position": {"lat_deg": math.degrees(station_lat[b, s]),
                                                     "lon_deg": math.degrees(station_lon[b, s]),
                                                     "alt_m": float(station_alt[b, s])}})
            measurements.append({"type": "bearing", "station_id": sid, "azimuth_deg": float(azimuth[b, s]),
                                 "elevation_deg": float(elevation[b, s]), "sigma_azimuth_deg": stated_sigma_deg,
                                 "sigma_elevation_deg": stated_sigma_deg})
        if with_range:
            measurements.append({"type": "range", "station_id": "rx-1", "range_m": float(ranges[b]),
                                 "sigma_m": RANGE_SIGMA * float(ranges[b])})
        request = {"frame": "wgs84", "stations": stations, "measurements": measurements, "method": method}
        if with_altitude:
            request["constraints"] = {"altitude_m": float(target_alt[b])}
        requests.append(request)
    return requests


def largest_fix_request(method: str = "auto", seed: int = 7) -> dict:
    """The largest fix the schema and the default ``max_fix_cost`` allow: 256 stations x 1,024 bearings.

    The stations stand on a ring of about 55 km around the target, four noisy bearings (azimuth and
    elevation) each.

    Parameters
    ----------
    method : str
    seed : int

    Returns
    -------
    dict
        A JSON-ready FixRequest body (frame ``wgs84``).
    """
    rng = np.random.default_rng(seed)
    stations_n, per_station = 256, 4
    target = np.radians(35.0), np.radians(110.0), 3000.0
    ring = 2 * np.pi * np.arange(stations_n) / stations_n
    station_lat = target[0] + np.radians(0.5) * np.cos(ring)
    station_lon = target[1] + np.radians(0.6) * np.sin(ring)
    station_alt = np.full(stations_n, 100.0)
    seen = geodesy.geodetic_to_enu(target[0], target[1], target[2], station_lat, station_lon, station_alt)
    azimuth = np.arctan2(seen[..., 0], seen[..., 1])[:, None]
    elevation = np.arctan2(seen[..., 2], np.hypot(seen[..., 0], seen[..., 1]))[:, None]
    sigma = np.radians(SIGMA_DEG)
    azimuth_deg = np.degrees(np.mod(azimuth + sigma * rng.standard_normal((stations_n, per_station)), 2 * np.pi))
    elevation_deg = np.degrees(elevation + sigma * rng.standard_normal((stations_n, per_station)))
    stations = [{"id": f"s{s}", "position": {"lat_deg": math.degrees(station_lat[s]),
                                             "lon_deg": math.degrees(station_lon[s]), "alt_m": 100.0}}
                for s in range(stations_n)]
    measurements = [{"type": "bearing", "station_id": f"s{s}", "azimuth_deg": float(azimuth_deg[s, k]),
                     "elevation_deg": float(elevation_deg[s, k]), "sigma_azimuth_deg": SIGMA_DEG,
                     "sigma_elevation_deg": SIGMA_DEG}
                    for s in range(stations_n) for k in range(per_station)]
    return {"frame": "wgs84", "stations": stations, "measurements": measurements, "method": method}
