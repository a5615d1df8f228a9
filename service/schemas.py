"""Request and response models of the HTTP contract (API.md). Field names are binding.

Every float is finite (NaN and Infinity are rejected on input); unknown fields
are rejected so that a misspelt optional field is an error, not a silent
default. Units are in the names; angles are degrees.
"""

from __future__ import annotations

from datetime import datetime, timedelta, timezone
from typing import Annotated, Any, Literal, Union, get_args

from pydantic import (AfterValidator, AwareDatetime, BaseModel, ConfigDict, Discriminator, Field, StrictBool, Tag,
                      ValidationInfo, model_validator)

from core.estimators import REGISTRY
from core.estimators.loss import LOSSES
from core.estimators.result import COVARIANCE_SOURCES, SCALED_COVARIANCE_SOURCES, WARNING_CODES
from service.limits import FIX_COST_LIMIT_KEY, check_fix

#: Local coordinates, heights and a known altitude lie within this distance of the frame (beyond geostationary
#: orbit); squares and products of such numbers stay far from float64 overflow.
MAX_COORDINATE_M = 1e8
#: A range is at most the distance between two such points, rounded up.
MAX_RANGE_M = 1e9
#: Sigma floors: 1/sigma^2 (the information weight) stays finite and far from overflow; ceilings: noise
#: larger than the physical quantity it blurs tells nothing.
MIN_SIGMA_DEG, MAX_SIGMA_AZIMUTH_DEG, MAX_SIGMA_ELEVATION_DEG = 1e-6, 180.0, 90.0
MIN_SIGMA_M, MAX_SIGMA_M = 1e-6, 1e8
MIN_SIGMA_S, MAX_SIGMA_S = 1e-15, 1.0
#: Times (TOA, session clocks) are seconds since a recent epoch: within +-1e10 s (~317 years) of it.
MAX_ABS_TIME_S = 1e10
#: Measurements of one fix: the ML fit's collinearity check is O(M^2), 4096 took 15 s and 1.1 GB.
MAX_FIX_MEASUREMENTS = 1024


class Strict(BaseModel):
    """Request models: unknown fields rejected, finite numbers, strict JSON types (a boolean is not a number,
    a string is not a number; an integer is accepted where a float is)."""

    model_config = ConfigDict(extra="forbid", allow_inf_nan=False, strict=True)


class GeodeticPosition(Strict):
    lat_deg: float = Field(ge=-90.0, le=90.0, description="WGS84 latitude, degrees north")
    lon_deg: float = Field(ge=-180.0, le=360.0, description="WGS84 longitude, degrees east")
    alt_m: float = Field(0.0, ge=-1.2e4, le=MAX_COORDINATE_M, description="height above the WGS84 ellipsoid, metres")


class LocalPosition(Strict):
    east_m: float = Field(ge=-MAX_COORDINATE_M, le=MAX_COORDINATE_M, description="metres east of the plane's origin")
    north_m: float = Field(ge=-MAX_COORDINATE_M, le=MAX_COORDINATE_M, description="metres north of the plane's origin")
    up_m: float = Field(0.0, ge=-MAX_COORDINATE_M, le=MAX_COORDINATE_M, description="metres above the plane")


class GeodeticPositionResult(BaseModel):
    """A computed position on the earth (a fix or a track): not bounded like a request's positions."""

    lat_deg: float = Field(ge=-90.0, le=90.0, description="WGS84 latitude, degrees north")
    lon_deg: float = Field(ge=-180.0, le=360.0, description="WGS84 longitude, degrees east")
    alt_m: float = Field(description="height above the WGS84 ellipsoid, metres")


class LocalPositionResult(BaseModel):
    """A computed position in a local east/north/up plane, metres: not bounded like a request's positions."""

    east_m: float = Field(description="metres east of the plane's origin")
    north_m: float = Field(description="metres north of the plane's origin")
    up_m: float = Field(description="metres up from the plane's origin")


def _position_kind(value: Any) -> str | None:
    if isinstance(value, dict):
        return "geodetic" if "lat_deg" in value or "lon_deg" in value else "local"
    if isinstance(value, GeodeticPosition):
        return "geodetic"
    if isinstance(value, LocalPosition):
        return "local"
    return None


Position = Annotated[
    Union[Annotated[GeodeticPosition, Tag("geodetic")], Annotated[LocalPosition, Tag("local")]],
    Discriminator(_position_kind),
]

