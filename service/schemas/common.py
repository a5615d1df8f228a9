"""Shapes every part of the HTTP contract shares (API.md): request positions, stations, measurements and
solver options with their bounds, error summaries, GeoJSON, warnings and problem details. Field names are binding.

Every float is finite (NaN and Infinity are rejected on input); unknown fields
are rejected so that a misspelt optional field is an error, not a silent
default. Units are in the names; angles are degrees.
"""

from __future__ import annotations

from datetime import datetime, timedelta, timezone
from typing import Annotated, Any, Literal, Union, get_args

from pydantic import (AfterValidator, AwareDatetime, BaseModel, ConfigDict, Discriminator, Field, StrictBool, Tag,
                      model_validator)

from core.estimators import REGISTRY
from core.estimators.loss import LOSSES
from core.estimators.result import WARNING_CODES


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


def codes_in_use(codes: dict[str, str]) -> str:
    """An open set of warning codes as a description names them: ``code``: meaning, sorted."""
    return "open set; those in use: " + "; ".join(f"`{code}`: {meaning}" for code, meaning in sorted(codes.items()))


class Warning(BaseModel):
    code: str = Field(description="fixes: " + codes_in_use(WARNING_CODES) + " (sessions: see SessionState.warnings)")
    message: str = Field(description="what was seen, with its figures, for a person")


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


class Health(BaseModel):
    status: str = Field(description="ok: the process answers")


class Readiness(BaseModel):
    status: str = Field(description="ready: the session store answered")
    store: str = Field(description="the session store's kind: sqlite or redis")
