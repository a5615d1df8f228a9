"""The bulk reader's range checks hold every bounded request field exactly where the schema does: at each bound
a value is read, one float beyond it the request gets the schema's error (the reader must never let through what
the schema refuses, nor send a valid value down the slow path with an error)."""

from __future__ import annotations

import copy
import math

import pytest

from service import schemas
from service.fixes.read import read_fix_requests
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