StationId = Annotated[str, Field(min_length=1, max_length=128)]


class Station(Strict):
    id: StationId
    position: Position


class BearingMeasurement(Strict):
    type: Literal["bearing"]
    station_id: StationId
    azimuth_deg: float = Field(ge=-360.0, le=720.0, description="clockwise from true north")
    elevation_deg: float | None = Field(None, ge=-90.0, le=90.0, description="absent = azimuth-only")
    sigma_azimuth_deg: float | None = Field(None, ge=MIN_SIGMA_DEG, le=MAX_SIGMA_AZIMUTH_DEG,
                                            description="optional only for method taylor_wls (then estimated)")
    sigma_elevation_deg: float | None = Field(None, ge=MIN_SIGMA_DEG, le=MAX_SIGMA_ELEVATION_DEG,
                                              description="required with elevation_deg")

    @model_validator(mode="after")
    def _elevation_sigma(self):
        if self.elevation_deg is not None and self.sigma_elevation_deg is None:
            raise ValueError("sigma_elevation_deg is required when elevation_deg is given")
        return self


class RangeMeasurement(Strict):
    type: Literal["range"]
    station_id: StationId
    range_m: float = Field(ge=0.0, le=MAX_RANGE_M)
    sigma_m: float = Field(ge=MIN_SIGMA_M, le=MAX_SIGMA_M)


class ToaMeasurement(Strict):
    type: Literal["toa"]
    station_id: StationId
    toa_s: float = Field(ge=-MAX_ABS_TIME_S, le=MAX_ABS_TIME_S, description=(
        "time of arrival, synchronised clocks; emission time unknown. JSON numbers are float64: send seconds "
        "since a recent epoch (float64 resolves ~2e-7 s at Unix time, ~2e-15 s at 10 s)"))
    sigma_s: float = Field(ge=MIN_SIGMA_S, le=MAX_SIGMA_S)


Measurement = Annotated[Union[BearingMeasurement, RangeMeasurement, ToaMeasurement], Field(discriminator="type")]

Method = Literal[tuple(["auto", *sorted(REGISTRY)])]  # type: ignore[valid-type]
#: The API method names.
METHODS = frozenset(get_args(Method))


class Constraints(Strict):
    altitude_m: float | None = Field(None, ge=-MAX_COORDINATE_M, le=MAX_COORDINATE_M,
                                     description="known target altitude (surface emitter): height above the "
                                                 "ellipsoid, or the up coordinate in a flat local frame")


Variant = Literal[tuple(sorted({v for spec in REGISTRY.values() for v in spec.variants}))]  # type: ignore[valid-type]


class EvaluationOptions(Strict):
    """Solver options: a fix's without its ``initial_guess`` (what an evaluation applies to every trial)."""

    max_iterations: int = Field(50, ge=1, le=1000)
    tolerance_m: float = Field(1e-3, ge=1e-9, le=1e6)
    variant: Annotated[Variant, Field(title="MethodSolver")] | None = Field(
        None, description="method variant: ctls newton (default) | projected")
    outliers: Literal["report", "exclude"] = Field(
        "report", description="exclude: fault detection and exclusion (chi-square test, then the measurement with "
                              "the largest studentized residual, repeated while the test fails and dof remain); "
                              "report: only warn")
    absolute_sigma: StrictBool = Field(
        True, description="false: scale the covariance by the fit's sigma_scale^2 (as scipy's curve_fit)")
    loss: Literal[LOSSES] = Field(  # type: ignore[valid-type]
        "linear", description="ml's loss, scipy least_squares' names and meanings, on residuals in sigmas: linear "
                              "(least squares) | huber | soft_l1 | cauchy | arctan. Redescending losses (cauchy, "
                              "arctan) set gross errors aside; huber and soft_l1 bound their pull. The covariance "
                              "is then the sandwich of the loss's final weights (covariance_source robust) and "
                              "fit.sigma_scale is sqrt(sum rho / dof), as curve_fit's; chi2 stays the plain sum")
    loss_scale: float = Field(1.0, gt=0.0, le=1e6, description="the loss's scale in sigmas (scipy's f_scale "
                                                                "applied to whitened residuals)")


class Options(EvaluationOptions):
    initial_guess: Position | None = None


Format = Literal["geojson", "cot"]


