"""The one translation between HTTP schemas (degrees, request order) and core types.

Fix requests, single or batched, take one road: :func:`fix_results` reads
decoded bodies (:mod:`service.wire`) into one core batch (:func:`read_fix_requests`), solves it with
:func:`core.estimators.iter_solutions` and writes every fix from the batch's
arrays (:func:`fix_bodies`, which writes each fix body as JSON text, read
as a mapping on demand: :class:`service.responses.JsonObject`). Responses
are plain dicts and such texts (serialised by orjson) rather than
re-validated models: the schema documents them and the tests check that
every response validates against it.
"""

from __future__ import annotations

import functools
import logging
import math
import re
import typing
from dataclasses import dataclass

import numba
import numpy as np
import orjson
from msgspec import UNSET
from pydantic import ValidationError

from core import geodesy
from core import kernels as core_kernels
from core.coverage import Grid, cells_per_side, coverage_map, grid
from core.crlb import gdop, information_at
from core.error_summary import error_summary, radius50_tables, summaries_kernel
from core.errors import InvalidInput, LocalizationError, UnobservableGeometry
from core.estimators import PART_PROBLEMS, FixBatch, SolveOptions, iter_solutions, resolve_methods
from core.measurements import KIND_NAMES, Kind
from core.parallel import Stopped
from core.problem import Bearing, GeodeticPoint, LocalPoint, Problem, Range, TimeOfArrival, build_problem
from core.problem_batch import ProblemBatch, size_groups
from core.problem_batch_build import build_problem_batch
from core.simulation.measurements import evaluate
from service import schemas, wire
from service.limits import check_grid, fix_cost_context, fix_within_limit
from service.maps import coverage_geojson, coverage_geotiff, coverage_kmz, coverage_png
from service.problems import ApiError, for_request, localization_problem, problem_body, validation_errors
from service.renderings import Renderings, fix_cot, fix_geojson, of_request
from service.responses import JsonObject

logger = logging.getLogger("passive_locator")

_AZ, _EL, _RG, _TOA = int(Kind.AZIMUTH), int(Kind.ELEVATION), int(Kind.RANGE), int(Kind.TOA)


def to_point(position) -> GeodeticPoint | LocalPoint:
    if isinstance(position, schemas.GeodeticPosition):
        return GeodeticPoint(math.radians(position.lat_deg), math.radians(position.lon_deg), position.alt_m)
    return LocalPoint(position.east_m, position.north_m, position.up_m)


def _radians(value: float | None) -> float | None:
    return None if value is None else math.radians(value)


def to_measurement(m):
    if m.type == "bearing":
        return Bearing(m.station_id, math.radians(m.azimuth_deg), _radians(m.elevation_deg),
                       _radians(m.sigma_azimuth_deg), _radians(m.sigma_elevation_deg))
    if m.type == "range":
        return Range(m.station_id, m.range_m, m.sigma_m)
    return TimeOfArrival(m.station_id, m.toa_s, m.sigma_s)


def _altitude(constraints: schemas.Constraints | None) -> float | None:
    return None if constraints is None else constraints.altitude_m


def to_problem(request: schemas.FixRequest) -> Problem:
    """Validate and place a fix request in its common frame (raises core InvalidInput)."""
    guess = request.options.initial_guess
    return build_problem(
        stations=[(s.id, to_point(s.position)) for s in request.stations],
        measurements=[to_measurement(m) for m in request.measurements],
        origin=None if request.origin is None else to_point(request.origin),
        altitude_m=_altitude(request.constraints),
        initial_guess=None if guess is None else to_point(guess),
        require_sigmas=False,
    )


def to_options(request: schemas.FixRequest | schemas.EvaluationRequest) -> SolveOptions:
    o = request.options
    return SolveOptions(max_iterations=o.max_iterations, tolerance_m=o.tolerance_m, variant=o.variant,
                        outliers=o.outliers, absolute_sigma=o.absolute_sigma, loss=o.loss, loss_scale=o.loss_scale)


def planning_problem(request: schemas.PlanningGeometry) -> Problem:
    """A problem whose measurements are the sensors' kinds (their values unused), in its common frame."""
    measurements = []
    for sensor in request.sensors:
        if sensor.azimuth:
            el = 0.0 if sensor.elevation else None
            measurements.append(Bearing(sensor.station_id, 0.0, el, _radians(sensor.sigma_azimuth_deg),
                                        _radians(sensor.sigma_elevation_deg)))
        if sensor.range:
            measurements.append(Range(sensor.station_id, 0.0, sensor.sigma_range_m))
        if sensor.toa:
            measurements.append(TimeOfArrival(sensor.station_id, 0.0, sensor.sigma_toa_s))
    if not measurements:
        raise InvalidInput("the sensors measure nothing", ("sensors",))
    return build_problem(
        stations=[(s.id, to_point(s.position)) for s in request.stations],
        measurements=measurements,
        origin=None if request.origin is None else to_point(request.origin),
        altitude_m=_altitude(request.constraints),
    )


def in_frame(problem: Problem, position, loc: tuple) -> np.ndarray:
    """A request position ``(3,)`` in the problem's common ENU frame (InvalidInput at ``loc`` if it cannot be)."""
    point = to_point(position)
    if isinstance(point, GeodeticPoint):
        if not problem.frame.is_geodetic:
            raise InvalidInput("a geodetic position needs a geodetic frame or an origin", loc)
        return problem.frame.from_geodetic(point.lat_rad, point.lon_rad, point.alt_m)
    return np.array([point.east_m, point.north_m, point.up_m])


def crlb_problem(request: schemas.CrlbRequest) -> tuple[Problem, np.ndarray]:
    """A problem whose measurements are the sensors' kinds, and the target in its frame."""
    problem = planning_problem(request)
    return problem, in_frame(problem, request.target, ("target",))


def crlb_response(request: schemas.CrlbRequest) -> dict:
    """The bound of a planned geometry at its target (UnobservableGeometry when the sensors cannot fix it)."""
    problem, target = crlb_problem(request)
    info = information_at(problem, target)
    if not info.observable[0]:
        raise UnobservableGeometry("these sensors do not determine the target position (singular information)")
    bound = info.covariance_enu_m2[0:1]
    frame = problem.frame
    if frame.is_geodetic:  # in the east/north/up axes at the target, as a fix's bound is
        lat, lon, _ = frame.to_geodetic(target)
        bound = geodesy.covariances_to_points(bound, lat, lon, frame.ecef_to_enu_rotation)
    return {"crlb_enu_m2": bound[0].tolist(),
            "error": error_dict(error_summary(bound), gdop(bound, info.reference_sigma_m))}


