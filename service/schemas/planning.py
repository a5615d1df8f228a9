"""The planning requests and responses of the HTTP contract: the bound at a target, the coverage map and the
Monte Carlo evaluation."""

from __future__ import annotations

from typing import Literal

from pydantic import BaseModel, Field, model_validator

from service.schemas.common import (Constraints, ErrorSummary, EvaluationOptions, GDOP_DESCRIPTION, GeodeticPosition,
                                    Geometry, MAX_COORDINATE_M, MAX_SIGMA_AZIMUTH_DEG, MAX_SIGMA_ELEVATION_DEG,
                                    MAX_SIGMA_M, MAX_SIGMA_S, MIN_SIGMA_DEG, MIN_SIGMA_M, MIN_SIGMA_S, Matrix3,
                                    Method, Position, Station, StationId, Strict)


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