#: The longest CoT stale time after the event's start (a week).
MAX_STALE_S = 7 * 86400.0
#: observed_at lies within these (UTC): a CoT event's start, and its stale time up to MAX_STALE_S later, are then
#: times Python, XML Schema and TAK servers can all write (years 1..9999).
OBSERVED_AT_RANGE = (datetime(1, 1, 2, tzinfo=timezone.utc),
                     datetime(9999, 12, 31, tzinfo=timezone.utc) - timedelta(seconds=MAX_STALE_S + 86400.0))


def _within_observed_range(moment: datetime) -> datetime:
    low, high = OBSERVED_AT_RANGE
    if not low <= moment <= high:
        raise ValueError(f"observed_at must lie between {low.isoformat()} and {high.isoformat()}, so that the CoT "
                         "stale time after it is a valid time")
    return moment


ObservedAt = Annotated[AwareDatetime, AfterValidator(_within_observed_range)]


class CotOptions(Strict):
    """How a fix is sent as Cursor-on-Target (the ``cot`` format, and the TAK feed)."""

    uid: str | None = Field(None, min_length=1, max_length=128, pattern=r"^[!-~]+$",
                            description="the emitter's CoT uid (printable ASCII, no spaces): events with one uid "
                                        "update one marker; absent = a new uid per fix")
    type: str = Field("a-u-G", max_length=64, pattern=r"^[A-Za-z0-9_]+(-[A-Za-z0-9_]+)*$",
                      description="CoT type; default a-u-G, an unknown-affiliation ground track")
    stale_s: float = Field(300.0, gt=0.0, le=MAX_STALE_S, description="stale = start + stale_s")
    callsign: str | None = Field(
        None, min_length=1, max_length=64, pattern=r"^[^\x00-\x1f\x7f-\x9f\ufffe\uffff]+$",
        description="the label a TAK client shows on the marker (detail/contact callsign; characters XML 1.0 "
                    "allows, no control characters); absent = the uid")


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


GDOP_DESCRIPTION = (
    "dimensionless geometric (position) dilution of precision: sqrt(trace(CRLB)) / sigma_ref_m, where "
    "sigma_ref_m = (mean over measurements of r_i^-2)^-1/2 and r_i is measurement i's sigma in metres at the "
    "target (its sigma over the norm of its gradient with respect to the position: sigma_m for a range, "
    "c * sigma_s for a TOA, sigma_azimuth_rad x horizontal distance for an azimuth, sigma_elevation_rad x slant "
    "range for an elevation). With one metres-equivalent sigma for all it is the classical "
    "sqrt(trace((H^T H)^-1)) of unit line-of-sight rows (for TOA: GNSS PDOP, the emission time marginalised)")


class Ellipse(BaseModel):
    """The 95 % horizontal error ellipse (chi-square, 2 degrees of freedom) in the east/north plane at the point."""

    semi_major_m: float = Field(description="semi-major axis, metres")
    semi_minor_m: float = Field(description="semi-minor axis, metres")
    orientation_deg: float = Field(description="major axis, clockwise from north, [0, 180)")


class ErrorSummary(BaseModel):
    """Error figures of a covariance in the east/north/up axes at the point (a fix's covariance_enu_m2, or the
    planning bound)."""

    cep50_m: float = Field(description="horizontal circular error probable: the radius, metres, of the circle "
                                       "around the estimate that holds it with probability 0.5")
    sep50_m: float = Field(description="spherical error probable: the radius, metres, of the sphere that holds "
                                       "it with probability 0.5")
    vertical_sigma_m: float = Field(description="one-sigma error up, metres: sqrt of the covariance's up-up entry")
    gdop: float | None = Field(description=GDOP_DESCRIPTION + "; null where undefined. Of the bound (a fix's "
                                                              "crlb_enu_m2), so it describes the geometry, not the "
                                                              "method; sqrt_trace_m holds the metres")
    sqrt_trace_m: float = Field(description="sqrt(trace(covariance)) in metres, east, north and up")
    ellipse95: Ellipse = Field(description="the 95 % horizontal error ellipse")


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


def codes_in_use(codes: dict[str, str]) -> str:
    """An open set of warning codes as a description names them: ``code``: meaning, sorted."""
    return "open set; those in use: " + "; ".join(f"`{code}`: {meaning}" for code, meaning in sorted(codes.items()))


