"""Read FixRequest bodies into one core batch (:func:`read_fix_requests`): the second step of the fix road.

Plainly valid bodies are read in bulk under the rules of :mod:`service.fixes.rules`; any other body is
validated by the schema and built by :func:`service.convert.to_problem`, which word its error.
"""

from __future__ import annotations

import math
import typing

import numba
import numpy as np
from msgspec import UNSET
from pydantic import ValidationError

from core.errors import LocalizationError
from core.estimators import SolveOptions
from core.problem.frame import Problem
from core.problem.batch import ProblemBatch
from core.problem.batch_build import build_problem_batch
from service import schemas
from service.convert import to_options, to_problem
from service.fixes import decode
from service.fixes.rules import (AZ, CHOICES, COORDINATE_BOUNDS, DEFAULT_OPTIONS, DEFAULT_SOLVE, EL, FRAME, METHOD,
                                 RG, RULES, SIGMA_BOUNDS, TOA, VALUE_BOUNDS)
from service.limits import fix_cost_context, fix_within_limit
from service.web.problems import localization_problem, problem_body, validation_errors
from service.renderings.points import Renderings, of_request

# The rules the reader applies, each from the one table (service.fixes.rules).
_FixRequest, _Options = schemas.FixRequest, schemas.Options
_LAT, _LON, _ALT = (RULES[schemas.GeodeticPosition, name] for name in ("lat_deg", "lon_deg", "alt_m"))
_EAST, _NORTH, _UP = (RULES[schemas.LocalPosition, name] for name in ("east_m", "north_m", "up_m"))
_STATIONS, _MEASUREMENTS = RULES[_FixRequest, "stations"], RULES[_FixRequest, "measurements"]
_FORMATS_LENGTH, _STATION_ID = RULES[_FixRequest, "formats"], RULES[schemas.Station, "id"]
_ITERATIONS, _TOLERANCE, _LOSS_SCALE = (RULES[_Options, name] for name in ("max_iterations", "tolerance_m",
                                                                             "loss_scale"))
_ALTITUDE = RULES[schemas.Constraints, "altitude_m"]
_FRAMES, _METHODS, _FORMATS = (CHOICES[_FixRequest, name] for name in ("frame", "method", "formats"))
_VARIANTS, _OUTLIERS, _LOSSES = (CHOICES[_Options, name] for name in ("variant", "outliers", "loss"))
_NAN3 = (math.nan, math.nan, math.nan)


class _Reject(Exception):
    """The lean reader cannot vouch for this problem: the schema and :func:`to_problem` decide."""


def _number(value, bounds) -> float:
    """A decoded float within its closed bounds (NaN, which only a non-JSON ``NaN`` literal gives, is not)."""
    if not bounds.low <= value <= bounds.high:
        raise _Reject
    return value


def _coordinates(position: decode.Position, geodetic: bool) -> tuple[float, float, float]:
    """A position's raw coordinates in API units, ``(lat_deg, lon_deg, alt_m)`` or ``(east_m, north_m, up_m)``
    (``_Reject`` unless it holds the fields of the frame's position model only)."""
    if geodetic:
        if position.lat_deg is UNSET or position.lon_deg is UNSET or position.east_m is not UNSET \
                or position.north_m is not UNSET or position.up_m is not UNSET:
            raise _Reject
        return position.lat_deg, position.lon_deg, 0.0 if position.alt_m is UNSET else position.alt_m
    if position.east_m is UNSET or position.north_m is UNSET or position.lat_deg is not UNSET \
            or position.lon_deg is not UNSET or position.alt_m is not UNSET:
        raise _Reject
    return position.east_m, position.north_m, 0.0 if position.up_m is UNSET else position.up_m


def _position(position: decode.Position, geodetic: bool) -> tuple[float, float, float]:
    """A position as core coordinates within the schema's bounds, ``(lat_rad, lon_rad, alt_m)`` or
    ``(east_m, north_m, up_m)``."""
    a, b, c = _coordinates(position, geodetic)
    if geodetic:
        return math.radians(_number(a, _LAT)), math.radians(_number(b, _LON)), _number(c, _ALT)
    return _number(a, _EAST), _number(b, _NORTH), _number(c, _UP)


