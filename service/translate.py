"""The one translation between HTTP schemas (degrees, request order) and core types.

Responses are built as plain dicts (serialised by orjson) rather than
re-validated models: the schema documents them and the tests check that every
response validates against it.
"""

from __future__ import annotations

import math

import numpy as np

from core import geodesy
from core.accuracy import error_summary
from core.batch import ProblemBatch, build_problem_batch
from core.estimators import Fix, SolveOptions
from core.measurements import Kind
from core.problem import Bearing, GeodeticPoint, LocalPoint, Problem, Range, TimeOfArrival, build_problem
from service import schemas
from service.limits import fix_within_limit

_COMPONENT = {Kind.AZIMUTH: "azimuth", Kind.ELEVATION: "elevation", Kind.RANGE: "range", Kind.TOA: "toa"}
_COMPONENT_NAMES = {int(k): name for k, name in _COMPONENT.items()}
_AZ, _EL, _RG, _TOA = int(Kind.AZIMUTH), int(Kind.ELEVATION), int(Kind.RANGE), int(Kind.TOA)
_ANGLE_CODES = frozenset((_AZ, _EL))


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


def to_options(request: schemas.FixRequest) -> SolveOptions:
    o = request.options
    return SolveOptions(max_iterations=o.max_iterations, tolerance_m=o.tolerance_m, variant=o.variant)


def crlb_problem(request: schemas.CrlbRequest) -> tuple[Problem, np.ndarray]:
    """A problem whose measurements are the sensors' kinds, and the target in its frame."""
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
        from core.errors import InvalidInput

        raise InvalidInput("the sensors measure nothing", ("sensors",))
    problem = build_problem(
        stations=[(s.id, to_point(s.position)) for s in request.stations],
        measurements=measurements,
        origin=None if request.origin is None else to_point(request.origin),
        altitude_m=_altitude(request.constraints),
    )
    target = to_point(request.target)
    if isinstance(target, GeodeticPoint):
        if not problem.frame.is_geodetic:
            from core.errors import InvalidInput

            raise InvalidInput("a geodetic target needs a geodetic frame or an origin", ("target",))
        target_enu = problem.frame.from_geodetic(target.lat_rad, target.lon_rad, target.alt_m)
    else:
        target_enu = np.array([target.east_m, target.north_m, target.up_m])
    return problem, target_enu


def _matrix(m) -> list[list[float]]:
    return np.asarray(m, dtype=float).tolist()


def _local(p) -> dict:
    return {"east_m": float(p[0]), "north_m": float(p[1]), "up_m": float(p[2])}


def error_dict(summary, i: int = 0) -> dict:
    return {
        "cep50_m": float(summary.cep50_m[i]),
        "sep50_m": float(summary.sep50_m[i]),
        "vertical_sigma_m": float(summary.vertical_sigma_m[i]),
        "gdop": float(summary.gdop_m[i]),
        "ellipse95": {
            "semi_major_m": float(summary.ellipse_semi_major_m[i]),
            "semi_minor_m": float(summary.ellipse_semi_minor_m[i]),
            "orientation_deg": float(np.degrees(summary.ellipse_orientation_rad[i])),
        },
    }


def _residual_value(kind: int, value: float) -> float:
    return math.degrees(value) if kind in _ANGLE_CODES else float(value)


