"""The papers' scenarios and the generic scenes: one definition for the tests, the scripts and the CLI.

Papers 000 and 004 and the generic scenes are :class:`Scene` objects; paper
002's and 003's geometries are problems (:func:`paper_002_problem`,
:func:`paper_003_problem`); paper 001's emitter is
:func:`core.simulation.emitter.paper_001_scenario` with its filter settings
in :func:`core.simulation.tracking.paper_config`.

A :class:`Scene` is a geometry (stations, a target, what each station
measures and how well); :meth:`Scene.measurements` draws one set of
measurements from it (noise-free without an ``rng``) and :func:`build`
turns measurements into a :class:`~core.problem.frame.Problem`, so that the same
noisy draw can be re-ordered or moved before it is solved.
"""

from __future__ import annotations

from dataclasses import dataclass, replace

import numpy as np

from core.problem.build import Bearing, Range, build_problem
from core.problem.frame import GeodeticPoint, LocalPoint, Problem
from core.simulation.measurements import true_values

DEG = np.pi / 180.0


@dataclass(frozen=True)
class Sensor:
    """What one line of sight measures: angles (and optionally a range) with their sigmas."""

    station_id: str
    sigma_azimuth_rad: float
    sigma_elevation_rad: float | None = None
    sigma_range_m: float | None = None


@dataclass(frozen=True)
class Scene:
    """A geometry: stations, the target, and the sensors (one line of sight each)."""

    name: str
    stations: tuple
    sensors: tuple
    target: GeodeticPoint | LocalPoint
    altitude_m: float | None = None
    sigma_known: bool = True

    def template(self) -> Problem:
        return build(self, self._measurements(np.zeros(self._size())))

    def target_enu_m(self, problem: Problem | None = None) -> np.ndarray:
        problem = problem or self.template()
        t = self.target
        if isinstance(t, GeodeticPoint):
            return problem.frame.from_geodetic(t.lat_rad, t.lon_rad, t.alt_m)
        return np.array([t.east_m, t.north_m, t.up_m])

    def true_values(self) -> np.ndarray:
        """Noise-free values ``(M,)`` in measurement order (rad, m)."""
        template = self.template()
        return true_values(template, self.target_enu_m(template))

    def measurements(self, rng: np.random.Generator | None = None) -> list:
        """One draw of the measurements (noise-free without ``rng``)."""
        values = self.true_values()
        if rng is not None:
            values = values + rng.standard_normal(values.size) * self.sigmas()
        return self._measurements(values)

    def problem(self, rng: np.random.Generator | None = None) -> Problem:
        return build(self, self.measurements(rng))

    def sigmas(self) -> np.ndarray:
        out = []
        for s in self.sensors:
            out.append(s.sigma_azimuth_rad)
            if s.sigma_elevation_rad is not None:
                out.append(s.sigma_elevation_rad)
            if s.sigma_range_m is not None:
                out.append(s.sigma_range_m)
        return np.array(out)

    def _size(self) -> int:
        return self.sigmas().size

    def _measurements(self, values) -> list:
        out, i = [], 0
        for s in self.sensors:
            az = values[i]
            i += 1
            el = None
            if s.sigma_elevation_rad is not None:
                el = values[i]
                i += 1
            out.append(Bearing(s.station_id, float(az), None if el is None else float(el),
                               s.sigma_azimuth_rad if self.sigma_known else None, s.sigma_elevation_rad))
            if s.sigma_range_m is not None:
                out.append(Range(s.station_id, float(abs(values[i])), s.sigma_range_m))
                i += 1
        return out


def build(scene: Scene, measurements, station_order=None, measurement_order=None) -> Problem:
    """A problem from a scene's stations and given measurements, optionally re-ordered."""
    stations = list(scene.stations)
    if station_order is not None:
        stations = [stations[i] for i in station_order]
    measurements = list(measurements)
    if measurement_order is not None:
        measurements = [measurements[i] for i in measurement_order]
    return build_problem(stations, measurements, altitude_m=scene.altitude_m, require_sigmas=scene.sigma_known)


def geodetic(lat_deg, lon_deg, alt_m) -> GeodeticPoint:
    return GeodeticPoint(lat_deg * DEG, lon_deg * DEG, alt_m)


def shifted(scene: Scene, lon_deg: float) -> Scene:
    """The scene moved east by a longitude shift (the geometry is unchanged: a rotation about the pole)."""
    def move(p):
        return GeodeticPoint(p.lat_rad, p.lon_rad + lon_deg * DEG, p.alt_m)

    return replace(scene, stations=tuple((i, move(p)) for i, p in scene.stations), target=move(scene.target))


def translated(scene: Scene, east_m: float, north_m: float) -> Scene:
    """A local-frame scene translated in its plane."""
    def move(p):
        return LocalPoint(p.east_m + east_m, p.north_m + north_m, p.up_m)

    return replace(scene, stations=tuple((i, move(p)) for i, p in scene.stations), target=move(scene.target))


GENERIC_STATIONS = (
    ("rx-a", geodetic(34.20, 108.70, 400.0)),
    ("rx-b", geodetic(34.85, 108.80, 1000.0)),
    ("rx-c", geodetic(34.60, 109.25, 150.0)),
    ("rx-d", geodetic(34.30, 109.15, 700.0)),
)
GENERIC_TARGET = geodetic(34.52, 108.95, 6000.0)


