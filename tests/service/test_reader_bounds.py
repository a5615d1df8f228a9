"""The bulk reader's range checks hold every bounded request field exactly where the schema does: at each bound
a value is read, one float beyond it the request gets the schema's error (the reader must never let through what
the schema refuses, nor send a valid value down the slow path with an error)."""

from __future__ import annotations

import copy
import math
import typing

import pytest

from service import schemas
from service.fixes.read import read_fix_requests
from service.fixes.rules import CHOICES, READ_FIELDS, RULES, SCHEMA_ONLY
from tests.service.test_extreme_values import _with

BASE = {
    "frame": "wgs84",
    "method": "ml",
    "stations": [{"id": "a", "position": {"lat_deg": 34.0, "lon_deg": 108.5, "alt_m": 100.0}},
                 {"id": "b", "position": {"lat_deg": 34.3, "lon_deg": 108.9, "alt_m": 50.0}}],
    "measurements": [
        {"type": "bearing", "station_id": "a", "azimuth_deg": 40.0, "elevation_deg": 2.0,
         "sigma_azimuth_deg": 0.5, "sigma_elevation_deg": 0.5},
        {"type": "range", "station_id": "b", "range_m": 30_000.0, "sigma_m": 50.0},
        {"type": "toa", "station_id": "b", "toa_s": 1e-3, "sigma_s": 1e-8},
    ],
}
LOCAL = {**copy.deepcopy(BASE), "frame": "local",
         "stations": [{"id": "a", "position": {"east_m": 0.0, "north_m": 0.0, "up_m": 0.0}},
                      {"id": "b", "position": {"east_m": 9e3, "north_m": 2e3, "up_m": 10.0}}]}
OPTIONS = {**copy.deepcopy(BASE), "options": {"tolerance_m": 1e-3, "loss_scale": 1.0},
           "constraints": {"altitude_m": 100.0}}
#: (request, path to the value, schema model, field)
FIELDS = [
    (BASE, ("stations", 0, "position", "lat_deg"), schemas.GeodeticPosition, "lat_deg"),
    (BASE, ("stations", 0, "position", "lon_deg"), schemas.GeodeticPosition, "lon_deg"),
    (BASE, ("stations", 0, "position", "alt_m"), schemas.GeodeticPosition, "alt_m"),
    (LOCAL, ("stations", 1, "position", "east_m"), schemas.LocalPosition, "east_m"),
    (LOCAL, ("stations", 1, "position", "north_m"), schemas.LocalPosition, "north_m"),
    (LOCAL, ("stations", 1, "position", "up_m"), schemas.LocalPosition, "up_m"),
    (BASE, ("measurements", 0, "azimuth_deg"), schemas.BearingMeasurement, "azimuth_deg"),
    (BASE, ("measurements", 0, "elevation_deg"), schemas.BearingMeasurement, "elevation_deg"),
    (BASE, ("measurements", 0, "sigma_azimuth_deg"), schemas.BearingMeasurement, "sigma_azimuth_deg"),
    (BASE, ("measurements", 0, "sigma_elevation_deg"), schemas.BearingMeasurement, "sigma_elevation_deg"),
    (BASE, ("measurements", 1, "range_m"), schemas.RangeMeasurement, "range_m"),
    (BASE, ("measurements", 1, "sigma_m"), schemas.RangeMeasurement, "sigma_m"),
    (BASE, ("measurements", 2, "toa_s"), schemas.ToaMeasurement, "toa_s"),
    (BASE, ("measurements", 2, "sigma_s"), schemas.ToaMeasurement, "sigma_s"),
    (OPTIONS, ("options", "tolerance_m"), schemas.Options, "tolerance_m"),
    (OPTIONS, ("options", "loss_scale"), schemas.Options, "loss_scale"),
    (OPTIONS, ("constraints", "altitude_m"), schemas.Constraints, "altitude_m"),
]