def fix_to_dict(problem: Problem, fix: Fix, formats=(), summary=None, index: int = 0) -> dict:
    """The response body of one fix.

    Parameters
    ----------
    problem, fix
    formats : sequence of {"geojson", "cot"}
    summary : core.accuracy.ErrorSummary, optional
        Precomputed for a batch (then ``index`` selects this fix).
    """
    if summary is None:
        summary, index = error_summary(fix.covariance_enu_m2), 0
    p = fix.position_enu_m
    names = problem.station_ids
    body: dict = {
        "method": fix.method,
        "position_local": _local(p),
        "covariance_enu_m2": _matrix(fix.covariance_enu_m2),
        "covariance_source": fix.covariance_source,
        "crlb_enu_m2": _matrix(fix.crlb_enu_m2),
        "error": error_dict(summary, index),
        "residuals": [
            {
                "station_id": names[s],
                "measurement_index": src,
                "component": _COMPONENT_NAMES[k],
                "residual": _residual_value(k, r),
                "normalized": n,
            }
            for s, src, k, r, n in zip(problem.station_index.tolist(), problem.source_index.tolist(),
                                       problem.kinds.tolist(), fix.residuals.tolist(),
                                       fix.normalized_residuals.tolist())
        ],
        "fit": {"chi2": fix.chi2, "dof": fix.dof, "p_value": fix.p_value, "sigma_scale": fix.sigma_scale},
        "converged": fix.converged,
        "iterations": fix.iterations,
        "warnings": [{"code": w.code, "message": w.message} for w in fix.warnings],
    }
    if problem.frame.is_geodetic:
        ecef = problem.frame.to_ecef(p)
        lat, lon, alt = geodesy.ecef_to_geodetic(ecef)
        rotation = problem.frame.ecef_to_enu
        body["position"] = {"lat_deg": math.degrees(lat), "lon_deg": math.degrees(lon), "alt_m": float(alt)}
        body["position_ecef_m"] = ecef.tolist()
        body["covariance_ecef_m2"] = _matrix(rotation.T @ np.asarray(fix.covariance_enu_m2, dtype=float) @ rotation)
    if fix.coarse_position_enu_m is not None:
        body["stages"] = {"coarse": _local(fix.coarse_position_enu_m)}
    if fix.estimated_bearing_errors_rad is not None:
        body["estimated_bearing_errors_deg"] = np.degrees(fix.estimated_bearing_errors_rad).tolist()
    if "geojson" in formats:
        body["geojson"] = _geojson(body)
    if "cot" in formats:
        body["cot"] = _cot(body)
    return body


def _geojson(body: dict) -> dict:
    """A GeoJSON Feature (RFC 7946: lon, lat, alt) with the error summary as properties."""
    properties = {"method": body["method"], **body["error"]}
    if "position" not in body:
        return {"type": "Feature", "geometry": None, "properties": properties}
    pos = body["position"]
    return {"type": "Feature",
            "geometry": {"type": "Point", "coordinates": [pos["lon_deg"], pos["lat_deg"], pos["alt_m"]]},
            "properties": properties}


def _cot(body: dict) -> str | None:
    """A Cursor-on-Target event (ce = CEP50 scaled to ~90 %, le = vertical 90 %)."""
    if "position" not in body:
        return None
    pos, err = body["position"], body["error"]
    ce = 2.146 / 1.1774 * err["cep50_m"]
    le = 1.645 * err["vertical_sigma_m"]
    return (f'<event version="2.0" uid="passive-locator-fix" type="a-u-G" how="m-g">'
            f'<point lat="{pos["lat_deg"]:.8f}" lon="{pos["lon_deg"]:.8f}" hae="{pos["alt_m"]:.2f}" '
            f'ce="{ce:.1f}" le="{le:.1f}"/></event>')


# --- The batch path: many fix requests straight from parsed JSON to one core batch, and back. ---

_GEODETIC_KEYS = frozenset(schemas.GeodeticPosition.model_fields)
_LOCAL_KEYS = frozenset(schemas.LocalPosition.model_fields)
_REQUEST_KEYS = frozenset(schemas.FixRequest.model_fields)
_STATION_KEYS = frozenset(schemas.Station.model_fields)
_BEARING_KEYS = frozenset(schemas.BearingMeasurement.model_fields)
_RANGE_KEYS = frozenset(schemas.RangeMeasurement.model_fields)
_TOA_KEYS = frozenset(schemas.ToaMeasurement.model_fields)
_OPTION_KEYS = frozenset(schemas.Options.model_fields)
_CONSTRAINT_KEYS = frozenset(schemas.Constraints.model_fields)
_FORMATS = frozenset(("geojson", "cot"))
_ML_METHODS = frozenset(("ml", "auto"))
_DEFAULT_OPTIONS = schemas.Options()
_DEFAULT_KEY = (_DEFAULT_OPTIONS.max_iterations, _DEFAULT_OPTIONS.tolerance_m)
#: A request with only these fields needs no per-field settings beyond frame and method.
_PLAIN_KEYS = frozenset(("frame", "method", "stations", "measurements"))
_NAN3 = (math.nan, math.nan, math.nan)


