"""Build one localisation problem from a caller's stations and measurements, with its checks.

:func:`build_problem` checks stations (geodetic or local) and measurements
(:class:`Bearing`, :class:`Range`, :class:`TimeOfArrival`), naming the field
at fault, and turns them into a :class:`Problem` in its common frame:
stations in the common tangent frame, each station's rotation (its own ENU
<- common ENU), and flat measurement arrays in radians, metres and seconds.
Every estimator reads only a :class:`Problem`. The frame placement is the
batch's (:func:`core.problem.batch_build.build_problem_batch` over one problem), so
a problem gets the same bits alone and in a batch; callers with many problems check each
(:func:`checked_inputs`) and place them all in one call (:func:`build_problems`).

The frame and the problem record live in :mod:`core.problem.frame`, below
this module and the batch.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import NamedTuple, Sequence

import numpy as np

from core.errors import InvalidInput
from core.measurements import Kind
from core.problem.batch import ProblemBatch
from core.problem.batch_build import build_problem_batch
from core.problem.frame import GeodeticPoint, LocalPoint, Problem

__all__ = [
    "Bearing",
    "Measurement",
    "ProblemInputs",
    "Range",
    "TimeOfArrival",
    "build_problem",
    "build_problems",
    "checked_inputs",
]


@dataclass(frozen=True)
class Bearing:
    """A line of sight measured by a station, angles in its own ENU frame.

    ``elevation_rad`` None means azimuth-only. ``sigma_azimuth_rad`` None
    means unknown (only ``taylor_wls`` estimates it).
    """

    station_id: str
    azimuth_rad: float
    elevation_rad: float | None = None
    sigma_azimuth_rad: float | None = None
    sigma_elevation_rad: float | None = None


@dataclass(frozen=True)
class Range:
    """Slant range from a station."""

    station_id: str
    range_m: float
    sigma_m: float


@dataclass(frozen=True)
class TimeOfArrival:
    """Time of arrival at a station with synchronised clocks; emission time unknown."""

    station_id: str
    toa_s: float
    sigma_s: float


Measurement = Bearing | Range | TimeOfArrival


def _check_finite(value, loc):
    if value is None or not math.isfinite(value):  # a Python or numpy scalar (math's test: no array made)
        raise InvalidInput(f"{_words(loc[-1])} must be a finite number", loc)


def _check_sigma(value, loc, required=True):
    if value is None:
        if required:
            raise InvalidInput(f"{_words(loc[-1])} is required", loc)
        return
    _check_finite(value, loc)
    if value <= 0:
        raise InvalidInput(f"{_words(loc[-1])} must be > 0", loc)


def _words(name: str) -> str:
    """A core field name as words without its unit: ``sigma_azimuth_rad`` -> ``sigma azimuth``."""
    head, _, unit = name.rpartition("_")
    return (head if unit in ("rad", "m", "s", "deg") and head else name).replace("_", " ")


class ProblemInputs(NamedTuple):
    """One problem's inputs once :func:`checked_inputs` has passed them: a row of what
    :func:`core.problem.batch_build.build_problem_batch` takes (its measurement columns are this problem's alone,
    ``station_index`` counting within it)."""

    station_ids: tuple[str, ...]
    station_coordinates: list[tuple[float, ...]]
    geodetic: bool
    origin: tuple[float, float, float]
    kinds: list[int]
    station_index: list[int]
    values: list[float]
    sigmas: list[float]
    bearing_index: list[int]
    source_index: list[int]
    altitude_m: float
    initial_guess: tuple[float, float, float]
    geodetic_guess: bool


def build_problem(
    stations: Sequence[tuple[str, GeodeticPoint | LocalPoint]],
    measurements: Sequence[Measurement],
    origin: GeodeticPoint | None = None,
    altitude_m: float | None = None,
    initial_guess: GeodeticPoint | LocalPoint | None = None,
    require_sigmas: bool = True,
) -> Problem:
    """Validate stations and measurements and place them in the common frame: :func:`checked_inputs` (its
    parameters; it raises ``InvalidInput`` naming the field), then :func:`build_problems` of that one problem."""
    return build_problems([checked_inputs(stations, measurements, origin, altitude_m, initial_guess,
                                          require_sigmas)]).problem(0)


def build_problems(inputs: Sequence[ProblemInputs]) -> ProblemBatch:
    """Problems that passed :func:`checked_inputs`, placed in their common frames in one batch (their
    frame placement in one call, rather than one per problem).

    Parameters
    ----------
    inputs : sequence of ProblemInputs, length B (>= 1)

    Returns
    -------
    ProblemBatch
        Problem ``b`` is ``inputs[b]``'s, as :func:`build_problem` would give it.
    """
    def column(name: str) -> list:
        return [value for one in inputs for value in getattr(one, name)]

    return build_problem_batch(
        station_counts=[len(one.station_ids) for one in inputs],
        station_ids=[one.station_ids for one in inputs],
        station_coordinates=column("station_coordinates"),
        geodetic_stations=[one.geodetic for one in inputs],
        origin=[one.origin for one in inputs],
        measurement_counts=[len(one.kinds) for one in inputs],
        kinds=column("kinds"),
        station_index=column("station_index"),
        values=column("values"),
        sigmas=column("sigmas"),
        bearing_index=column("bearing_index"),
        source_index=column("source_index"),
        altitude_m=[one.altitude_m for one in inputs],
        initial_guess=[one.initial_guess for one in inputs],
        geodetic_guess=[one.geodetic_guess for one in inputs],
    )


def checked_inputs(
    stations: Sequence[tuple[str, GeodeticPoint | LocalPoint]],
    measurements: Sequence[Measurement],
    origin: GeodeticPoint | None = None,
    altitude_m: float | None = None,
    initial_guess: GeodeticPoint | LocalPoint | None = None,
    require_sigmas: bool = True,
) -> ProblemInputs:
    """Validate stations and measurements: what :func:`build_problem` places in the common frame.

    Parameters
    ----------
    stations : sequence of (id, position)
        All positions geodetic (frame ``wgs84``) or all local.
    measurements : sequence of Bearing, Range or TimeOfArrival
    origin : GeodeticPoint, optional
        Tangent point of the common frame; for local positions, where their
        plane touches the earth. Default: the geodetic stations' centroid on
        the ellipsoid, or a flat plane for local positions.
    altitude_m : float, optional
        Known target altitude.
    initial_guess : GeodeticPoint or LocalPoint, optional
    require_sigmas : bool
        False lets a bearing omit ``sigma_azimuth_rad`` (estimated later).

    Raises
    ------
    InvalidInput
        With ``loc`` naming the offending field.
    """
    if not stations:
        raise InvalidInput("at least one station is required", ("stations",))
    if not measurements:
        raise InvalidInput("at least one measurement is required", ("measurements",))
    ids: dict[str, int] = {}
    for i, (station_id, _) in enumerate(stations):
        if station_id in ids:
            raise InvalidInput(f"duplicate station id {station_id!r}", ("stations", i, "id"))
        ids[station_id] = i

    geodetic = [isinstance(p, GeodeticPoint) for _, p in stations]
    if any(geodetic) and not all(geodetic):
        i = geodetic.index(not geodetic[0])
        raise InvalidInput("stations mix geodetic and local positions", ("stations", i, "position"))
    for i, (_, p) in enumerate(stations):
        for name, value in vars(p).items():
            _check_finite(value, ("stations", i, "position", name))
        if isinstance(p, GeodeticPoint) and abs(p.lat_rad) > np.pi / 2:
            raise InvalidInput("latitude must be within [-90, 90] deg", ("stations", i, "position", "lat_rad"))

    geodetic_frame = all(geodetic)
    kinds, station_index, values, sigmas, bearing_index, source_index = [], [], [], [], [], []
    n_bearings = 0

    def add(kind, station, value, sigma, bearing, source):
        kinds.append(kind)
        station_index.append(station)
        values.append(value)
        sigmas.append(np.nan if sigma is None else sigma)
        bearing_index.append(bearing)
        source_index.append(source)

    for i, m in enumerate(measurements):
        loc = ("measurements", i)
        if m.station_id not in ids:
            raise InvalidInput(f"unknown station id {m.station_id!r}", loc + ("station_id",))
        s = ids[m.station_id]
        if isinstance(m, Bearing):
            _check_finite(m.azimuth_rad, loc + ("azimuth_rad",))
            _check_sigma(m.sigma_azimuth_rad, loc + ("sigma_azimuth_rad",), required=require_sigmas)
            add(Kind.AZIMUTH, s, m.azimuth_rad, m.sigma_azimuth_rad, n_bearings, i)
            if m.elevation_rad is not None:
                _check_finite(m.elevation_rad, loc + ("elevation_rad",))
                if abs(m.elevation_rad) > np.pi / 2:
                    raise InvalidInput("elevation must be within [-90, 90] deg", loc + ("elevation_rad",))
                _check_sigma(m.sigma_elevation_rad, loc + ("sigma_elevation_rad",))
                add(Kind.ELEVATION, s, m.elevation_rad, m.sigma_elevation_rad, n_bearings, i)
            n_bearings += 1
        elif isinstance(m, Range):
            _check_finite(m.range_m, loc + ("range_m",))
            if m.range_m < 0:
                raise InvalidInput("range_m must be >= 0", loc + ("range_m",))
            _check_sigma(m.sigma_m, loc + ("sigma_m",))
            add(Kind.RANGE, s, m.range_m, m.sigma_m, -1, i)
        elif isinstance(m, TimeOfArrival):
            _check_finite(m.toa_s, loc + ("toa_s",))
            _check_sigma(m.sigma_s, loc + ("sigma_s",))
            add(Kind.TOA, s, m.toa_s, m.sigma_s, -1, i)
        else:
            raise InvalidInput(f"unsupported measurement {type(m).__name__}", loc)

    guess, geodetic_guess = (np.nan, np.nan, np.nan), False
    if initial_guess is not None:
        for name, value in vars(initial_guess).items():
            _check_finite(value, ("initial_guess", name))
        geodetic_guess = isinstance(initial_guess, GeodeticPoint)
        if geodetic_guess and not geodetic_frame and origin is None:
            raise InvalidInput("a geodetic initial guess needs a geodetic frame or an origin",
                               ("initial_guess",))
        guess = tuple(vars(initial_guess).values())
    if altitude_m is not None:
        _check_finite(altitude_m, ("altitude_m",))

    return ProblemInputs(
        station_ids=tuple(ids),
        station_coordinates=[tuple(vars(p).values()) for _, p in stations],
        geodetic=geodetic_frame,
        origin=(np.nan,) * 3 if origin is None else (origin.lat_rad, origin.lon_rad, origin.alt_m),
        kinds=kinds,
        station_index=station_index,
        values=values,
        sigmas=sigmas,
        bearing_index=bearing_index,
        source_index=source_index,
        altitude_m=np.nan if altitude_m is None else altitude_m,
        initial_guess=guess,
        geodetic_guess=geodetic_guess,
    )
