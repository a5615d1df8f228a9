"""The fix requests and responses of the HTTP contract: ``POST /v1/fixes`` and ``POST /v1/fixes/batch``."""

from __future__ import annotations

from typing import Any, Literal

from pydantic import BaseModel, Field, ValidationInfo, model_validator

from core.estimators.result import COVARIANCE_SOURCES, SCALED_COVARIANCE_SOURCES
from service.limits import FIX_COST_LIMIT_KEY, check_fix
from service.schemas.common import (Constraints, CotOptions, ErrorSummary, FeatureCollection, Format,
                                    GeodeticPosition, GeodeticPositionResult, LocalPosition, LocalPositionResult,
                                    MAX_FIX_MEASUREMENTS, Matrix3, Measurement, Method, OBSERVED_AT_RANGE, ObservedAt,
                                    Options, Problem, Station, Strict, Warning)


class FixRequest(Strict):
    frame: Literal["wgs84", "local"] = "wgs84"
    origin: GeodeticPosition | None = None
    stations: list[Station] = Field(min_length=1, max_length=256)
    measurements: list[Measurement] = Field(min_length=1, max_length=MAX_FIX_MEASUREMENTS, description=(
        "1..1024 (the largest fix, 256 stations x 1024 measurements, runs within 3 s and 300 MB); a service "
        "may set a lower max_fix_cost = stations x measurements (los_intersection: at least measurements^2 / 4), "
        "times, with options.outliers exclude, the solves its refits may take (up to 65)"))
    method: Method = "auto"  # type: ignore[valid-type]
    constraints: Constraints | None = None
    options: Options = Field(default_factory=Options)
    formats: list[Format] = Field(default_factory=list, max_length=2)
    observed_at: ObservedAt | None = Field(
        None, strict=False, description=(
            f"RFC 3339 time of the measurements (with an offset), from {OBSERVED_AT_RANGE[0].date().isoformat()} to "
            f"{OBSERVED_AT_RANGE[1].date().isoformat()} UTC: the CoT event's time and start, the GeoJSON time; "
            "absent = when the fix is made"))
    cot: CotOptions | None = Field(None, description="CoT uid, type and stale time; a fix that carries them is "
                                                     "also sent to the TAK feed when one is configured")

    @model_validator(mode="after")
    def _within_cost(self, info: ValidationInfo):
        # The limit is the app's, given by whoever validates (service.limits.fix_cost_context); none without it.
        check_fix(len(self.stations), len(self.measurements), self.method, self.options.outliers == "exclude",
                  (info.context or {}).get(FIX_COST_LIMIT_KEY))
        return self

    @model_validator(mode="after")
    def _stations_match_frame(self):
        wanted = GeodeticPosition if self.frame == "wgs84" else LocalPosition
        for station in self.stations:
            if not isinstance(station.position, wanted):
                raise ValueError(
                    f"frame {self.frame!r} needs {wanted.__name__} station positions; station {station.id!r} differs")
        return self


class Residual(BaseModel):
    """One measurement component's residual at the fix."""

    station_id: str = Field(description="the station that made the measurement")
    measurement_index: int = Field(description="index of the request measurement")
    component: Literal["azimuth", "elevation", "range", "toa"] = Field(
        description="which part of the measurement: a bearing gives an azimuth and, with an elevation, an "
                    "elevation residual")
    residual: float = Field(description="measured minus fitted: deg, m or s")
    normalized: float = Field(description="residual / sigma")
    used: bool = Field(True, description="false: left out of the fit and its verdicts (the method does not use "
                                         "this kind, or it was excluded)")
    excluded: bool = Field(False, description="removed by outlier exclusion (options.outliers exclude)")


class Fit(BaseModel):
    """How well the stated sigmas explain the residuals."""

    chi2: float = Field(description="sum of the squared normalized residuals of the measurements used")
    dof: int = Field(description="degrees of freedom: measurement components used minus unknowns")
    p_value: float | None = Field(description="probability of a chi2 at least this large if the sigmas are "
                                              "right; null when dof is 0")
    sigma_scale: float | None = Field(description="sqrt(chi2 / dof) (with a robust loss, sqrt(sum rho / dof)): "
                                                  "about 1 when the sigmas are right; null when dof is 0")


class Stages(BaseModel):
    """Intermediate results of a method with more than one stage."""

    coarse: LocalPositionResult | None = Field(None, description="the coarse stage's position (angle_range, "
                                                                 "los_intersection), in position_local's frame")