def _bounds(model, name: str) -> tuple[float, float, bool, bool]:
    """``(low, high, low_inclusive, high_inclusive)`` of a float field, read from its schema."""
    low, high, low_in, high_in = -math.inf, math.inf, True, True
    for rule in model.model_fields[name].metadata:
        if getattr(rule, "ge", None) is not None:
            low, low_in = float(rule.ge), True
        if getattr(rule, "gt", None) is not None:
            low, low_in = float(rule.gt), False
        if getattr(rule, "le", None) is not None:
            high, high_in = float(rule.le), True
        if getattr(rule, "lt", None) is not None:
            high, high_in = float(rule.lt), False
    return low, high, low_in, high_in


class _Reject(Exception):
    """The lean reader cannot vouch for this problem: the full schema path decides."""


def _number(value, bounds=None) -> float:
    if type(value) is not float and type(value) is not int:
        raise _Reject
    value = float(value)
    if not math.isfinite(value):
        raise _Reject
    if bounds is not None:
        low, high, low_in, high_in = bounds
        if not ((low <= value if low_in else low < value) and (value <= high if high_in else value < high)):
            raise _Reject
    return value


def _optional_number(body: dict, key: str, bounds=None):
    value = body.get(key)
    return None if value is None else _number(value, bounds)


_LAT = _bounds(schemas.GeodeticPosition, "lat_deg")
_LON = _bounds(schemas.GeodeticPosition, "lon_deg")
_ALT = _bounds(schemas.GeodeticPosition, "alt_m")
_AZIMUTH = _bounds(schemas.BearingMeasurement, "azimuth_deg")
_ELEVATION = _bounds(schemas.BearingMeasurement, "elevation_deg")
_SIGMA_AZIMUTH = _bounds(schemas.BearingMeasurement, "sigma_azimuth_deg")
_SIGMA_ELEVATION = _bounds(schemas.BearingMeasurement, "sigma_elevation_deg")
_RANGE = _bounds(schemas.RangeMeasurement, "range_m")
_SIGMA_RANGE = _bounds(schemas.RangeMeasurement, "sigma_m")
_SIGMA_TOA = _bounds(schemas.ToaMeasurement, "sigma_s")
_TOLERANCE = _bounds(schemas.Options, "tolerance_m")
_LOCAL = _bounds(schemas.LocalPosition, "east_m")
_TOA_TIME = _bounds(schemas.ToaMeasurement, "toa_s")
_ALTITUDE = _bounds(schemas.Constraints, "altitude_m")
_MEASUREMENTS_MAX = schemas.MAX_FIX_MEASUREMENTS
_STATION_ID_MAX = next(rule.max_length for rule in schemas.Station.model_fields["id"].metadata
                       if getattr(rule, "max_length", None) is not None)
_ABSENT = object()


def _position(body, geodetic: bool) -> tuple[float, float, float]:
    """A position dict as core coordinates: ``(lat_rad, lon_rad, alt_m)`` or ``(east_m, north_m, up_m)``."""
    if type(body) is not dict:
        raise _Reject
    if geodetic:
        if not body.keys() <= _GEODETIC_KEYS:
            raise _Reject
        return (math.radians(_number(body["lat_deg"], _LAT)), math.radians(_number(body["lon_deg"], _LON)),
                _number(body.get("alt_m", 0.0), _ALT))
    if not body.keys() <= _LOCAL_KEYS or "lat_deg" in body or "lon_deg" in body:
        raise _Reject
    return _number(body["east_m"], _LOCAL), _number(body["north_m"], _LOCAL), _number(body.get("up_m", 0.0), _LOCAL)