def grid_of_request(request: schemas.CrlbGridRequest, max_grid_cost: int | None = None) -> tuple[Problem, Grid]:
    """The planning problem and the grid of a coverage-map request.

    Raises 422s with field paths: InvalidInput for a centre that cannot be placed, ``invalid_input`` for an
    altitude other than the known one, ``over_limit`` when ``cells x measurement rows`` is over ``max_grid_cost``.
    """
    problem = planning_problem(request)
    spec = request.grid
    known = _altitude(request.constraints)
    altitude = spec.altitude_m if spec.altitude_m is not None else (0.0 if known is None else known)
    if known is not None and altitude != known:
        detail = (f"the grid's altitude_m {altitude:g} differs from constraints.altitude_m {known:g}, the known "
                  "target altitude")
        raise ApiError(422, "invalid_input", detail, [{"loc": ["grid", "altitude_m"], "msg": detail}])
    if max_grid_cost is not None:
        check_grid(cells_per_side(spec.half_width_m, spec.step_m) ** 2, int(problem.kinds.size), max_grid_cost)
    centre = in_frame(problem, spec.centre, ("grid", "centre"))
    return problem, grid(problem, centre, spec.half_width_m, spec.step_m, altitude)


def coverage_renderings(request: schemas.CrlbGridRequest, problem: Problem, grid_cells: Grid, formats, *,
                        scheduler=None, should_stop=None, progress=None) -> dict:
    """A coverage map computed once and rendered as asked: ``{"geojson": dict, "png": bytes, "kmz": bytes,
    "tiff": bytes}`` for ``formats`` (a KMZ or GeoTIFF raises :class:`service.maps.NotOnTheEarth` in a flat
    frame).

    Raises core.parallel.Stopped when ``should_stop`` says so; ``scheduler`` as for :func:`core.parallel.run_chunks`.
    """
    coverage = coverage_map(problem, grid_cells.cells_enu_m, scheduler=scheduler, should_stop=should_stop,
                            progress=progress)
    out = {}
    if "geojson" in formats:
        out["geojson"] = coverage_geojson(problem, grid_cells, coverage)
    if "png" in formats:
        out["png"] = coverage_png(problem, grid_cells, coverage, request.image.width_px, request.image.height_px)
    longer_side_px = max(request.image.width_px, request.image.height_px)
    if "kmz" in formats:
        out["kmz"] = coverage_kmz(problem, grid_cells, coverage, longer_side_px)
    if "tiff" in formats:
        out["tiff"] = coverage_geotiff(problem, grid_cells, coverage, longer_side_px)
    return out


def _finite(value):
    if isinstance(value, np.ndarray):
        return value.tolist() if np.all(np.isfinite(value)) else None
    return value if math.isfinite(value) else None


def evaluation_body(request: schemas.EvaluationRequest, problem: Problem, target_enu_m, methods, should_stop,
                    chunk_trials: int, scheduler: str | None = None, progress=None) -> dict:
    """The response body of a Monte Carlo evaluation (raises core.parallel.Stopped when ``should_stop`` says so).

    ``scheduler``: a Dask scheduler address to run the chunks on (the service's ``dask_scheduler``), else here.
    """
    results = evaluate(problem, target_enu_m, methods, request.trials, request.seed, request.noise,
                       options=to_options(request), should_stop=should_stop, chunk_trials=chunk_trials,
                       scheduler=scheduler, progress=progress)
    methods_out = {
        name: {
            "rmse_m": _finite(r.rmse_m),
            "rmse_enu_m": _finite(r.rmse_enu_m),
            "bias_enu_m": _finite(r.bias_enu_m),
            "crlb_rmse_m": r.crlb_rmse_m,
            "efficiency": _finite(r.efficiency),
            "nees_mean": _finite(r.nees_mean),
            "failures": r.failures,
            "excluded_trials": r.excluded_trials,
            "failure_reasons": [{"code": code, "trials": count, "example": message} for code, (count, message)
                                in sorted(r.failure_reasons.items(), key=lambda item: (-item[1][0], item[0]))],
        }
        for name, r in results.items()
    }
    return {"methods": methods_out, "trials": request.trials, "seed": request.seed, "noise": request.noise}


def error_dict(summary, gdops, i: int = 0) -> dict:
    """The ``error`` block of row ``i`` of an ErrorSummary, with its dimensionless GDOP (``(B,)``, NaN: null)."""
    return {
        "cep50_m": float(summary.cep50_m[i]),
        "sep50_m": float(summary.sep50_m[i]),
        "vertical_sigma_m": float(summary.vertical_sigma_m[i]),
        "gdop": _finite(float(gdops[i])),
        "sqrt_trace_m": float(summary.gdop_m[i]),
        "ellipse95": {
            "semi_major_m": float(summary.ellipse_semi_major_m[i]),
            "semi_minor_m": float(summary.ellipse_semi_minor_m[i]),
            "orientation_deg": float(np.degrees(summary.ellipse_orientation_rad[i])),
        },
    }


# --- Fix requests: one reader, one solve, one writer, for POST /v1/fixes (a batch of one) and the batch route. ---

#: The fields the reader handles, per request model: the :mod:`service.wire` structs' fields (and ``type``, their
#: tag). A test holds each set against the model's own fields, so a field added to the schema fails it until the
#: reader handles the field.
READ_FIELDS = {
    # A body with observed_at or cot options is read through the schema (they shape only its renderings).
    schemas.FixRequest: frozenset(wire.FixBody.__struct_fields__) | {"observed_at", "cot"},
    schemas.CotOptions: frozenset(schemas.CotOptions.model_fields),
    schemas.Station: frozenset(wire.Station.__struct_fields__),
    schemas.GeodeticPosition: frozenset(("lat_deg", "lon_deg", "alt_m")),
    schemas.LocalPosition: frozenset(("east_m", "north_m", "up_m")),
    schemas.BearingMeasurement: frozenset(wire.Bearing.__struct_fields__) | {"type"},
    schemas.RangeMeasurement: frozenset(wire.Range.__struct_fields__) | {"type"},
    schemas.ToaMeasurement: frozenset(wire.Toa.__struct_fields__) | {"type"},
    schemas.Options: frozenset(wire.Options.__struct_fields__),
    schemas.Constraints: frozenset(wire.Constraints.__struct_fields__),
}
_FORMATS = frozenset(typing.get_args(schemas.Format))
_METHODS = schemas.METHODS
_FRAME = schemas.FixRequest.model_fields["frame"].default
_METHOD = schemas.FixRequest.model_fields["method"].default
_DEFAULT_OPTIONS = schemas.Options()
_VARIANTS = frozenset(typing.get_args(schemas.Variant))
_OUTLIERS = frozenset(typing.get_args(schemas.Options.model_fields["outliers"].annotation))
_LOSSES = frozenset(typing.get_args(schemas.Options.model_fields["loss"].annotation))
_DEFAULT_SOLVE = SolveOptions(_DEFAULT_OPTIONS.max_iterations, _DEFAULT_OPTIONS.tolerance_m, _DEFAULT_OPTIONS.variant,
                              _DEFAULT_OPTIONS.outliers, _DEFAULT_OPTIONS.absolute_sigma, _DEFAULT_OPTIONS.loss,
                              _DEFAULT_OPTIONS.loss_scale)