class Warning(BaseModel):
    code: str = Field(description="fixes: " + codes_in_use(WARNING_CODES) + " (sessions: see SessionState.warnings)")
    message: str = Field(description="what was seen, with its figures, for a person")


class Stages(BaseModel):
    """Intermediate results of a method with more than one stage."""

    coarse: LocalPositionResult | None = Field(None, description="the coarse stage's position (angle_range, "
                                                                 "los_intersection), in position_local's frame")


Matrix3 = list[list[float]]


class PointGeometry(BaseModel):
    type: Literal["Point"] = Field(description="GeoJSON geometry type")
    coordinates: list[float] = Field(description="[longitude_deg, latitude_deg, height_m] (RFC 7946)")


class PolygonGeometry(BaseModel):
    type: Literal["Polygon"] = Field(description="GeoJSON geometry type")
    coordinates: list[list[list[float]]] = Field(description="one closed counter-clockwise ring of "
                                                             "[longitude_deg, latitude_deg]")


class MultiPolygonGeometry(BaseModel):
    type: Literal["MultiPolygon"] = Field(description="GeoJSON geometry type")
    coordinates: list[list[list[list[float]]]] = Field(description="a ring cut at the antimeridian: its two "
                                                                   "sides, each one closed ring of "
                                                                   "[longitude_deg, latitude_deg]")


class LineStringGeometry(BaseModel):
    type: Literal["LineString"] = Field(description="GeoJSON geometry type")
    coordinates: list[list[float]] = Field(description="[longitude_deg, latitude_deg] points: a network track's "
                                                       "course line")


Geometry = Annotated[Union[PointGeometry, PolygonGeometry, MultiPolygonGeometry, LineStringGeometry],
                     Field(discriminator="type")]


class Feature(BaseModel):
    type: Literal["Feature"] = Field(description="GeoJSON object type")
    geometry: Geometry | None = Field(description="null for a fix in a flat local frame (no place on the earth)")
    properties: dict[str, Any] = Field(description="kind fix: method, time, error summary; kind track: course_deg, "
                                                   "speed_mps; kind error_ellipse: semi-axes (m), orientation "
                                                   "(deg clockwise from north), probability 0.95; kind course (a "
                                                   "network track's line): id, course_deg, speed_mps, seconds")


class FeatureCollection(BaseModel):
    """GeoJSON (RFC 7946): the point, and its 95 % error ellipse as a polygon placed in the point's tangent plane."""

    type: Literal["FeatureCollection"] = Field(description="GeoJSON object type")
    features: list[Feature] = Field(description="kind fix (or track) Points, then kind error_ellipse Polygons "
                                                "(MultiPolygons when cut at the antimeridian)")


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
        description="information: inverse Fisher information at the fix; propagated: first-order through the "
                    "closed form; crlb: the bound; robust: with options.loss, the sandwich A^-1 B A^-1 of the "
                    "loss's final weights w = rho' (A = J^T W w J, B = J^T W w^2 J); _scaled: times "
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


class SensorSpec(Strict):
    station_id: StationId
    azimuth: bool = True
    elevation: bool = True
    range: bool = False
    toa: bool = False
    sigma_azimuth_deg: float | None = Field(None, ge=MIN_SIGMA_DEG, le=MAX_SIGMA_AZIMUTH_DEG)
    sigma_elevation_deg: float | None = Field(None, ge=MIN_SIGMA_DEG, le=MAX_SIGMA_ELEVATION_DEG)
    sigma_range_m: float | None = Field(None, ge=MIN_SIGMA_M, le=MAX_SIGMA_M)
    sigma_toa_s: float | None = Field(None, ge=MIN_SIGMA_S, le=MAX_SIGMA_S)

    @model_validator(mode="after")
    def _sigmas_present(self):
        for flag, sigma in (("azimuth", "sigma_azimuth_deg"), ("elevation", "sigma_elevation_deg"),
                            ("range", "sigma_range_m"), ("toa", "sigma_toa_s")):
            if getattr(self, flag) and getattr(self, sigma) is None:
                raise ValueError(f"{sigma} is required when {flag} is true")
        if self.elevation and not self.azimuth:
            raise ValueError("an elevation needs an azimuth on the same sensor")
        return self


