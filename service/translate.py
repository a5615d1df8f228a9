"""The one translation between HTTP schemas (degrees, request order) and core types.

Responses are built as plain dicts (serialised by orjson) rather than
re-validated models: the schema documents them and the tests check that every
response validates against it.
"""

from __future__ import annotations

import math

import numpy as np

from core.accuracy import error_summary
from core.estimators import Fix, SolveOptions
from core.measurements import Kind
from core.problem import Bearing, GeodeticPoint, LocalPoint, Problem, Range, TimeOfArrival, build_problem
from service import schemas

_COMPONENT = {Kind.AZIMUTH: "azimuth", Kind.ELEVATION: "elevation", Kind.RANGE: "range", Kind.TOA: "toa"}


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
    return math.degrees(value) if kind in (Kind.AZIMUTH, Kind.ELEVATION) else float(value)


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
    body: dict = {
        "method": fix.method,
        "position_local": _local(p),
        "covariance_enu_m2": _matrix(fix.covariance_enu_m2),
        "covariance_source": fix.covariance_source,
        "crlb_enu_m2": _matrix(fix.crlb_enu_m2),
        "error": error_dict(summary, index),
        "residuals": [
            {
                "station_id": problem.station_ids[s],
                "measurement_index": int(src),
                "component": _COMPONENT[Kind(k)],
                "residual": _residual_value(k, r),
                "normalized": float(n),
            }
            for s, src, k, r, n in zip(problem.station_index, problem.source_index, problem.kinds,
                                       fix.residuals, fix.normalized_residuals)
        ],
        "fit": {"chi2": fix.chi2, "dof": fix.dof, "p_value": fix.p_value, "sigma_scale": fix.sigma_scale},
        "converged": fix.converged,
        "iterations": fix.iterations,
        "warnings": [{"code": w.code, "message": w.message} for w in fix.warnings],
    }
    if problem.frame.is_geodetic:
        lat, lon, alt = problem.frame.to_geodetic(p)
        body["position"] = {"lat_deg": math.degrees(lat), "lon_deg": math.degrees(lon), "alt_m": float(alt)}
        body["position_ecef_m"] = problem.frame.to_ecef(p).tolist()
        body["covariance_ecef_m2"] = _matrix(problem.frame.covariance_to_ecef(fix.covariance_enu_m2))
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
