"""Between the HTTP schemas (degrees, request order) and core types (radians, SI), both ways.

Requests become core problems and options here (:func:`to_problem`,
:func:`to_options`, :func:`to_point`, :func:`to_measurement`), and core
error summaries become the response's ``error`` block (:func:`error_dict`),
for fixes, planning and sessions alike.
"""

from __future__ import annotations

import math

import numpy as np

from core.errors import InvalidInput
from core.estimators import SolveOptions
from core.problem.build import Bearing, Range, TimeOfArrival, build_problem
from core.problem.frame import GeodeticPoint, LocalPoint, Problem
from service import schemas


def to_point(position) -> GeodeticPoint | LocalPoint:
    if isinstance(position, schemas.GeodeticPosition):
        return GeodeticPoint(math.radians(position.lat_deg), math.radians(position.lon_deg), position.alt_m)
    return LocalPoint(position.east_m, position.north_m, position.up_m)


def radians_or_none(value: float | None) -> float | None:
    return None if value is None else math.radians(value)


def to_measurement(m):
    if m.type == "bearing":
        return Bearing(m.station_id, math.radians(m.azimuth_deg), radians_or_none(m.elevation_deg),
                       radians_or_none(m.sigma_azimuth_deg), radians_or_none(m.sigma_elevation_deg))
    if m.type == "range":
        return Range(m.station_id, m.range_m, m.sigma_m)
    return TimeOfArrival(m.station_id, m.toa_s, m.sigma_s)


def known_altitude(constraints: schemas.Constraints | None) -> float | None:
    return None if constraints is None else constraints.altitude_m


def to_problem(request: schemas.FixRequest) -> Problem:
    """Validate and place a fix request in its common frame (raises core InvalidInput)."""
    guess = request.options.initial_guess
    return build_problem(
        stations=[(s.id, to_point(s.position)) for s in request.stations],
        measurements=[to_measurement(m) for m in request.measurements],
        origin=None if request.origin is None else to_point(request.origin),
        altitude_m=known_altitude(request.constraints),
        initial_guess=None if guess is None else to_point(guess),
        require_sigmas=False,
    )


def to_options(request: schemas.FixRequest | schemas.EvaluationRequest) -> SolveOptions:
    o = request.options
    return SolveOptions(max_iterations=o.max_iterations, tolerance_m=o.tolerance_m, variant=o.variant,
                        outliers=o.outliers, absolute_sigma=o.absolute_sigma, loss=o.loss, loss_scale=o.loss_scale)


def in_frame(problem: Problem, position, loc: tuple) -> np.ndarray:
    """A request position ``(3,)`` in the problem's common ENU frame (InvalidInput at ``loc`` if it cannot be)."""
    point = to_point(position)
    if isinstance(point, GeodeticPoint):
        if not problem.frame.is_geodetic:
            raise InvalidInput("a geodetic position needs a geodetic frame or an origin", loc)
        return problem.frame.from_geodetic(point.lat_rad, point.lon_rad, point.alt_m)
    return np.array([point.east_m, point.north_m, point.up_m])


def finite_or_none(value):
    if isinstance(value, np.ndarray):
        return value.tolist() if np.all(np.isfinite(value)) else None
    return value if math.isfinite(value) else None


def error_dict(summary, gdops, i: int = 0) -> dict:
    """The ``error`` block of row ``i`` of an ErrorSummary, with its dimensionless GDOP (``(B,)``, NaN: null)."""
    return {
        "cep50_m": float(summary.cep50_m[i]),
        "sep50_m": float(summary.sep50_m[i]),
        "vertical_sigma_m": float(summary.vertical_sigma_m[i]),
        "gdop": finite_or_none(float(gdops[i])),
        "sqrt_trace_m": float(summary.gdop_m[i]),
        "ellipse95": {
            "semi_major_m": float(summary.ellipse_semi_major_m[i]),
            "semi_minor_m": float(summary.ellipse_semi_minor_m[i]),
            "orientation_deg": float(np.degrees(summary.ellipse_orientation_rad[i])),
        },
    }