class PlanningGeometry(Strict):
    """The sensor geometry of a planning request (shared by the bound at a target and the coverage map)."""

    frame: Literal["wgs84", "local"] = "wgs84"
    origin: GeodeticPosition | None = None
    stations: list[Station] = Field(min_length=1, max_length=256)
    sensors: list[SensorSpec] = Field(min_length=1, max_length=1024)
    constraints: Constraints | None = None


class CrlbRequest(PlanningGeometry):
    target: Position


class CrlbResponse(BaseModel):
    """The planning bound at a target."""

    crlb_enu_m2: Matrix3 = Field(description="3x3 Cramer-Rao bound, square metres, east/north/up at the target "
                                             "(a flat local frame: its own axes)")
    error: ErrorSummary = Field(description="figures of the bound")


#: Finest grid step: a millimetre (the number of cells is bounded by max_grid_cost anyway).
MIN_GRID_STEP_M = 1e-3


class GridSpec(Strict):
    """A square grid of target positions in the scene's common east/north/up frame."""

    centre: Position = Field(description="the centre cell (its height is ignored: altitude_m sets every cell's)")
    half_width_m: float = Field(gt=0.0, le=MAX_COORDINATE_M, description=(
        "cells reach this far east, west, north and south of the centre (the centre and floor(half_width_m / "
        "step_m) cells on each side)"))
    step_m: float = Field(ge=MIN_GRID_STEP_M, le=MAX_COORDINATE_M, description="distance between cell centres")
    altitude_m: float | None = Field(None, ge=-MAX_COORDINATE_M, le=MAX_COORDINATE_M, description=(
        "target altitude of every cell: height above the ellipsoid (wgs84 or with an origin), else the up "
        "coordinate; default constraints.altitude_m, else 0 (when both are given they must agree)"))


class ImageSpec(Strict):
    """Size of the pictures: the PNG heat map exactly; the KMZ and GeoTIFF rasters take the larger of the two
    along their longer side."""

    width_px: int = Field(640, ge=16, le=4096, description="PNG width, pixels")
    height_px: int = Field(480, ge=16, le=4096, description="PNG height, pixels")


class CrlbGridRequest(PlanningGeometry):
    grid: GridSpec
    image: ImageSpec = Field(default_factory=ImageSpec, description="the pictures' size (PNG, KMZ, GeoTIFF)")


class CellProperties(BaseModel):
    """One cell (kind cell) of a coverage map; the bound's values are null where the cell is unobservable."""

    kind: Literal["cell"] = Field(description="a cell of the grid")
    row: int = Field(description="0 = southernmost row")
    column: int = Field(description="0 = westernmost column")
    east_m: float = Field(description="cell centre east, metres, in the scene's common east/north/up frame")
    north_m: float = Field(description="cell centre north, metres, in that frame")
    up_m: float = Field(description="cell centre up, metres, in that frame")
    unobservable: bool = Field(description="the sensors do not determine a target here (singular information)")
    cep50_m: float | None = Field(description="horizontal CEP50 of the CRLB")
    sqrt_trace_crlb_m: float | None = Field(description="sqrt(trace(CRLB)), east, north and up")
    gdop: float | None = Field(description=GDOP_DESCRIPTION)
    sigma_ref_m: float | None = Field(description="the metres-equivalent sigma gdop is relative to")


class StationProperties(BaseModel):
    """One station (kind station) of a coverage map."""

    kind: Literal["station"] = Field(description="a station of the geometry")
    id: str = Field(description="the station's id")
    east_m: float = Field(description="east, metres, in the scene's common east/north/up frame")
    north_m: float = Field(description="north, metres, in that frame")
    up_m: float = Field(description="up, metres, in that frame")


class CoverageFeature(BaseModel):
    type: Literal["Feature"] = Field(description="GeoJSON object type")
    geometry: Geometry | None = Field(
        description="cell: its square (corners step_m / 2 from the centre in the common frame) as "
                    "[longitude_deg, latitude_deg] within [-180, 180], a MultiPolygon when cut at the "
                    "antimeridian, null around a pole; station: a Point; null in a flat local frame")
    properties: CellProperties | StationProperties = Field(description="a cell's bound, or a station")


class GridSummary(BaseModel):
    """The grid's shape."""

    rows: int = Field(description="cells south to north")
    columns: int = Field(description="cells west to east")
    step_m: float = Field(description="distance between cell centres, metres")
    altitude_m: float = Field(description="of every cell: height above the ellipsoid, or up in a flat frame")
    east_m: list[float] = Field(description="[first, last] column's east coordinate in the common frame")
    north_m: list[float] = Field(description="[first, last] row's north coordinate in the common frame")