def _limits(model, field):
    """``(value, inclusive)`` of each finite bound the schema states for a field."""
    out = []
    for rule in model.model_fields[field].metadata:
        for name, inclusive, side in (("ge", True, -1), ("gt", False, -1), ("le", True, 1), ("lt", False, 1)):
            value = getattr(rule, name, None)
            if value is not None and math.isfinite(value):
                out.append((float(value), inclusive, side))
    return out


@pytest.mark.parametrize("request_body, path, model, field", FIELDS, ids=[f[3] for f in FIELDS])
def test_each_bound_is_held_to_the_last_float(request_body, path, model, field):
    limits = _limits(model, field)
    assert limits, f"{model.__name__}.{field} states no bound: this test has nothing to hold"
    for bound, inclusive, side in limits:
        inside = bound if inclusive else math.nextafter(bound, -side * math.inf)
        outside = math.nextafter(bound, side * math.inf) if inclusive else bound
        read = read_fix_requests([_with(request_body, path, inside), _with(request_body, path, outside)])
        assert 0 not in read.errors, f"{field} = {inside!r} is inside the schema's bound but was refused"
        assert 1 in read.errors, f"{field} = {outside!r} is outside the schema's bound but was read"
        assert read.errors[1]["status"] == 422
        assert [tuple(e["loc"]) for e in read.errors[1]["errors"]] == [path], read.errors[1]


#: The integer bounds, which the float probes above cannot hold: each is held at its ends here.
INTEGER_FIELDS = [(OPTIONS, ("options", "max_iterations"), schemas.Options, "max_iterations")]


def test_a_body_one_past_an_integer_bound_gets_the_schemas_error():
    for request_body, path, model, field in INTEGER_FIELDS:
        low, high = RULES[model, field]
        values = [int(low), int(high), int(low) - 1, int(high) + 1]
        read = read_fix_requests([_with(request_body, path, value) for value in values])
        assert 0 not in read.errors and 1 not in read.errors, field
        for slot in (2, 3):
            assert [tuple(e["loc"]) for e in read.errors[slot]["errors"]] == [path], read.errors[slot]


def _bounded(model, name) -> bool:
    return any(getattr(rule, attr, None) is not None for rule in model.model_fields[name].metadata
               for attr in ("ge", "gt", "le", "lt", "min_length", "max_length", "pattern"))


def _has_names(annotation) -> bool:
    return typing.get_origin(annotation) is typing.Literal or any(_has_names(a) for a in typing.get_args(annotation))


def test_every_rule_of_a_field_the_reader_reads_is_in_its_table():
    """A bound, a pattern or a closed set of names added to a request field fails here until the reader's one
    table (``service.fixes.rules``) lists it, or the reader leaves bodies with that field to the schema; and every
    number the table bounds is probed at its ends above."""
    left_to_schema = {model for (owner, name) in SCHEMA_ONLY
                      for model in _models(owner.model_fields[name].annotation)}
    for model, fields in READ_FIELDS.items():
        if model in left_to_schema:
            continue
        for name in fields:
            if (model, name) in SCHEMA_ONLY:
                continue
            if _bounded(model, name):
                assert (model, name) in RULES, f"{model.__name__}.{name} has a bound the reader's RULES lack"
                assert not any(getattr(rule, "pattern", None) for rule in model.model_fields[name].metadata), \
                    f"{model.__name__}.{name}: the reader checks no pattern; leave the field to the schema"
            if _has_names(model.model_fields[name].annotation):
                assert (model, name) in CHOICES, f"{model.__name__}.{name} names choices the reader's CHOICES lack"
    probed = {(model, field) for *_, model, field in FIELDS + INTEGER_FIELDS}
    numbers = {(model, name) for model, name in RULES if _is_number(model.model_fields[name].annotation)}
    assert numbers <= probed, numbers - probed


def _is_number(annotation) -> bool:
    return annotation in (float, int) or set(typing.get_args(annotation)) in ({float, type(None)}, {int, type(None)})


def _models(annotation):
    from pydantic import BaseModel

    if isinstance(annotation, type) and issubclass(annotation, BaseModel):
        yield annotation
    for arg in typing.get_args(annotation):
        yield from _models(arg)