def generic_3d(sigma_deg: float = 1.0) -> Scene:
    """Four stations 30-45 km around a target at 6 km, azimuth and elevation at each."""
    sensors = tuple(Sensor(i, sigma_deg * DEG, sigma_deg * DEG) for i, _ in GENERIC_STATIONS)
    return Scene(f"4 stations, {sigma_deg:g} deg", GENERIC_STATIONS, sensors, GENERIC_TARGET)


def generic_azimuth_only(sigma_deg: float = 1.0, sigma_known: bool = True) -> Scene:
    """The generic scene with azimuths only and the target altitude known."""
    sensors = tuple(Sensor(i, sigma_deg * DEG) for i, _ in GENERIC_STATIONS)
    return Scene(f"4 stations azimuth-only, {sigma_deg:g} deg", GENERIC_STATIONS, sensors, GENERIC_TARGET,
                 altitude_m=GENERIC_TARGET.alt_m, sigma_known=sigma_known)


def generic_angle_range(sigma_deg: float = 1.0, sigma_range_m: float = 200.0) -> Scene:
    """The generic scene with a range at every station as well."""
    sensors = tuple(Sensor(i, sigma_deg * DEG, sigma_deg * DEG, sigma_range_m) for i, _ in GENERIC_STATIONS)
    return Scene(f"4 stations angle+range, {sigma_deg:g} deg", GENERIC_STATIONS, sensors, GENERIC_TARGET)


PAPER_000_TARGET = geodetic(34.5, 108.9, 8000.0)


def paper_000(looks: int = 1, moved_azimuth_only: bool = False, sigma_deg: float = 2.0) -> Scene:
    """Paper 000's simulation: two stations on the target's meridian, 2 deg on both angles.

    Parameters
    ----------
    looks : int
        Bearings per station; ``looks=2`` is the paper's N = 4 comparison
        ("let the two measurement points each take 2 measurements").
    moved_azimuth_only : bool
        The paper's figure 5: the first station moved to 108.8 E and giving
        the azimuth only.
    """
    first = geodetic(34.2, 108.8 if moved_azimuth_only else 108.9, 400.0)
    stations = (("st-1", first), ("st-2", geodetic(34.9, 108.9, 1000.0)))
    sigma = sigma_deg * DEG
    sensors = []
    for _ in range(looks):
        sensors.append(Sensor("st-1", sigma, None if moved_azimuth_only else sigma))
        sensors.append(Sensor("st-2", sigma, sigma))
    name = f"paper 000, N={2 * looks}" + (", st-1 azimuth-only at 108.8E" if moved_azimuth_only else "")
    return Scene(name, stations, tuple(sensors), PAPER_000_TARGET)


def paper_004(sigma_deg: float, sigma_known: bool = True) -> Scene:
    """Paper 004's scenario: one sensor on y = -0.2 x + 14 km, x = 15..30 km every 0.1 km, target (30, 35) km."""
    east_km = np.round(np.arange(150, 301) * 0.1, 10)
    stations = tuple((f"s{k:03d}", LocalPoint(1e3 * x, 1e3 * (-0.2 * x + 14.0), 0.0)) for k, x in enumerate(east_km))
    sensors = tuple(Sensor(i, sigma_deg * DEG) for i, _ in stations)
    return Scene(f"paper 004, {sigma_deg:g} deg", stations, sensors, LocalPoint(30e3, 35e3, 0.0),
                 altitude_m=0.0, sigma_known=sigma_known)


#: Paper 002: sensors at (0,0,0), (10,0,0), (5,10,0) km, 10 mrad on both angles, targets 0.5 km up over
#: x, y in [0, 10] km.
PAPER_002_SIGMA_RAD = 0.010
PAPER_002_STATIONS = (("s1", LocalPoint(0.0, 0.0, 0.0)), ("s2", LocalPoint(10_000.0, 0.0, 0.0)),
                      ("s3", LocalPoint(5_000.0, 10_000.0, 0.0)))
PAPER_002_TARGET_HEIGHT_M = 500.0


def paper_002_problem() -> Problem:
    """Paper 002's three sensors, azimuth and elevation at each (values zero: a template)."""
    sigma = PAPER_002_SIGMA_RAD
    return build_problem(list(PAPER_002_STATIONS), [Bearing(i, 0.0, 0.0, sigma, sigma) for i, _ in PAPER_002_STATIONS])


#: Paper 003: two aircraft at 5 km, 1 deg angles, 250 m ranges, a target about 50 km away.
PAPER_003_SIGMA_ANGLE_RAD = 1.0 * DEG
PAPER_003_SIGMA_RANGE_M = 250.0
PAPER_003_STATIONS = (("master", GeodeticPoint(41.8031 * DEG, 123.4262 * DEG, 5000.0)),
                      ("helper", GeodeticPoint(41.5010 * DEG, 122.9819 * DEG, 5000.0)))
#: (lat_rad, lon_rad, alt_m)
PAPER_003_TARGET = (41.3183 * DEG, 123.6043 * DEG, 5009.0)


def paper_003_problem(with_ranges: bool = True) -> Problem:
    """Paper 003's two stations with azimuth and elevation (and a range each unless ``with_ranges`` is False)."""
    sigma = PAPER_003_SIGMA_ANGLE_RAD
    measurements = [Bearing("master", 0.0, 0.0, sigma, sigma), Bearing("helper", 0.0, 0.0, sigma, sigma)]
    if with_ranges:
        measurements += [Range("master", 1.0, PAPER_003_SIGMA_RANGE_M), Range("helper", 1.0, PAPER_003_SIGMA_RANGE_M)]
    return build_problem(list(PAPER_003_STATIONS), measurements)