_NAN3 = (math.nan, math.nan, math.nan)


def _bounds(model, name: str) -> tuple[float, float]:
    """A float field's bounds as the closed interval ``[low, high]`` of the floats its schema accepts (an open
    end, ``gt`` or ``lt``, moves one float inwards)."""
    low, high = -math.inf, math.inf
    for rule in model.model_fields[name].metadata:
        if getattr(rule, "ge", None) is not None:
            low = float(rule.ge)
        if getattr(rule, "gt", None) is not None:
            low = math.nextafter(float(rule.gt), math.inf)
        if getattr(rule, "le", None) is not None:
            high = float(rule.le)
        if getattr(rule, "lt", None) is not None:
            high = math.nextafter(float(rule.lt), -math.inf)
    return low, high


class _Reject(Exception):
    """The lean reader cannot vouch for this problem: the schema and :func:`to_problem` decide."""


def _number(value, bounds) -> float:
    """A decoded float within its closed bounds (NaN, which only a non-JSON ``NaN`` literal gives, is not)."""
    if not bounds[0] <= value <= bounds[1]:
        raise _Reject
    return value


_LAT = _bounds(schemas.GeodeticPosition, "lat_deg")
_LON = _bounds(schemas.GeodeticPosition, "lon_deg")
_ALT = _bounds(schemas.GeodeticPosition, "alt_m")
_EAST = _bounds(schemas.LocalPosition, "east_m")
_NORTH = _bounds(schemas.LocalPosition, "north_m")
_UP = _bounds(schemas.LocalPosition, "up_m")
_AZIMUTH = _bounds(schemas.BearingMeasurement, "azimuth_deg")
_ELEVATION = _bounds(schemas.BearingMeasurement, "elevation_deg")
_SIGMA_AZIMUTH = _bounds(schemas.BearingMeasurement, "sigma_azimuth_deg")
_SIGMA_ELEVATION = _bounds(schemas.BearingMeasurement, "sigma_elevation_deg")
_RANGE = _bounds(schemas.RangeMeasurement, "range_m")
_SIGMA_RANGE = _bounds(schemas.RangeMeasurement, "sigma_m")
_TOA_S = _bounds(schemas.ToaMeasurement, "toa_s")
_SIGMA_TOA = _bounds(schemas.ToaMeasurement, "sigma_s")
_TOLERANCE = _bounds(schemas.Options, "tolerance_m")
_ITERATIONS = _bounds(schemas.Options, "max_iterations")
_LOSS_SCALE = _bounds(schemas.Options, "loss_scale")
_ALTITUDE = _bounds(schemas.Constraints, "altitude_m")
#: The bounds above as tables for the bulk checks: per frame (local, geodetic) and coordinate, and per kind code.
_COORDINATE_BOUNDS = np.array([[_EAST, _NORTH, _UP], [_LAT, _LON, _ALT]], dtype=float)
_VALUE_BOUNDS = np.array([{_AZ: _AZIMUTH, _EL: _ELEVATION, _RG: _RANGE, _TOA: _TOA_S}[k] for k in range(4)])
_SIGMA_BOUNDS = np.array([{_AZ: _SIGMA_AZIMUTH, _EL: _SIGMA_ELEVATION, _RG: _SIGMA_RANGE, _TOA: _SIGMA_TOA}[k]
                          for k in range(4)])
_MEASUREMENTS_MAX = schemas.MAX_FIX_MEASUREMENTS
_STATION_ID_MAX = next(rule.max_length for rule in schemas.Station.model_fields["id"].metadata
                       if getattr(rule, "max_length", None) is not None)


def _coordinates(position: wire.Position, geodetic: bool) -> tuple[float, float, float]:
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


def _position(position: wire.Position, geodetic: bool) -> tuple[float, float, float]:
    """A position as core coordinates within the schema's bounds, ``(lat_rad, lon_rad, alt_m)`` or
    ``(east_m, north_m, up_m)``."""
    a, b, c = _coordinates(position, geodetic)
    if geodetic:
        return math.radians(_number(a, _LAT)), math.radians(_number(b, _LON)), _number(c, _ALT)
    return _number(a, _EAST), _number(b, _NORTH), _number(c, _UP)


#: The renderings of a request that asks for none (one object shared by all such requests).
_PLAIN = Renderings()


def _problem_settings(body: wire.FixBody, frame: str, method: str) -> tuple:
    """The frame row, method, options and renderings of a body with more than stations and measurements
    (``_Reject`` if unusual). The frame row is nine numbers: geodetic (1 or 0), origin ``(lat_rad, lon_rad,
    alt_m)``, known altitude_m, initial guess (core coordinates) and whether that guess is geodetic (1 or 0);
    NaN where not given."""
    geodetic = frame == "wgs84"
    origin = _NAN3 if body.origin is None else _position(body.origin, True)
    options = body.options
    solve, guess, guess_geodetic = _DEFAULT_SOLVE, _NAN3, False
    if options is not UNSET:
        default = _DEFAULT_OPTIONS
        iterations = default.max_iterations if options.max_iterations is UNSET else options.max_iterations
        outliers = default.outliers if options.outliers is UNSET else options.outliers
        absolute_sigma = default.absolute_sigma if options.absolute_sigma is UNSET else options.absolute_sigma
        loss = default.loss if options.loss is UNSET else options.loss
        if not _ITERATIONS[0] <= iterations <= _ITERATIONS[1] or outliers not in _OUTLIERS or loss not in _LOSSES \
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
    if formats is not UNSET and (len(formats) > 2 or any(f not in _FORMATS for f in formats)):
        raise _Reject
    return ((float(geodetic), *origin, altitude, *guess, float(guess_geodetic)), method, solve,
            Renderings(formats) if formats else _PLAIN)


#: The settings of a body with only frame, method, stations and measurements (see :func:`_problem_settings`).
_PLAIN_SETTINGS = {(frame, method): ((float(frame == "wgs84"), *_NAN3, math.nan, *_NAN3, 0.0), method, _DEFAULT_SOLVE,
                                     _PLAIN)
                   for frame in ("wgs84", "local") for method in _METHODS}


