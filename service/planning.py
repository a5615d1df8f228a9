"""Planning: the bound of a sensor geometry at a target, its coverage map, and Monte Carlo evaluations.

The requests are read into core problems by :mod:`service.convert`; the
maps are drawn by :mod:`service.renderings.maps`.
"""

from __future__ import annotations

import numpy as np

from core import geodesy
from core.coverage import Grid, cells_per_side, coverage_map, grid
from core.crlb import gdop, information_at
from core.error_summary import error_summary
from core.errors import InvalidInput, UnobservableGeometry
from core.problem.build import Bearing, Range, TimeOfArrival, build_problem
from core.problem.frame import Problem
from core.simulation.measurements import evaluate
from service import schemas
from service.convert import (error_dict, finite_or_none, in_frame, known_altitude, radians_or_none, to_options,
                             to_point)
from service.limits import check_grid
from service.renderings.maps import coverage_geojson, coverage_geotiff, coverage_kmz, coverage_png
from service.web.problems import ApiError


def planning_problem(request: schemas.PlanningGeometry) -> Problem:
    """A problem whose measurements are the sensors' kinds (their values unused), in its common frame."""
    measurements = []
    for sensor in request.sensors:
        if sensor.azimuth:
            el = 0.0 if sensor.elevation else None
            measurements.append(Bearing(sensor.station_id, 0.0, el, radians_or_none(sensor.sigma_azimuth_deg),
                                        radians_or_none(sensor.sigma_elevation_deg)))
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
        altitude_m=known_altitude(request.constraints),
    )


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
    known = known_altitude(request.constraints)
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
    "tiff": bytes}`` for ``formats`` (a KMZ or GeoTIFF raises :class:`service.renderings.maps.NotOnTheEarth` in a flat
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
            "rmse_m": finite_or_none(r.rmse_m),
            "rmse_enu_m": finite_or_none(r.rmse_enu_m),
            "bias_enu_m": finite_or_none(r.bias_enu_m),
            "crlb_rmse_m": r.crlb_rmse_m,
            "efficiency": finite_or_none(r.efficiency),
            "nees_mean": finite_or_none(r.nees_mean),
            "failures": r.failures,
            "excluded_trials": r.excluded_trials,
            "failure_reasons": [{"code": code, "trials": count, "example": message} for code, (count, message)
                                in sorted(r.failure_reasons.items(), key=lambda item: (-item[1][0], item[0]))],
        }
        for name, r in results.items()
    }
    return {"methods": methods_out, "trials": request.trials, "seed": request.seed, "noise": request.noise}
