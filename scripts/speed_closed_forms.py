"""Core speed of the batched closed forms over 10,000 four-station problems (fixes/s).

Usage: ``.venv/bin/python -m scripts.speed_closed_forms [methods...] [--size N] [--repeats R]``

Each method gets the measurement mix it needs: bearings with elevation from four
wgs84 stations (``los_intersection``, ``taylor_wls``), plus a range at every
station (``angle_range``). The timed call is ``spec.solve_batch`` (estimator and
finisher), best of the repeats; the estimator alone is timed as well.
"""

from __future__ import annotations

import argparse
import dataclasses
import time

import numpy as np

from core import geodesy
from core.problem_batch import ProblemBatch, build_problem_batch
from core.estimators import SolveOptions
from core.estimators.base import get_estimator
from core.measurements import Kind, MeasurementModel

SIGMA_RAD = np.radians(0.5)
SIGMA_RANGE_M = 100.0
MIXES = {"los_intersection": False, "taylor_wls": False, "angle_range": True, "ml": False, "eove": False}


def four_station_batch(size: int, with_ranges: bool, seed: int = 7) -> ProblemBatch:
    """``size`` problems: four stations within ~40 km, a target 20-60 km away at 1-10 km height, noisy."""
    rng = np.random.default_rng(seed)
    base_lat = np.radians(34.0 + rng.uniform(-1.0, 1.0, size))
    base_lon = np.radians(108.0 + rng.uniform(-1.0, 1.0, size))
    offsets = np.radians(rng.uniform(-0.2, 0.2, (size, 4, 2)))
    coords = np.stack([base_lat[:, None] + offsets[..., 0], base_lon[:, None] + offsets[..., 1],
                       rng.uniform(0.0, 500.0, (size, 4))], axis=-1)
    direction = rng.uniform(0.0, 2 * np.pi, size)
    distance = rng.uniform(20e3, 60e3, size)
    target = np.stack([base_lat + distance * np.cos(direction) / 6.371e6,
                       base_lon + distance * np.sin(direction) / (6.371e6 * np.cos(base_lat)),
                       rng.uniform(1e3, 10e3, size)], axis=-1)
    kinds = [Kind.AZIMUTH, Kind.ELEVATION] * 4 + ([Kind.RANGE] * 4 if with_ranges else [])
    station = [0, 0, 1, 1, 2, 2, 3, 3] + ([0, 1, 2, 3] if with_ranges else [])
    bearing = [0, 0, 1, 1, 2, 2, 3, 3] + ([-1] * 4 if with_ranges else [])
    source = [0, 0, 1, 1, 2, 2, 3, 3] + ([4, 5, 6, 7] if with_ranges else [])
    sigma = [SIGMA_RAD] * 8 + ([SIGMA_RANGE_M] * 4 if with_ranges else [])
    m = len(kinds)

    def tiled(row):
        return np.tile(np.asarray(row), size)

    batch = build_problem_batch(
        np.full(size, 4), [("a", "b", "c", "d")] * size, coords.reshape(-1, 3), np.ones(size, bool),
        np.full((size, 3), np.nan), np.full(size, m), tiled(np.array(kinds, dtype=np.int8)), tiled(station),
        np.zeros(size * m), tiled(sigma), tiled(bearing), tiled(source), np.full(size, np.nan),
        np.full((size, 3), np.nan), np.zeros(size, bool))
    target_enu = geodesy.geodetic_to_enu(target[:, 0], target[:, 1], target[:, 2],
                                         batch.origin[:, 0], batch.origin[:, 1], batch.origin[:, 2])
    stations, rotations = batch.measurement_stations()
    true, _ = MeasurementModel(stations, rotations, batch.kinds).predict(target_enu, np.zeros(size))
    return dataclasses.replace(batch, values=true + rng.standard_normal(true.shape) * batch.sigmas)


def best_of(repeats: int, call) -> float:
    times = []
    for _ in range(repeats):
        started = time.perf_counter()
        call()
        times.append(time.perf_counter() - started)
    return min(times)


def main() -> None:
    parser = argparse.ArgumentParser()
    parser.add_argument("methods", nargs="*", default=list(MIXES))
    parser.add_argument("--size", type=int, default=10_000)
    parser.add_argument("--repeats", type=int, default=3)
    args = parser.parse_args()
    options = SolveOptions()
    for name in args.methods:
        batch = four_station_batch(args.size, MIXES[name])
        spec = get_estimator(name)
        fixes = spec.solve_batch(batch, options)
        whole = best_of(args.repeats, lambda: spec.solve_batch(dataclasses.replace(batch), options))
        alone = best_of(args.repeats, lambda: spec.estimate(dataclasses.replace(batch), options))
        print(f"{name:17s} {args.size} problems: solve_batch {whole:7.3f} s = {args.size / whole:9.0f} fixes/s; "
              f"estimate only {alone:7.3f} s = {args.size / alone:9.0f} /s; {len(fixes.errors)} errors")


if __name__ == "__main__":
    main()