def _read(bodies: list, max_fix_cost: int | None = None):
    """Structure checks and raw columns of the problems that decode as :class:`service.wire.FixBody` and look
    plainly valid (the numbers are checked later, in bulk).

    Returns
    -------
    accepted : list of int
    settings : list of tuple
        Per problem: frame row, method, options and renderings (see :func:`_problem_settings`).
    station_counts, measurement_counts : list of int
    station_ids : list of tuple of str
    coordinates : list of float
        Station positions, API units, three per station, flattened (a missing height is 0).
    scalars : list of int
        The scalar measurements' structure, four per measurement (kind, station, bearing, source),
        flattened.
    readings : list of float
        Their values, API units, two per measurement (value, sigma), flattened; a missing azimuth
        sigma is NaN.
    frames : list of float
        The frame rows of the settings, nine per problem, flattened.
    rest : list of int
    """
    accepted, settings, station_counts, measurement_counts, station_ids = [], [], [], [], []
    coordinates, scalars, readings, frames, rest = [], [], [], [], []
    add_coordinates, add_scalar, add_reading = coordinates.extend, scalars.extend, readings.extend
    id_max, unset, nan, plain, coordinates_of = _STATION_ID_MAX, UNSET, math.nan, _PLAIN_SETTINGS, _coordinates
    Bearing, Range = wire.Bearing, wire.Range
    for slot, raw in enumerate(bodies):
        body = wire.as_fix_body(raw)
        if body is None:
            rest.append(slot)
            continue
        n_coordinates, n_scalars, n_readings = len(coordinates), len(scalars), len(readings)
        try:
            frame = _FRAME if body.frame is unset else body.frame
            method = _METHOD if body.method is unset else body.method
            if body.origin is None and body.options is unset and body.constraints is None and body.formats is unset:
                setting = plain.get((frame, method))
                if setting is None:
                    raise _Reject
            elif frame in ("wgs84", "local") and method in _METHODS:
                setting = _problem_settings(body, frame, method)
            else:
                raise _Reject
            geodetic = frame == "wgs84"
            stations = body.stations
            if not 0 < len(stations) <= 256:
                raise _Reject
            ids: dict[str, int] = {}
            for station in stations:
                sid, position = station.id, station.position
                if not 0 < len(sid) <= id_max or sid in ids:
                    raise _Reject
                ids[sid] = len(ids)
                add_coordinates(coordinates_of(position, geodetic))
            measurements = body.measurements
            if not 0 < len(measurements) <= _MEASUREMENTS_MAX or \
                    not fix_within_limit(len(ids), len(measurements), method, setting[2].outliers == "exclude",
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
                        add_scalar((_AZ, station, n_bearings, i, _EL, station, n_bearings, i))
                        add_reading((m.azimuth_deg, sigma_azimuth, elevation, sigma_elevation))
                    elif sigma_elevation is not None:
                        raise _Reject
                    else:
                        add_scalar((_AZ, station, n_bearings, i))
                        add_reading((m.azimuth_deg, sigma_azimuth))
                    n_bearings += 1
                elif kind is Range:
                    add_scalar((_RG, station, -1, i))
                    add_reading((m.range_m, m.sigma_m))
                else:
                    add_scalar((_TOA, station, -1, i))
                    add_reading((m.toa_s, m.sigma_s))
        except _Reject:
            del coordinates[n_coordinates:], scalars[n_scalars:], readings[n_readings:]
            rest.append(slot)
            continue
        accepted.append(slot)
        settings.append(setting)
        frames.extend(setting[0])
        station_counts.append(len(ids))
        station_ids.append(tuple(ids))
        measurement_counts.append((len(scalars) - n_scalars) // 4)
    return (accepted, settings, station_counts, measurement_counts, station_ids, coordinates, scalars, readings,
            frames, rest)


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
        The problems' frame rows (see :func:`_problem_settings`): the first number is 1 for a geodetic frame.
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
                    sigma_bounds[k, 0] <= sigma <= sigma_bounds[k, 1] or (k == _AZ and math.isnan(sigma)))):
                bad[b] = True
            if k == _AZ or k == _EL:
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
    """Read FixRequest bodies (:class:`service.wire.FixBody` structs or parsed JSON) into one core batch.

    A body that is plainly valid (a FixBody, or parsed JSON that converts to
    one, within the bounds of :class:`schemas.FixRequest`, with known and
    unique station ids) is read in bulk: structure problem by problem, numbers
    range-checked for all at once, the frames placed by
    :func:`core.problem_batch_build.build_problem_batch`.
    Any other body is validated by the schema and built by :func:`to_problem`,
    which decide and word its error, and joins the same batch. A body over
    ``max_fix_cost`` (the app's limit; None: no limit) takes the schema's road,
    which words its 422.
    """
    (accepted, settings, station_counts, measurement_counts, station_ids, coordinates, scalars, readings, frames,
     rest) = _read(bodies, max_fix_cost)
    errors: dict[int, dict] = {}
    lean = None
    if accepted:
        station_counts = np.array(station_counts, dtype=np.intp)
        measurement_counts = np.array(measurement_counts, dtype=np.intp)
        frames = np.array(frames, dtype=float).reshape(-1, 9)
        coords = np.array(coordinates, dtype=float).reshape(-1, 3)
        table = np.array(scalars, dtype=np.intp).reshape(-1, 4)
        reading = np.array(readings, dtype=float).reshape(-1, 2)
        bad = np.empty(len(accepted), dtype=bool)
        if _checked_core_units(coords, station_counts, frames, table, reading, measurement_counts,
                               _COORDINATE_BOUNDS, _VALUE_BOUNDS, _SIGMA_BOUNDS, bad):
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
                geodetic_stations=frames[:, 0],
                origin=frames[:, 1:4],
                measurement_counts=measurement_counts,
                kinds=table[:, 0],
                station_index=table[:, 1],
                values=reading[:, 0],
                sigmas=reading[:, 1],
                bearing_index=table[:, 2],
                source_index=table[:, 3],
                altitude_m=frames[:, 4],
                initial_guess=frames[:, 5:8],
                geodetic_guess=frames[:, 8],
            )
    slots = list(accepted)
    methods = [s[1] for s in settings]
    options = [s[2] for s in settings]
    formats = [s[3] for s in settings]
    built: list[Problem] = []
    for slot in rest:
        try:
            request = schemas.FixRequest.model_validate(wire.as_builtins(bodies[slot]),
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


#: A template's slot marker, written raw: the slot's number between NUL bytes, which orjson never writes
#: (it escapes control characters in strings, station ids included).
_SLOT = re.compile(rb"\x00(\d+)\x00")
_NUMPY = orjson.OPT_SERIALIZE_NUMPY
_MAX = np.finfo(np.float64).max
#: The value blocks of a fix body, in their order among its values in :func:`fix_bodies` (the first eleven are
#: numbers), and their widths (``None``: one per residual).
_BLOCKS = {"position": 3, "covariance": 9, "crlb": 9, "error": 8, "residual": None, "normalized": None, "fit": 3,
           "geodetic": 3, "ecef": 3, "covariance_ecef": 9, "coarse": 3, "warnings": 1, "bearing_errors": 1}


@dataclass(frozen=True)
class _Template:
    """The JSON text of the fix bodies of one structure: constant pieces around value slots.

    Attributes
    ----------
    pieces : ndarray of uint8
        The ``S + 1`` constant pieces (before, between and after the slots), joined.
    piece_starts, piece_lengths : ndarray of int, shape ``(S + 1,)``
        Where each piece is in ``pieces``.
    columns : ndarray of int, shape ``(S,)``
        The value that fills each slot: its column among a fix's values.
    """

    pieces: np.ndarray
    piece_starts: np.ndarray
    piece_lengths: np.ndarray
    columns: np.ndarray


def _fix_template(structure: bytes, station_ids: tuple, method: str, source: str) -> _Template:
    """The template of the fix bodies of one structure.

    The body is the FixResponse dict with the structure's own values in place and a marker for each
    value of the fix (positions, covariances, error figures, residual values, warnings...);
    orjson writes it and the text is cut at the markers.

    Parameters
    ----------
    structure : bytes
        A row of :func:`_fix_structures`; its width sets the residual columns among a fix's values (the
        batch's widest problem).
    station_ids : tuple of str
    method, source : str
        The ``method`` and ``covariance_source`` of the fixes.
    """
    row = np.frombuffer(structure, dtype=np.int64)
    width = (row.size - 7) // 5
    n, dof, converged, iterations, geodetic, coarse, bearing_errors = row[:7].tolist()
    stations, sources, kinds, used, excluded = row[7:].reshape(5, width)[:, :n].tolist()
    residuals = zip([station_ids[s] for s in stations], sources, [KIND_NAMES[k] for k in kinds], map(bool, used),
                    map(bool, excluded))
    names: list[tuple[str, int]] = []

    def slot(block: str, column: int = 0) -> orjson.Fragment:
        names.append((block, column))
        return orjson.Fragment(b"\x00%d\x00" % (len(names) - 1))

    def matrix(block: str) -> list:
        return [[slot(block, 3 * i + j) for j in range(3)] for i in range(3)]

    def enu(block: str) -> dict:
        return {"east_m": slot(block, 0), "north_m": slot(block, 1), "up_m": slot(block, 2)}

    body = {
        "method": method,
        "position_local": enu("position"),
        "covariance_enu_m2": matrix("covariance"),
        "covariance_source": source,
        "crlb_enu_m2": matrix("crlb"),
        "error": {
            "cep50_m": slot("error", 0), "sep50_m": slot("error", 1), "vertical_sigma_m": slot("error", 2),
            "gdop": slot("error", 3), "sqrt_trace_m": slot("error", 4),
            "ellipse95": {"semi_major_m": slot("error", 5), "semi_minor_m": slot("error", 6),
                          "orientation_deg": slot("error", 7)},
        },
        "residuals": [
            {"station_id": station, "measurement_index": index, "component": component,
             "residual": slot("residual", m), "normalized": slot("normalized", m), "used": used,
             "excluded": excluded}
            for m, (station, index, component, used, excluded) in enumerate(residuals)
        ],
        "fit": {"chi2": slot("fit", 0), "dof": dof, "p_value": slot("fit", 1), "sigma_scale": slot("fit", 2)},
        "converged": bool(converged),
        "iterations": iterations,
        "warnings": slot("warnings"),
    }
    if geodetic:
        body["position"] = {"lat_deg": slot("geodetic", 0), "lon_deg": slot("geodetic", 1),
                            "alt_m": slot("geodetic", 2)}
        body["position_ecef_m"] = [slot("ecef", i) for i in range(3)]
        body["covariance_ecef_m2"] = matrix("covariance_ecef")
    if coarse:
        body["stages"] = {"coarse": enu("coarse")}
    if bearing_errors:
        body["estimated_bearing_errors_deg"] = slot("bearing_errors")
    parts = _SLOT.split(orjson.dumps(body))
    slots = [names[int(i)] for i in parts[1::2]]
    widths = [width if w is None else w for w in _BLOCKS.values()]
    first = dict(zip(_BLOCKS, np.cumsum([0, *widths[:-1]]).tolist()))
    pieces, piece_starts, piece_lengths = _text_spans(parts[0::2])
    return _Template(np.frombuffer(pieces, dtype=np.uint8), piece_starts, piece_lengths,
                     np.array([first[block] + column for block, column in slots], dtype=np.intp))


#: Templates of fixes with at most this many residuals are kept, the last 1024 used: about 20 KB each at most
#: (128-character station ids), where one of 2048 residuals takes about 0.5 MB (kept, a client could make the
#: cache hold half a gigabyte).
_KEPT_RESIDUALS = 64
_kept_template = functools.lru_cache(maxsize=1024)(_fix_template)


def _template(structure: bytes, station_ids: tuple, method: str, source: str, residuals: int) -> _Template:
    """:func:`_fix_template`, from the cache when its ``residuals`` (the fix's measurement rows) are few enough to
    keep."""
    build = _kept_template if residuals <= _KEPT_RESIDUALS else _fix_template
    return build(structure, station_ids, method, source)


@numba.njit(cache=True, nogil=True)
def _value_spans(values, text_lengths, starts, lengths):
    """Where each value of each fix is in the values' text, and the bytes they take in all.

    Parameters
    ----------
    values : ndarray of uint8
        orjson's text of the B fixes' numbers, ``K`` each, as one flat array (``[a,b,...]``), then ``2 B``
        texts: each fix's warnings, then each fix's bearing errors.
    text_lengths : ndarray of int, shape (2 B,)
        The texts' lengths.
    starts, lengths : ndarray of int, shape ``(B, K + 2)``
        Filled with each value's first byte in ``values`` and its length: a fix's numbers, its warnings and its
        bearing errors.

    Returns
    -------
    int
    """
    size, columns = starts.shape
    total = 0
    at = 1
    for b in range(size):
        for j in range(columns - 2):
            end = at
            while values[end] != 44 and values[end] != 93:  # the comma after a number, or the closing bracket
                end += 1
            starts[b, j], lengths[b, j] = at, end - at
            total += end - at
            at = end + 1
    for j in range(2):
        for b in range(size):
            starts[b, columns - 2 + j], lengths[b, columns - 2 + j] = at, text_lengths[j * size + b]
            total += text_lengths[j * size + b]
            at += text_lengths[j * size + b]
    return total


@numba.njit(cache=True, nogil=True, error_model="numpy")
def _fix_structures(n_measurements, dof, converged, iterations, geodetic, coarse_enu_m, bearing_error_lengths,
                    station_index, source_index, kinds, used, excluded):
    """Each fix body's structure, what its template (:func:`_fix_template`) is made of, as a row of integers.

    Parameters
    ----------
    n_measurements, dof, iterations : ndarray of int64, shape (B,)
    converged, geodetic : ndarray of bool, shape (B,)
    coarse_enu_m : ndarray, shape (B, 3)
        NaN where no coarse stage ran.
    bearing_error_lengths : ndarray of int64, shape (B,)
        The length of each fix's estimated bearing errors text (0: none).
    station_index, source_index : ndarray of int64, shape (B, M)
    kinds : ndarray of int8, shape (B, M)
    used, excluded : ndarray of bool, shape (B, M)

    Returns
    -------
    ndarray of int64, shape (B, 7 + 5 M)
        Per fix: measurement rows, dof, converged, iterations, geodetic, a coarse stage, bearing errors, then
        ``M`` each of station indices, source indices, kind codes, used and excluded flags (padding included).
    """
    size, width = kinds.shape
    out = np.empty((size, 7 + 5 * width), dtype=np.int64)
    for b in range(size):
        row, columns = out[b, :7], out[b, 7:].reshape(5, width)
        row[0], row[1], row[2], row[3] = n_measurements[b], dof[b], converged[b], iterations[b]
        row[4], row[5], row[6] = geodetic[b], not math.isnan(coarse_enu_m[b, 0]), bearing_error_lengths[b] > 0
        for m in range(width):
            columns[0, m], columns[1, m], columns[2, m] = station_index[b, m], source_index[b, m], kinds[b, m]
            columns[3, m], columns[4, m] = used[b, m], excluded[b, m]
    return out


@numba.njit(cache=True, nogil=True)
def _write_bodies(pieces, piece_starts, piece_lengths, columns, rows, values, value_starts, value_lengths, out, at,
                  ends):
    """Write the bodies of ``rows`` from one template into ``out`` from ``at`` on; return where they end.

    Parameters
    ----------
    pieces : ndarray of uint8
        The template's ``S + 1`` constant pieces, joined; ``piece_starts``, ``piece_lengths`` ``(S + 1,)`` say
        where each is.
    columns : ndarray of int, shape ``(S,)``
        The value column that fills each slot.
    rows : ndarray of int, shape ``(G,)``
    values : ndarray of uint8
        The values' text; ``value_starts``, ``value_lengths`` ``(B, W)`` say where each row's values are.
    out : ndarray of uint8
    at : int
    ends : ndarray of int, shape ``(B,)``
        Set at ``rows``: where each body ends in ``out``.
    """
    k = numba.uint64(at)  # unsigned offsets: no negative-index wraparound per byte (twice as fast)
    for b in rows:
        for j in range(columns.size + 1):
            start, length = numba.uint64(piece_starts[j]), numba.uint64(piece_lengths[j])
            for i in range(length):
                out[k + i] = pieces[start + i]
            k += length
            if j < columns.size:
                start, length = numba.uint64(value_starts[b, columns[j]]), numba.uint64(value_lengths[b, columns[j]])
                for i in range(length):
                    out[k + i] = values[start + i]
                k += length
        ends[b] = k
    return k


def _text_spans(texts: list) -> tuple[bytes, np.ndarray, np.ndarray]:
    """``texts`` joined, and where each one is in the join: ``(joined, starts (N,), lengths (N,))``."""
    lengths = np.fromiter(map(len, texts), dtype=np.int64, count=len(texts))
    return b"".join(texts), lengths.cumsum() - lengths, lengths


def _warning_texts(warnings_per_fix) -> list[bytes]:
    """Each fix's warnings as JSON text, written once for the fixes that hold the same warning objects (the
    finisher shares one object among the fixes a warning says the same of)."""
    written: dict[tuple, bytes] = {}
    texts = []
    for warnings in warnings_per_fix:
        if not warnings:
            texts.append(b"[]")
            continue
        key = tuple(map(id, warnings))  # the objects are alive for the whole call: an id names one
        text = written.get(key)
        if text is None:
            text = written[key] = orjson.dumps([{"code": w.code, "message": w.message} for w in warnings])
        texts.append(text)
    return texts


@numba.njit(cache=True, nogil=True, error_model="numpy")
def _fix_numbers(ok, position_enu_m, covariance_enu_m2, crlb_enu_m2, gdop, residuals, normalized, kinds, chi2,
                 p_value, sigma_scale, coarse_enu_m, geodetic, origin_ecef_m, rotation, circle, sphere):
    """Every number of each fix body, in :data:`_BLOCKS` order (the first eleven blocks), in one pass.

    A geodetic fix's covariance and CRLB are written in the east/north/up axes at the fix
    (:func:`core.geodesy.covariance_to_point`), as its error figures and renderings are, and not in the
    common frame's axes at the stations' centroid; a flat frame has one set of axes.

    Parameters
    ----------
    ok : ndarray of bool, shape (B,)
        Fixes whose position and covariance are written (zeros for the others).
    position_enu_m, covariance_enu_m2, crlb_enu_m2 : ndarray, shape (B, 3), (B, 3, 3), (B, 3, 3)
        In the common frame.
    gdop, chi2, p_value, sigma_scale : ndarray, shape (B,)
    residuals, normalized : ndarray, shape (B, M)
        Residuals in model units (angles in radians: written in degrees).
    kinds : ndarray of int8, shape (B, M)
    coarse_enu_m : ndarray, shape (B, 3)
        NaN where no coarse stage ran (written as 0).
    geodetic : ndarray of bool, shape (B,)
        Whether each frame touches the earth.
    origin_ecef_m, rotation : ndarray, shape (B, 3), (B, 3, 3)
        Each frame's placement (:meth:`core.problem_batch.ProblemBatch.frame_placements`).
    circle, sphere : ndarray
        :func:`core.error_summary.radius50_tables`.

    Returns
    -------
    ndarray, shape (B, 50 + 2 M)
    """
    size, width = residuals.shape
    position, covariance, crlb = np.zeros((size, 3)), np.zeros((size, 3, 3)), crlb_enu_m2.copy()
    placed, covariance_ecef = np.empty((size, 6)), np.empty((size, 3, 3))
    turn = np.empty((3, 3))
    for b in range(size):
        r = rotation[b]
        if ok[b]:
            position[b], covariance[b] = position_enu_m[b], covariance_enu_m2[b]
        x, y, z = geodesy.enu_to_ecef_point(position[b, 0], position[b, 1], position[b, 2], origin_ecef_m[b], r)
        lat, lon, alt = geodesy.ecef_to_geodetic_point(x, y, z)
        placed[b, 0], placed[b, 1], placed[b, 2], placed[b, 3], placed[b, 4], placed[b, 5] = lat, lon, alt, x, y, z
        geodesy.covariance_enu_to_ecef_point(covariance[b], r, covariance_ecef[b])
        if ok[b] and geodetic[b]:
            geodesy.covariance_to_point(covariance_enu_m2[b], lat, lon, r, turn, covariance[b])
            geodesy.covariance_to_point(crlb_enu_m2[b], lat, lon, r, turn, crlb[b])
    _, _, orientation, cep, sep, vertical, root_trace, semi_major, semi_minor, _ = summaries_kernel(
        covariance, circle, sphere, True)
    out = np.empty((size, 50 + 2 * width))
    to_degrees = 180.0 / math.pi
    for b in range(size):
        row = out[b]
        row[0:3] = position[b]
        row[3:12] = covariance[b].ravel()
        row[12:21] = crlb[b].ravel()
        row[21], row[22], row[23], row[24] = cep[b], sep[b], vertical[b], gdop[b]
        row[25], row[26], row[27] = root_trace[b], semi_major[b], semi_minor[b]
        row[28] = orientation[b] * to_degrees
        k = 29
        for m in range(width):
            angle = kinds[b, m] == _AZ or kinds[b, m] == _EL
            row[k + m] = residuals[b, m] * to_degrees if angle else residuals[b, m]
            row[k + width + m] = normalized[b, m]
        k += 2 * width
        row[k], row[k + 1], row[k + 2] = chi2[b], p_value[b], sigma_scale[b]
        row[k + 3], row[k + 4], row[k + 5] = placed[b, 0] * to_degrees, placed[b, 1] * to_degrees, placed[b, 2]
        row[k + 6], row[k + 7], row[k + 8] = placed[b, 3], placed[b, 4], placed[b, 5]
        row[k + 9:k + 18] = covariance_ecef[b].ravel()
        for i in range(3):
            coarse = coarse_enu_m[b, i]
            row[k + 18 + i] = 0.0 if math.isnan(coarse) else min(max(coarse, -_MAX), _MAX)
    return out


def fix_bodies(fixes: FixBatch, formats) -> list[dict]:
    """Response bodies of a :class:`core.estimators.FixBatch`: a fix body, or the problem body of its error.

    Conversions (error summaries, geodetic positions, ECEF covariances,
    degrees) run once over the batch, and so does writing their numbers as
    JSON text (one orjson call). Fixes of one structure (the residuals'
    stations, components and flags, the frame, stages...) share a template
    (:func:`_fix_template`); every body is then its template's pieces and
    its values' text in turn, written by one compiled loop per template: no
    Python object per value. A fix asking for renderings is read back from
    its text to make them.

    Parameters
    ----------
    fixes : FixBatch
    formats : sequence of tuple of str, length B

    Returns
    -------
    list of dict
        ``{"ok": True, "fix": JsonObject}`` or ``{"ok": False, "error": problem body}`` per problem.
    """
    batch = fixes.problems
    size = batch.size
    ok = fixes.ok
    coarse = fixes.coarse_position_enu_m
    bearing_errors = [b"" if e is None else orjson.dumps(np.degrees(e).tolist())
                      for e in fixes.estimated_bearing_errors_rad]

    # The text of every value and where it is, columns by block in _BLOCKS' order: the numbers, then the
    # warnings and the bearing errors (one text each per fix).
    numbers = _fix_numbers(ok, *(np.ascontiguousarray(a, dtype=float) for a in (
        fixes.position_enu_m, fixes.covariance_enu_m2, fixes.crlb_enu_m2, fixes.gdop, fixes.residuals,
        fixes.normalized_residuals)), np.ascontiguousarray(batch.kinds, dtype=np.int8),
        *(np.ascontiguousarray(a, dtype=float) for a in (fixes.chi2, fixes.p_value, fixes.sigma_scale, coarse)),
        np.ascontiguousarray(batch.geodetic, dtype=bool), *batch.frame_placements(), *radius50_tables())
    value_texts = _warning_texts(fixes.warnings) + bearing_errors
    values = np.frombuffer(orjson.dumps(numbers.ravel(), option=_NUMPY) + b"".join(value_texts), dtype=np.uint8)
    text_lengths = np.fromiter(map(len, value_texts), dtype=np.int64, count=len(value_texts))
    value_starts = np.empty((size, numbers.shape[1] + 2), dtype=np.int64)
    value_lengths = np.empty_like(value_starts)
    value_bytes = _value_spans(values, text_lengths, value_starts, value_lengths)

    # Fixes of one structure share a template. The structure as a row of integers groups them (padding
    # columns included: rows that differ only there make two groups of one template).
    c = np.ascontiguousarray
    structures = _fix_structures(
        c(batch.n_measurements, dtype=np.int64), c(fixes.dof, dtype=np.int64), c(fixes.converged, dtype=bool),
        c(fixes.iterations, dtype=np.int64), c(batch.geodetic, dtype=bool), c(coarse, dtype=float),
        text_lengths[size:], c(batch.station_index, dtype=np.int64), c(batch.source_index, dtype=np.int64),
        c(batch.kinds, dtype=np.int8), c(fixes.used, dtype=bool), c(fixes.excluded, dtype=bool))
    blob, step = structures.tobytes(), structures.shape[1] * 8
    groups: dict[tuple, list[int]] = {}
    for b in ok.nonzero()[0].tolist():
        groups.setdefault((blob[b * step:(b + 1) * step], batch.station_ids[b]), []).append(b)

    # Each body: its template's pieces and its values in turn, all written into one buffer.
    work = [(_template(structure, ids, fixes.method, fixes.covariance_source, int(batch.n_measurements[members[0]])),
             members) for (structure, ids), members in groups.items()]
    texts: list[bytes | None] = [None] * size
    if work:
        written = np.empty(sum(len(members) * template.pieces.size for template, members in work) + value_bytes,
                           dtype=np.uint8)
        ends = np.empty(size, dtype=np.int64)
        end = 0
        for template, members in work:
            end = _write_bodies(template.pieces, template.piece_starts, template.piece_lengths, template.columns,
                                np.array(members), values, value_starts, value_lengths, written, end, ends)
        ends = ends.tolist()
        view = memoryview(written)  # each body copied out once (no whole-buffer bytes to slice again)
        start = 0
        for _, members in work:
            for b in members:
                texts[b] = bytes(view[start:ends[b]])
                start = ends[b]

    known = {"method": fixes.method}
    out: list[dict] = []
    for b, text in enumerate(texts):
        if text is None:
            out.append({"ok": False, "error": localization_problem(fixes.errors[b])})
            continue
        wanted = formats[b]
        if wanted:
            body = orjson.loads(text)
            if "geojson" in wanted:
                body["geojson"] = fix_geojson(body, wanted)
            if "cot" in wanted:
                body["cot"] = fix_cot(body, wanted)
            text = orjson.dumps(body)
        out.append({"ok": True, "fix": JsonObject(text, known)})
    return out


#: Fix bodies that reach every kernel of this module: geodetic and local frames, every measurement kind, an
#: azimuth without a sigma, a known altitude, renderings, and a body the lean reader hands to the schema.
_WARM_BODIES = [
    {"frame": "wgs84", "formats": ["geojson", "cot"],
     "stations": [{"id": "a", "position": {"lat_deg": 34.0, "lon_deg": 108.0, "alt_m": 400.0}},
                  {"id": "b", "position": {"lat_deg": 34.1, "lon_deg": 108.2, "alt_m": 450.0}},
                  {"id": "c", "position": {"lat_deg": 34.2, "lon_deg": 108.0}}],
     "measurements": [{"type": "bearing", "station_id": "a", "azimuth_deg": 45.0, "elevation_deg": 1.0,
                       "sigma_azimuth_deg": 0.5, "sigma_elevation_deg": 0.5},
                      {"type": "bearing", "station_id": "b", "azimuth_deg": 330.0, "sigma_azimuth_deg": 0.5},
                      {"type": "range", "station_id": "c", "range_m": 20000.0, "sigma_m": 50.0},
                      {"type": "toa", "station_id": "a", "toa_s": 1e-4, "sigma_s": 1e-7},
                      {"type": "toa", "station_id": "b", "toa_s": 1.2e-4, "sigma_s": 1e-7}]},
    {"frame": "local", "method": "taylor_wls", "constraints": {"altitude_m": 1000.0},
     "stations": [{"id": "a", "position": {"east_m": 0.0, "north_m": 0.0}},
                  {"id": "b", "position": {"east_m": 10000.0, "north_m": 0.0}},
                  {"id": "c", "position": {"east_m": 0.0, "north_m": 10000.0, "up_m": 50.0}}],
     "measurements": [{"type": "bearing", "station_id": s, "azimuth_deg": a} for s, a in
                      (("a", 40.0), ("b", 300.0), ("c", 150.0))]},
    {"stations": [], "measurements": []},
]


def compile_kernels() -> None:
    """Compile (or load from numba's on-disk cache) every kernel a request can reach: the core's
    (:func:`core.kernels.compile_kernels`) and this module's, by reading, solving and writing
    :data:`_WARM_BODIES`. Run at install and image build time (which fill the cache) and in the lifespan."""
    core_kernels.compile_kernels()
    fix_results(_WARM_BODIES)


def fix_results(bodies: list, request_ids=None, should_stop=None, methods_run: list | None = None,
                max_fix_cost: int | None = None) -> list[dict]:
    """Results of FixRequest bodies (see :func:`read_fix_requests`): read, solved and written as one batch.

    A failure that is no problem's own error (a bug) fails only the bodies
    that meet it: the shared call's exception is logged, each body is then
    solved alone, and a body that fails alone too gets a 500
    ``internal_error`` in its slot (logged with its request id).

    Parameters
    ----------
    bodies : list
        Parsed JSON of each request.
    request_ids : str or sequence of str, optional
        Written into each error body (one for all, or one per body).
    should_stop : callable returning bool, optional
        Asked before each part is solved (:func:`core.estimators.iter_solutions`: deadline, disconnect,
        shutdown).
    methods_run : list, optional
        Replaced by the method of each body, in order, whatever its outcome: the estimator that ran (``auto``
        resolved), or the requested method of a body refused before solving (what metrics count a fix under).
    max_fix_cost : int, optional
        The app's ``max_fix_cost``: a body over it fails its slot (422); None: no limit.

    Returns
    -------
    list of dict
        ``{"index", "ok": True, "fix"}`` or ``{"index", "ok": False, "error"}`` per body, in order.

    Raises
    ------
    core.parallel.Stopped
        When ``should_stop`` said so.
    """
    if request_ids is None or isinstance(request_ids, str):
        request_ids = [request_ids] * len(bodies)
    ran: list = [None] * len(bodies)
    results = None
    if len(bodies) > 1:
        try:
            results = _shared_results(bodies, request_ids, should_stop, ran, max_fix_cost)
        except Stopped:
            raise
        except Exception:
            logger.exception("shared solve of %d fixes failed; solving each alone", len(bodies))
    if results is None:
        results = [{**_alone(body, request_id, should_stop, ran, slot, max_fix_cost), "index": slot}
                   for slot, (body, request_id) in enumerate(zip(bodies, request_ids))]
    if methods_run is not None:
        methods_run[:] = ran
    return results


def _alone(body, request_id: str | None, should_stop, ran: list, slot: int, max_fix_cost: int | None) -> dict:
    """One body's result, solved alone (its method set in ``ran[slot]``); a bug is its slot's 500 ``internal_error``."""
    one = [None]
    try:
        return _shared_results([body], [request_id], should_stop, one, max_fix_cost)[0]
    except Stopped:
        raise
    except Exception:
        logger.exception("fix failed", extra={"request_id": request_id})
        return {"ok": False, "error": problem_body(500, "internal_error",
                                                   f"internal error; quote request id {request_id}",
                                                   request_id=request_id)}
    finally:
        ran[slot] = one[0] if one[0] is not None else wire.requested_method(body)


def _shared_results(bodies: list, request_ids: list, should_stop, ran: list, max_fix_cost: int | None) -> list[dict]:
    """:func:`fix_results` as one shared read, solve and write (chunk by chunk), which any exception fails whole.

    ``ran[slot]`` is set to the method each body ran with (the requested one when it was refused before solving).
    """
    results: list[dict | None] = [None] * len(bodies)

    def put(slot: int, result: dict, method) -> None:
        if not result["ok"]:
            for_request(result["error"], request_ids[slot])
        results[slot] = {"index": slot, **result}
        ran[slot] = method

    # Read in chunks of a solve part, each set solving on the solver threads while the next one is read
    # (reading holds the GIL, the compiled solves do not), then write every chunk's fixes in turn.
    chunks = [group[start:start + PART_PROBLEMS] for group in _size_classes(bodies)
              for start in range(0, len(group), PART_PROBLEMS)]
    started = []
    try:
        for chunk in chunks:
            read = read_fix_requests([bodies[slot] for slot in chunk], max_fix_cost)
            for j, error in read.errors.items():
                put(chunk[j], {"ok": False, "error": error}, wire.requested_method(bodies[chunk[j]]))
            if read.batch is not None:
                started.append((chunk, read, iter_solutions(read.batch, read.methods, read.options, should_stop,
                                                            background=len(chunks) > 1)))
        for chunk, read, solutions in started:
            for rows, fixes in solutions:
                if isinstance(fixes, LocalizationError):
                    resolved = resolve_methods(read.batch, read.methods)
                    for r in rows.tolist():
                        put(chunk[read.slots[r]], {"ok": False, "error": localization_problem(fixes)}, resolved[r])
                    continue
                for r, result in zip(rows.tolist(), fix_bodies(fixes, [read.formats[r] for r in rows])):
                    put(chunk[read.slots[r]], result, fixes.method)
    finally:
        for *_, solutions in started:
            solutions.close()
    return results


def _size_classes(bodies: list) -> list[list[int]]:
    """The slots of ``bodies`` in groups of like size, each to be read as one batch.

    A batch pads every problem to its largest, so reading all at once made
    memory grow with the number of problems times the largest one: 9,000
    four-bearing problems and one of 1,024 bearings took 750 MB more than
    the 9,000 alone, and twice the time. Grouped by
    :func:`core.problem_batch.size_groups` on each body's station and
    measurement counts (a bearing is one or two rows), a problem is padded
    to at most four times its own rows. Anything but a problem counts as size 1.
    """
    stations = np.ones(len(bodies), dtype=np.intp)
    measurements = np.ones(len(bodies), dtype=np.intp)
    for slot, body in enumerate(bodies):
        if type(body) is wire.FixBody:
            stations[slot], measurements[slot] = len(body.stations), len(body.measurements)
        elif type(body) is dict:
            listed = body.get("stations"), body.get("measurements")
            if type(listed[0]) is list:
                stations[slot] = len(listed[0])
            if type(listed[1]) is list:
                measurements[slot] = len(listed[1])
    return [group.tolist() for group in size_groups(measurements, stations)]