class CrlbGridResponse(BaseModel):
    """GeoJSON (RFC 7946): one feature per cell (row-major from the south-west corner), then the stations."""

    type: Literal["FeatureCollection"] = Field(description="GeoJSON object type")
    features: list[CoverageFeature] = Field(description="the cells, row-major from the south-west corner, then "
                                                        "the stations")
    grid: GridSummary = Field(description="a foreign member (RFC 7946 section 6.1): the grid's shape")


class ProblemError(BaseModel):
    """One invalid field."""

    loc: list[str | int] = Field(description="path to the field in the request: names and list indices")
    msg: str = Field(description="what is wrong with it")
    type: str | None = Field(None, description="machine-readable kind of error, when the validator gives one")


class Problem(BaseModel):
    """RFC 9457 problem details (``application/problem+json``)."""

    type: str = Field(description="URI of the problem type: PROBLEM_BASE + code")
    title: str = Field(description="short summary of the problem type")
    status: int = Field(description="the HTTP status")
    detail: str = Field(description="what went wrong in this request, naming the first invalid field")
    code: str = Field(description="stable machine-readable code, e.g. invalid_input, unobservable, not_found")
    errors: list[ProblemError] = Field(default_factory=list, description="every invalid field (422)")
    instance: str | None = Field(None, description="URI of this occurrence (urn:passive-locator:request:<id>)")
    request_id: str | None = Field(None, description="the X-Request-ID of the request: quote it when reporting")


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


class EvaluationRequest(Strict):
    scenario: CrlbRequest
    methods: list[Method] = Field(min_length=1, max_length=16)  # type: ignore[valid-type]
    trials: int = Field(1000, ge=1, le=100000)
    seed: int = Field(7, ge=0, le=2**63 - 1)
    noise: Literal["gaussian", "uniform", "outlier"] = Field(
        "gaussian", description="uniform: zero-mean with the same sigma (half-width sigma*sqrt(3)); outlier: a "
                                "contaminated gaussian, each measurement N(0, sigma^2) except with probability 0.05 "
                                "a gross error N(0, (10 sigma)^2) (try it with options.outliers = exclude)")
    options: EvaluationOptions = Field(default_factory=lambda: EvaluationOptions(),
                                       description="solver options for every trial (a fix's options without the "
                                                   "per-fix initial_guess)")


class FailureReason(BaseModel):
    code: str = Field(description="the problem code a single fix of such a trial answers with (unobservable, ...)")
    trials: int = Field(description="failed trials with this code")
    example: str = Field(description="the detail of the first of them")


class MethodEvaluation(BaseModel):
    rmse_m: float | None = Field(description="null when every trial failed")
    rmse_enu_m: list[float] | None = Field(description="[east, north, up] root-mean-square errors, metres, in the "
                                                       "scene's common frame; null when every trial failed")
    bias_enu_m: list[float] | None = Field(description="[east, north, up] mean error, metres; null when every "
                                                       "trial failed")
    crlb_rmse_m: float = Field(description="sqrt(trace(CRLB)) at the target: the least rmse_m an unbiased "
                                           "method can reach")
    efficiency: float | None = Field(description="rmse^2 / trace(crlb); 1 is efficient")
    nees_mean: float | None = Field(description="mean e^T C^-1 e with the method's own covariance; 3 if honest")
    failures: int = Field(description="trials without a fix")
    excluded_trials: int = Field(0, description="trials with a fix in which outlier exclusion dropped a measurement")
    failure_reasons: list[FailureReason] = Field(default_factory=list, description=(
        "why the failed trials gave no fix, one entry per problem code, most trials first"))


class EvaluationResponse(BaseModel):
    """Monte Carlo accuracy of each method on one scenario."""

    methods: dict[str, MethodEvaluation] = Field(description="by method name, as requested")
    trials: int = Field(description="noisy trials per method")
    seed: int = Field(description="the random seed: the same request gives the same numbers")
    noise: str = Field(description="the noise model of the trials")


class Health(BaseModel):
    status: str = Field(description="ok: the process answers")


class Readiness(BaseModel):
    status: str = Field(description="ready: the session store answered")
    store: str = Field(description="the session store's kind: sqlite or redis")