#: The renderings of a request that asks for none (one object shared by all such requests).
_PLAIN = Renderings()

#: The columns of a frame row (:attr:`_Settings.frame`, nine numbers, NaN where not given): geodetic (1 or 0),
#: origin ``(lat_rad, lon_rad, alt_m)``, the known altitude_m, the initial guess in core coordinates and whether
#: that guess is geodetic (1 or 0).
_GEODETIC, _ORIGIN, _ALTITUDE_M, _GUESS, _GUESS_GEODETIC = 0, slice(1, 4), 4, slice(5, 8), 8


class _Settings(typing.NamedTuple):
    """What a body says besides its stations and measurements."""

    #: Nine numbers, one row of the batch's frame table (its columns: ``_GEODETIC`` ... ``_GUESS_GEODETIC``).
    frame: tuple
    method: str
    options: SolveOptions
    renderings: Renderings


#: The columns of a scalar measurement's structure row in :class:`_Columns`.
_KIND, _STATION, _BEARING, _SOURCE = range(4)


class _Columns(typing.NamedTuple):
    """Structure checks and raw columns of the bodies the lean reader takes (the numbers are checked later, in
    bulk), and the slots of those it leaves to the schema.

    Attributes
    ----------
    accepted : list of int
        Request index of each body read.
    settings : list of _Settings
    station_counts, measurement_counts : list of int
        Per body read; a measurement count counts scalar measurements (a bearing with an elevation is two).
    station_ids : list of tuple of str
    coordinates : list of float
        Station positions, API units, three per station, flattened (a missing height is 0).
    scalars : list of int
        The scalar measurements' structure, four per measurement (kind code, station index, bearing index or
        -1, request measurement index), flattened.
    readings : list of float
        Their values, API units, two per measurement (value, sigma), flattened; a missing azimuth sigma is NaN.
    frames : list of float
        The frame rows of the settings, nine per body, flattened.
    rest : list of int
        Request index of each body left to the schema.
    """

    accepted: list
    settings: list
    station_counts: list
    measurement_counts: list
    station_ids: list
    coordinates: list
    scalars: list
    readings: list
    frames: list
    rest: list


def _problem_settings(body: decode.FixBody, frame: str, method: str) -> _Settings:
    """The settings of a body with more than stations and measurements (``_Reject`` if unusual)."""
    geodetic = frame == "wgs84"
    origin = _NAN3 if body.origin is None else _position(body.origin, True)
    options = body.options
    solve, guess, guess_geodetic = DEFAULT_SOLVE, _NAN3, False
    if options is not UNSET:
        default = DEFAULT_OPTIONS
        iterations = default.max_iterations if options.max_iterations is UNSET else options.max_iterations
        outliers = default.outliers if options.outliers is UNSET else options.outliers
        absolute_sigma = default.absolute_sigma if options.absolute_sigma is UNSET else options.absolute_sigma
        loss = default.loss if options.loss is UNSET else options.loss
        if not _ITERATIONS.low <= iterations <= _ITERATIONS.high or outliers not in _OUTLIERS or loss not in _LOSSES \
                or options.variant is not None and options.variant not in _VARIANTS:
            raise _Reject
        solve = SolveOptions(iterations,
                             default.tolerance_m if options.tolerance_m is UNSET else _number(options.tolerance_m,
                                                                                              _TOLERANCE),
                             options.variant, outliers, absolute_sigma, loss,
                             default.loss_scale if options.loss_scale is UNSET else _number(options.loss_scale,
                                                                                            _LOSS_SCALE))
        raw = options.initial_guess
        if raw is not None:
            guess_geodetic = raw.lat_deg is not UNSET or raw.lon_deg is not UNSET
            if guess_geodetic and not geodetic and math.isnan(origin[0]):
                raise _Reject
            guess = _position(raw, guess_geodetic)
    altitude = math.nan
    if body.constraints is not None and body.constraints.altitude_m is not None:
        altitude = _number(body.constraints.altitude_m, _ALTITUDE)
    formats = body.formats
    if formats is not UNSET and (not _FORMATS_LENGTH.low <= len(formats) <= _FORMATS_LENGTH.high
                                 or any(f not in _FORMATS for f in formats)):
        raise _Reject
    return _Settings((float(geodetic), *origin, altitude, *guess, float(guess_geodetic)), method, solve,
                     Renderings(formats) if formats else _PLAIN)