def _station_id(value) -> str:
    if type(value) is not str or not 0 < len(value) <= _STATION_ID_MAX:
        raise _Reject
    return value


def _problem_settings(body: dict) -> tuple:
    """Frame, origin, options, guess, altitude and formats of one FixRequest dict (``_Reject`` if unusual)."""
    frame = body.get("frame", "wgs84")
    if frame != "wgs84" and frame != "local":
        raise _Reject
    geodetic = frame == "wgs84"
    if body.get("method", "auto") not in _ML_METHODS:
        raise _Reject
    origin = body.get("origin")
    origin = _NAN3 if origin is None else _position(origin, True)
    options = body.get("options", _ABSENT)
    key, guess, guess_geodetic = _DEFAULT_KEY, _NAN3, False
    if options is not _ABSENT:
        if type(options) is not dict or not options.keys() <= _OPTION_KEYS:
            raise _Reject
        iterations = options.get("max_iterations", _DEFAULT_OPTIONS.max_iterations)
        if type(iterations) is not int or not 1 <= iterations <= 1000:
            raise _Reject
        key = (iterations, _number(options.get("tolerance_m", _DEFAULT_OPTIONS.tolerance_m), _TOLERANCE))
        variant = options.get("variant")
        if variant is not None and (type(variant) is not str or len(variant) > 32):
            raise _Reject
        raw = options.get("initial_guess")
        if raw is not None:
            guess_geodetic = type(raw) is dict and ("lat_deg" in raw or "lon_deg" in raw)
            if guess_geodetic and not geodetic and math.isnan(origin[0]):
                raise _Reject
            guess = _position(raw, guess_geodetic)
    constraints = body.get("constraints")
    altitude = math.nan
    if constraints is not None:
        if type(constraints) is not dict or not constraints.keys() <= _CONSTRAINT_KEYS:
            raise _Reject
        value = _optional_number(constraints, "altitude_m", _ALTITUDE)
        altitude = math.nan if value is None else value
    formats = body.get("formats", ())
    if formats != ():
        if type(formats) is not list or len(formats) > 2 or any(type(f) is not str or f not in _FORMATS
                                                                 for f in formats):
            raise _Reject
        formats = tuple(formats)
    return geodetic, origin, key, guess, guess_geodetic, altitude, formats