class FixResponse(BaseModel):
    """One fix: the position, its covariance, the bound, the fit and what to watch for.

    Covariances are in square metres; a geodetic fix's ENU matrices are in the east/north/up axes at the fix."""

    method: str = Field(description="the method that ran (auto resolves to its choice)")
    position: GeodeticPositionResult | None = Field(None, description="WGS84 position; present when the frame is "
                                                                      "wgs84 or an origin is given")
    position_local: LocalPositionResult = Field(description="in the request's local plane (frame local), else in "
                                                            "the east/north/up plane at the reference point (the "
                                                            "origin, or the stations' centroid on the ellipsoid)")
    position_ecef_m: list[float] | None = Field(None, description="[x, y, z] earth-centred earth-fixed, metres; "
                                                                  "when geodetic")
    covariance_enu_m2: Matrix3 = Field(description="3x3 position covariance, east/north/up at the fix (a flat "
                                                   "local frame: its own axes); its source is covariance_source")
    covariance_ecef_m2: Matrix3 | None = Field(None, description="the same covariance in earth-centred "
                                                                 "earth-fixed axes; when geodetic")
    covariance_source: Literal[COVARIANCE_SOURCES + SCALED_COVARIANCE_SOURCES] = Field(  # type: ignore[valid-type]
        description="information: inverse Fisher information at the fix, except on a fix that warns "
                    "second_solution_plausible (the covariance is then the two-solution mixture's) or "
                    "curved_uncertainty (the unscented spread of the estimator, never below the bound), "
                    "either widened where needed so that its 99 % region holds 99 % of the error; "
                    "propagated: first-order through the closed form; crlb: the bound; robust: with "
                    "options.loss, the sandwich A^-1 B A^-1 of the loss's final weights w = rho' "
                    "(A = J^T W w J, B = J^T W w^2 J); _scaled: times "
                    "sigma_scale^2 (options.absolute_sigma false)")
    crlb_enu_m2: Matrix3 = Field(description="3x3 Cramer-Rao bound at the fix for the measurements used, "
                                             "east/north/up at the fix (the least covariance an unbiased "
                                             "estimator can reach)")
    error: ErrorSummary = Field(description="figures of covariance_enu_m2 (gdop: of crlb_enu_m2)")
    residuals: list[Residual] = Field(description="one per measurement component, in request order")
    fit: Fit = Field(description="the chi-square test of the residuals")
    converged: bool = Field(description="false: the iteration limit came first (warning not_converged)")
    iterations: int = Field(description="iterations the method took (0 for a closed form)")
    stages: Stages | None = Field(None, description="methods with a coarse stage")
    estimated_bearing_errors_deg: list[float] | None = Field(None, description="taylor_wls: each bearing's "
                                                                               "estimated sigma, request order")
    warnings: list[Warning] = Field(description="conditions that make the fix less trustworthy than its "
                                                "covariance says; empty when none")
    geojson: FeatureCollection | None = Field(None, description="when formats asks for geojson")
    cot: str | None = Field(None, description="when formats asks for cot: a CoT 2.0 event; point ce and le are "
                                              "one-sigma errors in metres, ce = sqrt((l1 + l2) / 2) of the "
                                              "horizontal covariance's eigenvalues at the fix, le = sigma_up; "
                                              "detail/shape/ellipse is the 95 % ellipse (semi-axes in metres, "
                                              "angle clockwise from north); null in a flat local frame")


class BatchRequest(Strict):
    problems: list[dict[str, Any]] = Field(
        min_length=1, max_length=10000,
        description="FixRequest objects; each is validated on its own so one bad problem fails only its slot")
    formats: list[Literal["geojson"]] = Field(
        default_factory=list, max_length=1,
        description="geojson: one FeatureCollection of every solved fix (Point and 95 % ellipse, each with its "
                    "`index`) in the response's `geojson`")


class BatchResult(BaseModel):
    """One problem's outcome."""

    index: int = Field(description="the problem's index in the request")
    ok: bool = Field(description="true: fix is given; false: error is")
    fix: FixResponse | None = Field(None, description="the fix, when ok")
    error: Problem | None = Field(None, description="why there is no fix, when not ok")


class BatchResponse(BaseModel):
    results: list[BatchResult] = Field(description="one per problem, in request order")
    geojson: FeatureCollection | None = Field(None, description="when the request's formats ask for geojson")