#: The settings of a body with only frame, method, stations and measurements (see :func:`_problem_settings`).
_PLAIN_SETTINGS = {(frame, method): _Settings((float(frame == "wgs84"), *_NAN3, math.nan, *_NAN3, 0.0), method,
                                               DEFAULT_SOLVE, _PLAIN)
                   for frame in _FRAMES for method in _METHODS}


def _read(bodies: list, max_fix_cost: int | None = None) -> _Columns:
    """Structure checks and raw columns of the bodies that decode as :class:`service.fixes.decode.FixBody` and
    look plainly valid (see :class:`_Columns`)."""
    accepted, settings, station_counts, measurement_counts, station_ids = [], [], [], [], []
    coordinates, scalars, readings, frames, rest = [], [], [], [], []
    add_coordinates, add_scalar, add_reading = coordinates.extend, scalars.extend, readings.extend
    unset, nan, plain, coordinates_of = UNSET, math.nan, _PLAIN_SETTINGS, _coordinates
    stations_min, stations_max, id_min, id_max = *_STATIONS, *_STATION_ID
    measurements_min, measurements_max = _MEASUREMENTS
    Bearing, Range = decode.Bearing, decode.Range
    for slot, raw in enumerate(bodies):
        body = decode.as_fix_body(raw)
        if body is None:
            rest.append(slot)
            continue
        n_coordinates, n_scalars, n_readings = len(coordinates), len(scalars), len(readings)
        try:
            frame = FRAME if body.frame is unset else body.frame
            method = METHOD if body.method is unset else body.method
            if body.origin is None and body.options is unset and body.constraints is None and body.formats is unset:
                setting = plain.get((frame, method))
                if setting is None:
                    raise _Reject
            elif frame in _FRAMES and method in _METHODS:
                setting = _problem_settings(body, frame, method)
            else:
                raise _Reject
            geodetic = frame == "wgs84"
            stations = body.stations
            if not stations_min <= len(stations) <= stations_max:
                raise _Reject
            ids: dict[str, int] = {}
            for station in stations:
                sid, position = station.id, station.position
                if not id_min <= len(sid) <= id_max or sid in ids:
                    raise _Reject
                ids[sid] = len(ids)
                add_coordinates(coordinates_of(position, geodetic))
            measurements = body.measurements
            if not measurements_min <= len(measurements) <= measurements_max or \
                    not fix_within_limit(len(ids), len(measurements), method, setting.options.outliers == "exclude",
                                         max_fix_cost):
                raise _Reject
            n_bearings = 0
            for i, m in enumerate(measurements):
                station = ids.get(m.station_id)
                if station is None:
                    raise _Reject
                kind = type(m)
                if kind is Bearing:
                    sigma_azimuth, elevation = m.sigma_azimuth_deg, m.elevation_deg
                    sigma_elevation = m.sigma_elevation_deg
                    if sigma_azimuth is None:
                        sigma_azimuth = nan
                    elif sigma_azimuth != sigma_azimuth:  # a NaN literal: not the absent sigma that NaN stands for
                        raise _Reject
                    if elevation is not None:
                        if sigma_elevation is None:
                            raise _Reject
                        add_scalar((AZ, station, n_bearings, i, EL, station, n_bearings, i))
                        add_reading((m.azimuth_deg, sigma_azimuth, elevation, sigma_elevation))
                    elif sigma_elevation is not None:
                        raise _Reject
                    else:
                        add_scalar((AZ, station, n_bearings, i))
                        add_reading((m.azimuth_deg, sigma_azimuth))
                    n_bearings += 1
                elif kind is Range:
                    add_scalar((RG, station, -1, i))
                    add_reading((m.range_m, m.sigma_m))
                else:
                    add_scalar((TOA, station, -1, i))
                    add_reading((m.toa_s, m.sigma_s))
        except _Reject:
            del coordinates[n_coordinates:], scalars[n_scalars:], readings[n_readings:]
            rest.append(slot)
            continue
        accepted.append(slot)
        settings.append(setting)
        frames.extend(setting.frame)
        station_counts.append(len(ids))
        station_ids.append(tuple(ids))
        measurement_counts.append((len(scalars) - n_scalars) // 4)
    return _Columns(accepted, settings, station_counts, measurement_counts, station_ids, coordinates, scalars,
                    readings, frames, rest)


@numba.njit(cache=True, nogil=True, error_model="numpy")
def _checked_core_units(coordinates, station_counts, frames, scalars, readings, measurement_counts,
                        coordinate_bounds, value_bounds, sigma_bounds, bad):
    """The lean reader's bulk checks, and its conversion to core units in place, in one pass.

    Parameters
    ----------
    coordinates : ndarray, shape (S, 3)
        Station coordinates as sent, ``station_counts`` ``(B,)`` consecutive rows per problem:
        ``(lat_deg, lon_deg, alt_m)`` where the frame is geodetic, else ``(east_m, north_m, up_m)``. Set to core
        units: latitude and longitude in radians.
    frames : ndarray, shape (B, 9)
        The problems' frame rows (columns ``_GEODETIC`` ... ``_GUESS_GEODETIC``): the first number is 1 for a geodetic frame.
    scalars : ndarray of int, shape (T, 4)
        The scalar measurements' structure (kind code first), ``measurement_counts`` ``(B,)`` consecutive rows
        per problem.
    readings : ndarray, shape (T, 2)
        Value and sigma as sent (angles in degrees; an azimuth's sigma may be NaN: not given). Set to core
        units: angles in radians.
    coordinate_bounds : ndarray, shape (2, 3, 2)
        Closed bounds per frame (local, geodetic) and coordinate; ``value_bounds``, ``sigma_bounds`` ``(4, 2)``
        per kind code.
    bad : ndarray of bool, shape (B,)
        Set where a problem has a number out of its bounds (its numbers are not all converted).

    Returns
    -------
    int
        How many problems are bad.
    """
    bad[:] = False
    station, scalar = 0, 0
    for b in range(station_counts.size):
        frame = 1 if frames[b, 0] else 0
        for _ in range(station_counts[b]):
            c = coordinates[station]
            for j in range(3):
                if not coordinate_bounds[frame, j, 0] <= c[j] <= coordinate_bounds[frame, j, 1]:
                    bad[b] = True
            if frame:
                c[0], c[1] = math.radians(c[0]), math.radians(c[1])
            station += 1
        for _ in range(measurement_counts[b]):
            k, value, sigma = scalars[scalar, 0], readings[scalar, 0], readings[scalar, 1]
            if not (value_bounds[k, 0] <= value <= value_bounds[k, 1] and (
                    sigma_bounds[k, 0] <= sigma <= sigma_bounds[k, 1] or (k == AZ and math.isnan(sigma)))):
                bad[b] = True
            if k == AZ or k == EL:
                readings[scalar, 0], readings[scalar, 1] = math.radians(value), math.radians(sigma)
            scalar += 1
    return np.count_nonzero(bad)


class FixRequests(typing.NamedTuple):
    """Fix requests read into one core batch (a named tuple: made for every request, and cheaper to make than a
    dataclass).

    Attributes
    ----------
    batch : ProblemBatch or None
        The problems that were read; None when none was.
    slots : list of int
        Request index of each batch row.
    methods : list of str
    options : list of SolveOptions
    formats : list of Renderings
        Per batch row: the formats asked for, with the options that shape them.
    errors : dict of int to dict
        Problem bodies of the requests that could not be read, by request index.
    """

    batch: ProblemBatch | None
    slots: list[int]
    methods: list[str]
    options: list[SolveOptions]
    formats: list[tuple[str, ...]]
    errors: dict[int, dict]


def read_fix_requests(bodies: list, max_fix_cost: int | None = None) -> FixRequests:
    """Read FixRequest bodies (:class:`service.fixes.decode.FixBody` structs or parsed JSON) into one core batch.

    A body that is plainly valid (a FixBody, or parsed JSON that converts to
    one, within the bounds of :class:`schemas.FixRequest`, with known and
    unique station ids) is read in bulk: structure problem by problem, numbers
    range-checked for all at once, the frames placed by
    :func:`core.problem.batch_build.build_problem_batch`.
    Any other body is validated by the schema and built by :func:`to_problem`,
    which decide and word its error, and joins the same batch. A body over
    ``max_fix_cost`` (the app's limit; None: no limit) takes the schema's road,
    which words its 422.
    """
    read = _read(bodies, max_fix_cost)
    accepted, settings, station_ids, rest = read.accepted, read.settings, read.station_ids, read.rest
    errors: dict[int, dict] = {}
    lean = None
    if accepted:
        station_counts = np.array(read.station_counts, dtype=np.intp)
        measurement_counts = np.array(read.measurement_counts, dtype=np.intp)
        frames = np.array(read.frames, dtype=float).reshape(-1, 9)
        coords = np.array(read.coordinates, dtype=float).reshape(-1, 3)
        table = np.array(read.scalars, dtype=np.intp).reshape(-1, 4)
        reading = np.array(read.readings, dtype=float).reshape(-1, 2)
        bad = np.empty(len(accepted), dtype=bool)
        if _checked_core_units(coords, station_counts, frames, table, reading, measurement_counts,
                               COORDINATE_BOUNDS, VALUE_BOUNDS, SIGMA_BOUNDS, bad):
            rest = sorted(rest + [accepted[i] for i in np.flatnonzero(bad)])
            keep = np.flatnonzero(~bad)
            station_keep, scalar_keep = ~bad.repeat(station_counts), ~bad.repeat(measurement_counts)
            accepted = [accepted[i] for i in keep]
            settings = [settings[i] for i in keep]
            station_ids = [station_ids[i] for i in keep]
            station_counts, measurement_counts = station_counts[keep], measurement_counts[keep]
            frames = frames[keep]
            coords, table, reading = coords[station_keep], table[scalar_keep], reading[scalar_keep]
        if accepted:
            lean = build_problem_batch(
                station_counts=station_counts,
                station_ids=station_ids,
                station_coordinates=coords,
                geodetic_stations=frames[:, _GEODETIC],
                origin=frames[:, _ORIGIN],
                measurement_counts=measurement_counts,
                kinds=table[:, _KIND],
                station_index=table[:, _STATION],
                values=reading[:, 0],
                sigmas=reading[:, 1],
                bearing_index=table[:, _BEARING],
                source_index=table[:, _SOURCE],
                altitude_m=frames[:, _ALTITUDE_M],
                initial_guess=frames[:, _GUESS],
                geodetic_guess=frames[:, _GUESS_GEODETIC],
            )
    slots = list(accepted)
    methods = [s.method for s in settings]
    options = [s.options for s in settings]
    formats = [s.renderings for s in settings]
    built: list[Problem] = []
    for slot in rest:
        try:
            request = schemas.FixRequest.model_validate(decode.as_builtins(bodies[slot]),
                                                        context=fix_cost_context(max_fix_cost))
        except ValidationError as error:
            errors[slot] = _invalid(error)
            continue
        try:
            built.append(to_problem(request))
        except LocalizationError as error:
            errors[slot] = localization_problem(error)
            continue
        slots.append(slot)
        methods.append(request.method)
        options.append(to_options(request))
        formats.append(of_request(request))
    batch = lean
    if built:
        through_schema = ProblemBatch.from_problems(built)
        batch = through_schema if lean is None else ProblemBatch.concatenate([lean, through_schema])
    return FixRequests(batch, slots, methods, options, formats, errors)


def _invalid(error: ValidationError) -> dict:
    errors = validation_errors(error.errors())
    first = errors[0] if errors else {"loc": [], "msg": "invalid problem"}
    detail = f"{'.'.join(map(str, first['loc'])) or 'problem'}: {first['msg']}"
    return problem_body(422, "invalid_input", detail, errors)