def _read(bodies: list):
    """Structure checks and raw columns of the problems that look plainly valid (numbers are checked later, in bulk).

    Returns
    -------
    accepted : list of int
    settings : list of tuple (see :func:`_problem_settings`)
    station_counts, measurement_counts : list of int
    station_ids : list of tuple of str
    coordinates : list
        Raw station position values, API units, three per station, flattened.
    scalars : list
        Raw scalar measurements, API units, six per measurement (kind, station, value, sigma,
        bearing, source), flattened.
    rest : list of int
    """
    accepted, settings, station_counts, measurement_counts, station_ids = [], [], [], [], []
    coordinates, scalars, rest = [], [], []
    add_coordinates, add_scalar = coordinates.extend, scalars.extend
    geodetic_keys, local_keys, station_keys = _GEODETIC_KEYS, _LOCAL_KEYS, _STATION_KEYS
    bearing_keys, range_keys, toa_keys, id_max = _BEARING_KEYS, _RANGE_KEYS, _TOA_KEYS, _STATION_ID_MAX
    plain = {"wgs84": (True, _NAN3, _DEFAULT_KEY, _NAN3, False, math.nan, ()),
             "local": (False, _NAN3, _DEFAULT_KEY, _NAN3, False, math.nan, ())}
    for slot, body in enumerate(bodies):
        n_coordinates, n_scalars = len(coordinates), len(scalars)
        try:
            if type(body) is not dict:
                raise _Reject
            keys = body.keys()
            if keys <= _PLAIN_KEYS and body.get("method", "auto") in _ML_METHODS:
                setting = plain.get(body.get("frame", "wgs84"))
                if setting is None:
                    raise _Reject
            elif keys <= _REQUEST_KEYS:
                setting = _problem_settings(body)
            else:
                raise _Reject
            geodetic = setting[0]
            stations = body["stations"]
            if type(stations) is not list or not 0 < len(stations) <= 256:
                raise _Reject
            ids: dict[str, int] = {}
            for station in stations:
                if type(station) is not dict or station.keys() != station_keys:
                    raise _Reject
                sid, position = station["id"], station["position"]
                if type(sid) is not str or not 0 < len(sid) <= id_max or sid in ids or type(position) is not dict:
                    raise _Reject
                ids[sid] = len(ids)
                if geodetic:
                    if not position.keys() <= geodetic_keys:
                        raise _Reject
                    add_coordinates((position["lat_deg"], position["lon_deg"], position.get("alt_m", 0.0)))
                else:
                    if not position.keys() <= local_keys or "lat_deg" in position or "lon_deg" in position:
                        raise _Reject
                    add_coordinates((position["east_m"], position["north_m"], position.get("up_m", 0.0)))
            measurements = body["measurements"]
            if type(measurements) is not list or not 0 < len(measurements) <= _MEASUREMENTS_MAX \
                    or not fix_within_limit(len(ids), len(measurements)):
                raise _Reject
            n_bearings = 0
            for i, m in enumerate(measurements):
                if type(m) is not dict:
                    raise _Reject
                kind = m.get("type")
                station = ids.get(m.get("station_id"))
                if station is None:
                    raise _Reject
                if kind == "bearing":
                    if not m.keys() <= bearing_keys:
                        raise _Reject
                    add_scalar((_AZ, station, m["azimuth_deg"], m["sigma_azimuth_deg"], n_bearings, i))
                    elevation, sigma_elevation = m.get("elevation_deg"), m.get("sigma_elevation_deg")
                    if elevation is not None:
                        if sigma_elevation is None:
                            raise _Reject
                        add_scalar((_EL, station, elevation, sigma_elevation, n_bearings, i))
                    elif sigma_elevation is not None:
                        raise _Reject
                    n_bearings += 1
                elif kind == "range":
                    if m.keys() != range_keys:
                        raise _Reject
                    add_scalar((_RG, station, m["range_m"], m["sigma_m"], -1, i))
                elif kind == "toa":
                    if m.keys() != toa_keys:
                        raise _Reject
                    add_scalar((_TOA, station, m["toa_s"], m["sigma_s"], -1, i))
                else:
                    raise _Reject
        except (_Reject, KeyError, TypeError):
            del coordinates[n_coordinates:], scalars[n_scalars:]
            rest.append(slot)
            continue
        accepted.append(slot)
        settings.append(setting)
        station_counts.append(len(ids))
        station_ids.append(tuple(ids))
        measurement_counts.append((len(scalars) - n_scalars) // 6)
    return accepted, settings, station_counts, measurement_counts, station_ids, coordinates, scalars, rest


def _numeric(flat: list, width: int) -> tuple[np.ndarray, np.ndarray]:
    """Rows of raw JSON numbers (flattened) as floats ``(R, width)``, and which rows hold only numbers.

    JSON numbers convert as pydantic converts them; a row with anything else (a boolean, which the strict
    schema refuses, a string, null, a list, a huge integer) is marked for the full path.
    """
    try:
        table = np.array(flat) if flat and bool not in set(map(type, flat)) else None
    except ValueError:  # a list where a number belongs: ragged
        table = None
    if table is not None and table.dtype.kind in "fiu":
        return table.astype(float, copy=False).reshape(-1, width), np.ones(len(flat) // width, dtype=bool)
    rows = [flat[i:i + width] for i in range(0, len(flat), width)]
    good = np.array([all(type(v) in (float, int) and abs(v) < 1e300 for v in row) for row in rows], dtype=bool)
    table = np.array([row if ok else [0.0] * width for row, ok in zip(rows, good)], dtype=float).reshape(-1, width)
    return table, good


def _within(values, bounds) -> np.ndarray:
    low, high, low_in, high_in = bounds
    above = values >= low if low_in else values > low
    below = values <= high if high_in else values < high
    return above & below


def to_problem_batch(bodies: list) -> tuple[list[int], list[tuple[int, float]], list[tuple[str, ...]],
                                            ProblemBatch | None, list[int]]:
    """Read FixRequest dicts straight into one core batch, for the ML problems the lean reader vouches for.

    A problem is taken when it is plainly valid (the exact fields, the types
    and bounds of :class:`schemas.FixRequest`, known and unique station ids),
    asks for ``ml`` or for ``auto`` with every sigma given (which resolves to
    ML), and builds exactly as :func:`to_problem` would build it. Anything
    else is left to the full path (``FixRequest.model_validate``,
    :func:`to_problem`, :func:`core.estimators.solve_many`), which decides
    and words its errors. Structure is checked problem by problem; numbers
    are converted and range-checked for the whole batch at once.

    Parameters
    ----------
    bodies : list
        Parsed JSON of each problem.

    Returns
    -------
    slots : list of int
        Request index of each batch row.
    options : list of (int, float)
        ``(max_iterations, tolerance_m)`` of each row.
    formats : list of tuple of str
        Extra renderings asked for by each row.
    batch : ProblemBatch or None
        None when no problem was taken.
    rest : list of int
        Request indices for the full path, in request order.
    """
    accepted, settings, station_counts, measurement_counts, station_ids, coordinates, scalars, rest = _read(bodies)
    if not accepted:
        return [], [], [], None, rest
    station_counts = np.array(station_counts)
    measurement_counts = np.array(measurement_counts)
    station_owner = np.repeat(np.arange(len(accepted)), station_counts)
    scalar_owner = np.repeat(np.arange(len(accepted)), measurement_counts)
    geodetic = np.array([s[0] for s in settings], dtype=bool)

    coords, coords_ok = _numeric(coordinates, 3)
    table, scalars_ok = _numeric(scalars, 6)
    kinds = table[:, 0].astype(np.int8)
    values, sigmas = table[:, 2], table[:, 3]
    on_earth = geodetic[station_owner]
    coords_ok &= np.all(np.isfinite(coords), axis=-1)
    coords_ok &= ~on_earth | (_within(coords[:, 0], _LAT) & _within(coords[:, 1], _LON) & _within(coords[:, 2], _ALT))
    coords_ok &= on_earth | np.all(_within(coords, _LOCAL), axis=-1)
    is_az, is_el, is_range, is_toa = kinds == _AZ, kinds == _EL, kinds == _RG, kinds == _TOA
    scalars_ok &= np.isfinite(values) & np.isfinite(sigmas)
    scalars_ok &= ~is_az | (_within(values, _AZIMUTH) & _within(sigmas, _SIGMA_AZIMUTH))
    scalars_ok &= ~is_el | (_within(values, _ELEVATION) & _within(sigmas, _SIGMA_ELEVATION))
    scalars_ok &= ~is_range | (_within(values, _RANGE) & _within(sigmas, _SIGMA_RANGE))
    scalars_ok &= ~is_toa | (_within(values, _TOA_TIME) & _within(sigmas, _SIGMA_TOA))
    bad = np.zeros(len(accepted), dtype=bool)
    bad[station_owner[~coords_ok]] = True
    bad[scalar_owner[~scalars_ok]] = True
    if np.any(bad):
        rest = sorted(rest + [accepted[i] for i in np.flatnonzero(bad)])
        keep = np.flatnonzero(~bad)
        if keep.size == 0:
            return [], [], [], None, rest
        station_keep, scalar_keep = ~bad[station_owner], ~bad[scalar_owner]
        accepted = [accepted[i] for i in keep]
        settings = [settings[i] for i in keep]
        station_ids = [station_ids[i] for i in keep]
        station_counts, measurement_counts, geodetic = station_counts[keep], measurement_counts[keep], geodetic[keep]
        coords, on_earth = coords[station_keep], on_earth[station_keep]
        table, kinds, is_az, is_el = table[scalar_keep], kinds[scalar_keep], is_az[scalar_keep], is_el[scalar_keep]
        values, sigmas = table[:, 2], table[:, 3]

    coords = np.where(on_earth[:, None], np.concatenate([np.radians(coords[:, :2]), coords[:, 2:]], axis=-1), coords)
    angle = is_az | is_el
    batch = build_problem_batch(
        station_counts=station_counts,
        station_ids=station_ids,
        station_coordinates=coords,
        geodetic_stations=geodetic,
        origin=np.array([s[1] for s in settings], dtype=float),
        measurement_counts=measurement_counts,
        kinds=kinds,
        station_index=table[:, 1].astype(np.intp),
        values=np.where(angle, np.radians(values), values),
        sigmas=np.where(angle, np.radians(sigmas), sigmas),
        bearing_index=table[:, 4].astype(np.intp),
        source_index=table[:, 5].astype(np.intp),
        altitude_m=np.array([s[5] for s in settings], dtype=float),
        initial_guess=np.array([s[3] for s in settings], dtype=float),
        geodetic_guess=np.array([s[4] for s in settings], dtype=bool),
    )
    return accepted, [s[2] for s in settings], [s[6] for s in settings], batch, rest


#: Error summaries are computed this many at a time: their quadrature arrays (B x 192) then stay in cache
#: (about four times faster than one pass over 10,000 covariances).
_SUMMARY_CHUNK = 256


def batch_error_summary(fixes):
    """Error summaries of a FixBatch's covariances (failed rows get a zero covariance's)."""
    ok = np.ones(fixes.problems.size, dtype=bool)
    ok[list(fixes.errors)] = False
    return _error_summaries(np.where(ok[:, None, None], fixes.covariance_enu_m2, 0.0))


def _error_summaries(covariance_enu_m2):
    """:func:`core.accuracy.error_summary` of ``(B, 3, 3)`` covariances, in cache-sized chunks."""
    parts = [error_summary(covariance_enu_m2[i:i + _SUMMARY_CHUNK])
             for i in range(0, max(len(covariance_enu_m2), 1), _SUMMARY_CHUNK)]
    if len(parts) == 1:
        return parts[0]
    return type(parts[0])(*(np.concatenate([getattr(p, f) for p in parts])
                            for f in parts[0].__dataclass_fields__))


def fix_batch_to_dicts(fixes, formats, summary=None) -> list[dict | None]:
    """Response bodies of a :class:`core.estimators.ml.FixBatch`, as :func:`fix_to_dict` gives them one by one.

    Conversions (error summaries, geodetic positions, ECEF covariances,
    degrees) run once over the batch; only the dicts are built per fix. The
    matrices and the ECEF position are numpy views (orjson's
    ``OPT_SERIALIZE_NUMPY`` writes them byte for byte as it writes lists), which
    spares some fifty Python objects per fix.

    Parameters
    ----------
    fixes : FixBatch
    formats : sequence of tuple of str, length B
    summary : core.accuracy.ErrorSummary, optional
        Of ``fixes.covariance_enu_m2`` (see :func:`batch_error_summary`), when already computed.

    Returns
    -------
    list of dict or None
        None for the rows in ``fixes.errors``.
    """
    batch = fixes.problems
    size = batch.size
    ok = np.ones(size, dtype=bool)
    ok[list(fixes.errors)] = False
    position = np.where(ok[:, None], fixes.position_enu_m, 0.0)
    covariance = np.where(ok[:, None, None], fixes.covariance_enu_m2, 0.0)
    if summary is None:
        summary = batch_error_summary(fixes)
    geodetic = batch.geodetic
    o = batch.origin
    ecef = geodesy.enu_to_ecef(position, o[:, 0], o[:, 1], o[:, 2])
    lat, lon, alt = geodesy.ecef_to_geodetic(ecef)
    rotation = geodesy.ecef_to_enu_rotation(o[:, 0], o[:, 1])
    covariance_ecef = np.swapaxes(rotation, -1, -2) @ covariance @ rotation

    position_l = position.tolist()
    covariance_l = list(np.ascontiguousarray(covariance))
    crlb_l = list(np.ascontiguousarray(fixes.crlb_enu_m2))
    ecef_l = list(np.ascontiguousarray(ecef))
    covariance_ecef_l = list(np.ascontiguousarray(covariance_ecef))
    lat_l, lon_l, alt_l = np.degrees(lat).tolist(), np.degrees(lon).tolist(), alt.tolist()
    cep, sep = summary.cep50_m.tolist(), summary.sep50_m.tolist()
    vertical, gdop = summary.vertical_sigma_m.tolist(), summary.gdop_m.tolist()
    major, minor = summary.ellipse_semi_major_m.tolist(), summary.ellipse_semi_minor_m.tolist()
    orientation = np.degrees(summary.ellipse_orientation_rad).tolist()
    is_angle = (batch.kinds == Kind.AZIMUTH) | (batch.kinds == Kind.ELEVATION)
    residual_l = np.where(is_angle, np.degrees(fixes.residuals), fixes.residuals).tolist()
    normalized_l = fixes.normalized_residuals.tolist()
    component_l = [[_COMPONENT_NAMES[k] for k in row] for row in batch.kinds.tolist()]
    station_l = batch.station_index.tolist()
    source_l = batch.source_index.tolist()
    counts = batch.n_measurements.tolist()
    chi2, dof = fixes.chi2.tolist(), fixes.dof.tolist()
    p_value = [None if math.isnan(v) else v for v in fixes.p_value.tolist()]
    sigma_scale = [None if math.isnan(v) else v for v in fixes.sigma_scale.tolist()]
    converged, iterations = fixes.converged.tolist(), fixes.iterations.tolist()
    geodetic_l = geodetic.tolist()
    method, source = fixes.method, fixes.covariance_source

    out: list[dict | None] = []
    for b in range(size):
        if not ok[b]:
            out.append(None)
            continue
        p = position_l[b]
        ids = batch.station_ids[b]
        stations, components, sources = station_l[b], component_l[b], source_l[b]
        res, nres = residual_l[b], normalized_l[b]
        body = {
            "method": method,
            "position_local": {"east_m": p[0], "north_m": p[1], "up_m": p[2]},
            "covariance_enu_m2": covariance_l[b],
            "covariance_source": source,
            "crlb_enu_m2": crlb_l[b],
            "error": {
                "cep50_m": cep[b], "sep50_m": sep[b], "vertical_sigma_m": vertical[b], "gdop": gdop[b],
                "ellipse95": {"semi_major_m": major[b], "semi_minor_m": minor[b], "orientation_deg": orientation[b]},
            },
            "residuals": [
                {"station_id": ids[stations[m]], "measurement_index": sources[m], "component": components[m],
                 "residual": res[m], "normalized": nres[m]}
                for m in range(counts[b])
            ],
            "fit": {"chi2": chi2[b], "dof": dof[b], "p_value": p_value[b], "sigma_scale": sigma_scale[b]},
            "converged": converged[b],
            "iterations": iterations[b],
            "warnings": [{"code": w.code, "message": w.message} for w in fixes.warnings[b]],
        }
        if geodetic_l[b]:
            body["position"] = {"lat_deg": lat_l[b], "lon_deg": lon_l[b], "alt_m": alt_l[b]}
            body["position_ecef_m"] = ecef_l[b]
            body["covariance_ecef_m2"] = covariance_ecef_l[b]
        wanted = formats[b]
        if wanted:
            if "geojson" in wanted:
                body["geojson"] = _geojson(body)
            if "cot" in wanted:
                body["cot"] = _cot(body)
        out.append(body)
    return out

