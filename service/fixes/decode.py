"""Fix requests as the fast reader decodes them: typed structs straight from the JSON bytes.

msgspec decodes a body into these structs in one C pass: JSON types checked
(strict as the schema: a boolean or a string is not a number, an integer is
a float, no null where the schema has none), unknown fields refused, no dict
per object. What these types do not say (bounds, lengths, the frame's
position kind, station references) :func:`service.fixes.read.read_fix_requests`
checks in bulk. When a body (or one problem of a batch) does not decode, it
is parsed as plain JSON and each problem's dicts are converted to these
structs (:func:`as_fix_body`); a problem that does not convert either, or
that carries a field the structs leave out (``observed_at``, ``cot``), is
read through the schema (:mod:`service.schemas`), which words its error.

Absent fields are ``UNSET`` (``None`` where the schema's default is null), so
the schema's defaults stay the only ones. A problem the reader refuses goes to
the schema as the dicts it was decoded from (:func:`as_builtins`).
``service.fixes.rules.READ_FIELDS`` lists these fields per schema model, and a
test holds them to the models.

Why msgspec (a well-kept C extension) rather than orjson's dicts and a walk
over them: 10,000 four-station bodies (11.3 MB) became one core batch in
106-134 ms (decode 33-38 ms, read 72-95 ms) against 183-215 ms (orjson 65-82,
dict walk and read 117-133), best of 5 per process, three processes of each
alternating on one machine.
"""

from __future__ import annotations

from typing import Annotated

import msgspec
from msgspec import UNSET, Struct, UnsetType


class Position(Struct, forbid_unknown_fields=True, omit_defaults=True):
    """A GeodeticPosition's or a LocalPosition's fields: the request's frame says which it must hold."""

    lat_deg: float | UnsetType = UNSET
    lon_deg: float | UnsetType = UNSET
    alt_m: float | UnsetType = UNSET
    east_m: float | UnsetType = UNSET
    north_m: float | UnsetType = UNSET
    up_m: float | UnsetType = UNSET


class Station(Struct, forbid_unknown_fields=True, omit_defaults=True):
    id: str
    position: Position


class Bearing(Struct, tag_field="type", tag="bearing", forbid_unknown_fields=True, omit_defaults=True):
    station_id: str
    azimuth_deg: float
    elevation_deg: float | None = None
    sigma_azimuth_deg: float | None = None
    sigma_elevation_deg: float | None = None


class Range(Struct, tag_field="type", tag="range", forbid_unknown_fields=True, omit_defaults=True):
    station_id: str
    range_m: float
    sigma_m: float


class Toa(Struct, tag_field="type", tag="toa", forbid_unknown_fields=True, omit_defaults=True):
    station_id: str
    toa_s: float
    sigma_s: float


#: Signed 64-bit integers, which orjson parses as integers too; it makes a float of an integer beyond 64 bits,
#: which the schema then refuses as an integer. Beyond these the body is left to orjson and the schema, so that
#: its answer does not depend on the parser.
_JSON_INT = Annotated[int, msgspec.Meta(ge=-(2**63), le=2**63 - 1)]


class Options(Struct, forbid_unknown_fields=True, omit_defaults=True):
    max_iterations: _JSON_INT | UnsetType = UNSET
    tolerance_m: float | UnsetType = UNSET
    initial_guess: Position | None = None
    variant: str | None = None
    outliers: str | UnsetType = UNSET
    absolute_sigma: bool | UnsetType = UNSET
    loss: str | UnsetType = UNSET
    loss_scale: float | UnsetType = UNSET


class Constraints(Struct, forbid_unknown_fields=True, omit_defaults=True):
    altitude_m: float | None = None


class FixBody(Struct, forbid_unknown_fields=True, omit_defaults=True):
    """A FixRequest body without ``observed_at`` and ``cot``."""

    stations: list[Station]
    measurements: list[Bearing | Range | Toa]
    frame: str | UnsetType = UNSET
    origin: Position | None = None
    method: str | UnsetType = UNSET
    constraints: Constraints | None = None
    options: Options | UnsetType = UNSET
    formats: list[str] | UnsetType = UNSET


class _Batch(Struct, forbid_unknown_fields=True, omit_defaults=True):
    problems: list[FixBody]


_fix_decoder = msgspec.json.Decoder(FixBody)
_batch_decoder = msgspec.json.Decoder(_Batch)


def decode_fix(raw: bytes) -> FixBody | None:
    """The body as a :class:`FixBody`, or None when it is not one (parse it as JSON then)."""
    try:
        return _fix_decoder.decode(raw)
    except (msgspec.ValidationError, msgspec.DecodeError):
        return None


def decode_batch(raw: bytes) -> list[FixBody] | None:
    """The problems of a ``{"problems": [...]}`` body whose every problem is a :class:`FixBody`, or None."""
    try:
        return _batch_decoder.decode(raw).problems
    except (msgspec.ValidationError, msgspec.DecodeError):
        return None


def as_fix_body(body) -> FixBody | None:
    """A parsed JSON body (dicts and lists) as a :class:`FixBody`, or None when it is not one."""
    if type(body) is FixBody:
        return body
    try:
        return msgspec.convert(body, FixBody)
    except msgspec.ValidationError:
        return None


def as_builtins(body):
    """A body as parsed JSON: a :class:`FixBody` as the dicts and lists it was decoded from (less the nulls
    that mean what an absent field means), anything else as it is."""
    return msgspec.to_builtins(body) if type(body) is FixBody else body


def requested_method(body):
    """The ``method`` a parsed or decoded body asks for (``"auto"`` when absent; None when it is no object)."""
    if type(body) is FixBody:
        return "auto" if body.method is UNSET else body.method
    return body.get("method", "auto") if type(body) is dict else None


def requests_exclusion(body) -> bool:
    """Whether a parsed or decoded body asks for ``options.outliers`` ``"exclude"``."""
    if type(body) is FixBody:
        return body.options is not UNSET and body.options.outliers == "exclude"
    options = body.get("options") if type(body) is dict else None
    return type(options) is dict and options.get("outliers") == "exclude"


def station_count(body) -> int | None:
    """How many stations a parsed or decoded body holds (None when it holds no list of them)."""
    if type(body) is FixBody:
        return len(body.stations)
    stations = body.get("stations") if type(body) is dict else None
    return len(stations) if type(stations) is list else None


def measurement_count(body) -> int | None:
    """How many measurements a parsed or decoded body holds (None when it holds no list of them)."""
    if type(body) is FixBody:
        return len(body.measurements)
    measurements = body.get("measurements") if type(body) is dict else None
    return len(measurements) if type(measurements) is list else None
