"""The request's fields and rules as the lean reader (:mod:`service.fixes.read`) applies them, taken from the
schema (:mod:`service.schemas`): one place for each rule."""

from __future__ import annotations

import math
import typing

import numpy as np

from core.estimators import SolveOptions
from core.measurements import Kind
from service import schemas
from service.fixes import decode

_AZ, _EL, _RG, _TOA = int(Kind.AZIMUTH), int(Kind.ELEVATION), int(Kind.RANGE), int(Kind.TOA)

#: The fields the reader handles, per request model: the :mod:`service.fixes.decode` structs' fields (and ``type``, their
#: tag). A test holds each set against the model's own fields, so a field added to the schema fails it until the
#: reader handles the field.
READ_FIELDS = {
    # A body with observed_at or cot options is read through the schema (they shape only its renderings).
    schemas.FixRequest: frozenset(decode.FixBody.__struct_fields__) | {"observed_at", "cot"},
    schemas.CotOptions: frozenset(schemas.CotOptions.model_fields),
    schemas.Station: frozenset(decode.Station.__struct_fields__),
    schemas.GeodeticPosition: frozenset(("lat_deg", "lon_deg", "alt_m")),
    schemas.LocalPosition: frozenset(("east_m", "north_m", "up_m")),
    schemas.BearingMeasurement: frozenset(decode.Bearing.__struct_fields__) | {"type"},
    schemas.RangeMeasurement: frozenset(decode.Range.__struct_fields__) | {"type"},
    schemas.ToaMeasurement: frozenset(decode.Toa.__struct_fields__) | {"type"},
    schemas.Options: frozenset(decode.Options.__struct_fields__),
    schemas.Constraints: frozenset(decode.Constraints.__struct_fields__),
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
