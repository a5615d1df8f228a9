"""The request's fields and the rules the lean reader (:mod:`service.fixes.read`) applies to them: one table.

Each rule is written once, in the schema (:mod:`service.schemas`); this
module reads the schema's rules into the tables the reader checks: the
bounds of each number, string length and list length (:data:`RULES`), the
closed sets of names (:data:`CHOICES`), the defaults, and the rules that span
fields (:data:`VALIDATORS`, which the reader re-implements). Tests hold the
tables to the schema: a constrained field, a set of names or a validator
added to a request model fails them until it is listed here (and read), or
its body is left to the schema (:data:`SCHEMA_ONLY`).
"""

from __future__ import annotations

import math
import typing

import numpy as np

from core.estimators import SolveOptions
from core.measurements import Kind
from service import schemas
from service.fixes import decode


class Bounds(typing.NamedTuple):
    """The closed interval ``[low, high]`` a field accepts: a number's value, or a string's or a list's length."""

    low: float
    high: float


def schema_bounds(model, name: str) -> Bounds:
    """A field's bounds as the schema gives them: a number's as the closed interval of the floats it accepts
    (an open end, ``gt`` or ``lt``, moves one float inwards), or a string's or a list's length."""
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
        if getattr(rule, "min_length", None) is not None:
            low = rule.min_length
        if getattr(rule, "max_length", None) is not None:
            high = rule.max_length
    return Bounds(low, high)


#: The fields the reader handles, per request model: the :mod:`service.fixes.decode` structs' fields (and
#: ``type``, their tag). A test holds each set against the model's own fields, so a field added to the schema
#: fails it until the reader handles the field.
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

#: Fields the reader leaves to the schema: a body that holds one is validated and read by the schema.
SCHEMA_ONLY = frozenset({(schemas.FixRequest, "observed_at"), (schemas.FixRequest, "cot")})

#: Every bounded field the reader checks, by (schema model, field name): its bounds, read from the schema.
RULES = {(model, name): schema_bounds(model, name) for model, name in (
    (schemas.FixRequest, "stations"),
    (schemas.FixRequest, "measurements"),
    (schemas.FixRequest, "formats"),
    (schemas.Station, "id"),
    (schemas.GeodeticPosition, "lat_deg"),
    (schemas.GeodeticPosition, "lon_deg"),
    (schemas.GeodeticPosition, "alt_m"),
    (schemas.LocalPosition, "east_m"),
    (schemas.LocalPosition, "north_m"),
    (schemas.LocalPosition, "up_m"),
    (schemas.BearingMeasurement, "station_id"),
    (schemas.BearingMeasurement, "azimuth_deg"),
    (schemas.BearingMeasurement, "elevation_deg"),
    (schemas.BearingMeasurement, "sigma_azimuth_deg"),
    (schemas.BearingMeasurement, "sigma_elevation_deg"),
    (schemas.RangeMeasurement, "station_id"),
    (schemas.RangeMeasurement, "range_m"),
    (schemas.RangeMeasurement, "sigma_m"),
    (schemas.ToaMeasurement, "station_id"),
    (schemas.ToaMeasurement, "toa_s"),
    (schemas.ToaMeasurement, "sigma_s"),
    (schemas.Options, "max_iterations"),
    (schemas.Options, "tolerance_m"),
    (schemas.Options, "loss_scale"),
    (schemas.Constraints, "altitude_m"),
)}


def _names(annotation) -> frozenset:
    """The names a ``Literal`` (or a list or an optional of one) allows."""
    found = set()
    for arg in typing.get_args(annotation):
        if isinstance(arg, str):
            found.add(arg)
        else:
            found |= _names(arg)
    return frozenset(found)


#: Every field of closed names the reader checks, by (schema model, field name): the names, read from the schema.
CHOICES = {(model, name): _names(model.model_fields[name].annotation) for model, name in (
    (schemas.FixRequest, "frame"),
    (schemas.FixRequest, "method"),
    (schemas.FixRequest, "formats"),
    (schemas.Options, "variant"),
    (schemas.Options, "outliers"),
    (schemas.Options, "loss"),
    (schemas.BearingMeasurement, "type"),
    (schemas.RangeMeasurement, "type"),
    (schemas.ToaMeasurement, "type"),
)}

#: The schema's rules that span fields (validators, by model name and method name), each re-implemented by the
#: reader: frame and station positions agree, the body is within the fix cost limit, an elevation has a sigma.
VALIDATORS = frozenset({("FixRequest", "_stations_match_frame"), ("FixRequest", "_within_cost"),
                        ("BearingMeasurement", "_elevation_sigma")})

FRAME = schemas.FixRequest.model_fields["frame"].default
METHOD = schemas.FixRequest.model_fields["method"].default
DEFAULT_OPTIONS = schemas.Options()
DEFAULT_SOLVE = SolveOptions(DEFAULT_OPTIONS.max_iterations, DEFAULT_OPTIONS.tolerance_m, DEFAULT_OPTIONS.variant,
                             DEFAULT_OPTIONS.outliers, DEFAULT_OPTIONS.absolute_sigma, DEFAULT_OPTIONS.loss,
                             DEFAULT_OPTIONS.loss_scale)

AZ, EL, RG, TOA = int(Kind.AZIMUTH), int(Kind.ELEVATION), int(Kind.RANGE), int(Kind.TOA)
_GEODETIC = [RULES[schemas.GeodeticPosition, name] for name in ("lat_deg", "lon_deg", "alt_m")]
_LOCAL = [RULES[schemas.LocalPosition, name] for name in ("east_m", "north_m", "up_m")]
#: The bounds as tables for the bulk checks: per frame (local, geodetic) and coordinate ``(2, 3, 2)``, and per
#: measurement kind code ``(4, 2)``: a value's and a sigma's.
COORDINATE_BOUNDS = np.array([_LOCAL, _GEODETIC], dtype=float)
_VALUES = {AZ: ("BearingMeasurement", "azimuth_deg", "sigma_azimuth_deg"),
           EL: ("BearingMeasurement", "elevation_deg", "sigma_elevation_deg"),
           RG: ("RangeMeasurement", "range_m", "sigma_m"),
           TOA: ("ToaMeasurement", "toa_s", "sigma_s")}
VALUE_BOUNDS = np.array([RULES[getattr(schemas, _VALUES[k][0]), _VALUES[k][1]] for k in range(4)], dtype=float)
SIGMA_BOUNDS = np.array([RULES[getattr(schemas, _VALUES[k][0]), _VALUES[k][2]] for k in range(4)], dtype=float)
