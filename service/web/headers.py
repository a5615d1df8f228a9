"""The request header fields the service reads, parsed once, strictly, before anything uses them.

Every field the service acts on is read here and nowhere else: the middleware calls
:meth:`RequestHeaders.parse` on each request and keeps the result in the scope (``state["headers"]``, read
back with :func:`of`). A value outside its grammar is a :class:`HeaderError` (400 problem+json naming the
field; 401 for ``Authorization``) rather than whatever the first ``int()`` or ``split()`` that meets it
does: Python's ``str.isdigit`` holds for ``'²'`` which ``int`` refuses, and ``int`` refuses more than 4,300
digits, each of which was a 500.

The grammars are RFC 9110's, restricted to visible ASCII (obs-text is refused), with a bound on length:

- numbers (``Content-Length``, ``Last-Event-ID``): ``1*DIGIT`` of ASCII digits, at most 19 (an int64);
- ``X-Request-ID``: 1..128 visible ASCII characters;
- ``Authorization``: ``auth-scheme [ 1*SP token68 ]`` (RFC 9110 11.4 / RFC 6750 2.1);
- ``Content-Type``: ``type "/" subtype *( OWS ";" OWS [ parameter ] )``;
- ``Accept``: a list of media ranges with an optional ``q`` of at most three decimals in [0, 1];
- ``If-Match``: ``"*"`` or a list of entity tags (a bare version number is taken for its quoted form).

A field defined to hold one value (:data:`SINGLETONS`) sent on several lines is refused: two
``Authorization`` lines would otherwise be one identity to whatever takes the first and another to whatever
takes the last. List fields (``Accept``) on several lines are joined with commas (RFC 9110 5.3).
"""

from __future__ import annotations

import re
from dataclasses import dataclass

#: Fields that hold one value: more than one line of any of them is a 400 (401 for Authorization).
SINGLETONS = frozenset((b"authorization", b"content-type", b"content-length", b"if-match", b"last-event-id",
                        b"x-request-id", b"host", b"origin"))
#: The longest value of any field the service reads (larger ones are refused, not scanned).
MAX_VALUE_BYTES = 8192
#: Digits of a number field: 19 fit an int64 (and stay far from ``int``'s 4,300-digit refusal).
MAX_DIGITS = 19
#: Length of a client's ``X-Request-ID``.
MAX_REQUEST_ID = 128

_TOKEN = rb"[!#$%&'*+.^_`|~0-9A-Za-z-]+"
_QUOTED = rb'"(?:[\t !#-\[\]-~]|\\[\t -~])*"'
_PARAMETER = rb"%s=(?:%s|%s)" % (_TOKEN, _TOKEN, _QUOTED)
#: Every repeated group starts at its delimiter and takes the blanks after it only with what follows them, so
#: a run of blanks has one reading: two ``[ \t]*`` side by side in a repeated group made a failing match take
#: time exponential in the number of empty parameters or list elements.
_MEDIA_TYPE = re.compile(rb"(%s)/(%s)((?:[ \t]*;(?:[ \t]*%s)?)*)" % (_TOKEN, _TOKEN, _PARAMETER))
_ACCEPT = re.compile(rb"(?:[ \t]*%s)?(?:[ \t]*,(?:[ \t]*%s)?)*[ \t]*" % ((_MEDIA_TYPE.pattern,) * 2))
_PARAMETERS = re.compile(rb"[ \t]*;[ \t]*(%s)=(%s|%s)" % (_TOKEN, _TOKEN, _QUOTED))
_QVALUE = re.compile(rb"0(?:\.[0-9]{0,3})?|1(?:\.0{0,3})?")
_AUTHORIZATION = re.compile(rb"(%s)(?: +([A-Za-z0-9._~+/-]+=*))?" % _TOKEN)
_ENTITY_TAG = re.compile(rb'(?:W/)?"[!#-~]*"')
_DIGITS = re.compile(rb"[0-9]{1,%d}" % MAX_DIGITS)
_VISIBLE = re.compile(rb"[!-~]{1,%d}" % MAX_REQUEST_ID)


class HeaderError(Exception):
    """A header field outside its grammar, or repeated where it holds one value."""

    def __init__(self, field: str, detail: str):
        super().__init__(f"{field}: {detail}")
        self.field = field
        self.detail = f"header {field}: {detail}"

    @property
    def status(self) -> int:
        return 401 if self.field == "Authorization" else 400


@dataclass(frozen=True)
class MediaRange:
    """One element of ``Accept``: ``type/subtype`` in lower case and its weight ``q`` in [0, 1]."""

    media: str
    q: float


@dataclass(frozen=True)
class Credentials:
    """``Authorization: <scheme> <token68>``: the scheme in lower case, the token as sent (None without one)."""

    scheme: str
    token: bytes | None


@dataclass(frozen=True)
class RequestHeaders:
    """The fields the service reads, parsed (None: absent).

    Attributes
    ----------
    authorization : Credentials or None
    content_type : bytes or None
        The media type, ``type/subtype`` in lower case, without parameters.
    content_length : int or None
    request_id : str or None
        The client's ``X-Request-ID``.
    if_match : tuple of str or None
        The entity tags as sent (``'"7"'``, ``'W/"7"'``), or ``("*",)``.
    last_event_id : int or None
    accept : tuple of MediaRange
        Empty when absent (anything is acceptable).
    """

    authorization: Credentials | None = None
    content_type: bytes | None = None
    content_length: int | None = None
    request_id: str | None = None
    if_match: tuple[str, ...] | None = None
    last_event_id: int | None = None
    accept: tuple[MediaRange, ...] = ()

    @classmethod
    def parse(cls, raw: list[tuple[bytes, bytes]]) -> "RequestHeaders":
        """Parse the ASGI scope's header list (names in lower case).

        Raises
        ------
        HeaderError
            A field outside its grammar or over :data:`MAX_VALUE_BYTES`, or a singleton field repeated.
        """
        fields: dict[bytes, bytes] = {}
        for name, value in raw:
            if name not in _READ:
                continue
            if len(value) > MAX_VALUE_BYTES:
                raise HeaderError(_display(name), f"longer than {MAX_VALUE_BYTES} bytes")
            if name in fields:
                if name in SINGLETONS:
                    raise HeaderError(_display(name), "sent more than once (it holds one value)")
                fields[name] += b", " + value
            else:
                fields[name] = value
        parsed = {attribute: parse(fields[name]) for name, (attribute, parse) in _PARSERS.items() if name in fields}
        return cls(**parsed) if parsed else _NONE


#: Field -> (attribute of RequestHeaders, its parser).
_PARSERS = {
    b"authorization": ("authorization", lambda value: parse_authorization(value)),
    b"content-type": ("content_type", lambda value: parse_media_type(value)),
    b"content-length": ("content_length", lambda value: parse_number("Content-Length", value)),
    b"x-request-id": ("request_id", lambda value: parse_request_id(value)),
    b"if-match": ("if_match", lambda value: parse_if_match(value)),
    b"last-event-id": ("last_event_id", lambda value: parse_number("Last-Event-ID", value)),
    b"accept": ("accept", lambda value: parse_accept(value)),
}
#: Every field looked at: the parsed ones and the singletons only checked for repeats.
_READ = SINGLETONS | frozenset(_PARSERS)
_NONE = RequestHeaders()
_ANYTHING = (MediaRange("*/*", 1.0),)


def _display(name: bytes) -> str:
    """A field name as documents spell it (``last-event-id`` -> ``Last-Event-ID``)."""
    special = {b"x-request-id": "X-Request-ID", b"last-event-id": "Last-Event-ID"}
    return special.get(name) or "-".join(part.capitalize() for part in name.decode("latin-1").split("-"))


def _strip(value: bytes) -> bytes:
    return value.strip(b" \t")


def parse_number(field: str, value: bytes) -> int:
    """``1*DIGIT`` in ASCII, at most :data:`MAX_DIGITS` digits."""
    value = _strip(value)
    if not _DIGITS.fullmatch(value):
        raise HeaderError(field, f"not a non-negative integer of 1 to {MAX_DIGITS} ASCII digits")
    return int(value)


def parse_request_id(value: bytes) -> str:
    value = _strip(value)
    if not _VISIBLE.fullmatch(value):
        raise HeaderError("X-Request-ID", f"not 1 to {MAX_REQUEST_ID} visible ASCII characters")
    return value.decode("ascii")


def parse_authorization(value: bytes) -> Credentials:
    found = _AUTHORIZATION.fullmatch(_strip(value))
    if found is None:
        raise HeaderError("Authorization", "not '<scheme> <token>' in visible ASCII (Bearer <key>)")
    return Credentials(found.group(1).decode("ascii").lower(), found.group(2))


def parse_media_type(value: bytes) -> bytes:
    found = _MEDIA_TYPE.fullmatch(_strip(value))
    if found is None:
        raise HeaderError("Content-Type", "not a media type (type/subtype; parameters)")
    return found.group(1).lower() + b"/" + found.group(2).lower()


def parse_accept(value: bytes) -> tuple[MediaRange, ...]:
    """The media ranges of an ``Accept`` value, in the order sent (empty list elements are allowed, as RFC 9110
    5.6.1 says; a comma inside a quoted parameter value is part of that value)."""
    if value == b"*/*":
        return _ANYTHING  # what most clients send
    if not _ACCEPT.fullmatch(value):
        raise HeaderError("Accept", "not a list of media ranges (type/subtype;q=0.5, ...) in visible ASCII")
    ranges = []
    for found in _MEDIA_TYPE.finditer(value):
        q = 1.0
        for name, parameter in _PARAMETERS.findall(found.group(3)):
            if name.lower() == b"q":
                if not _QVALUE.fullmatch(parameter):
                    raise HeaderError("Accept", f"q={parameter[:10].decode('ascii')} is not a weight in [0, 1] "
                                                "with at most three decimals")
                q = float(parameter)
        ranges.append(MediaRange((found.group(1) + b"/" + found.group(2)).decode("ascii").lower(), q))
    return tuple(ranges)


def parse_if_match(value: bytes) -> tuple[str, ...]:
    value = _strip(value)
    if value == b"*":
        return ("*",)
    tags = []
    for element in value.split(b","):
        element = _strip(element)
        if not element:
            continue
        if _DIGITS.fullmatch(element):
            element = b'"' + element + b'"'  # a bare version: what clients that drop the quotes send
        if not _ENTITY_TAG.fullmatch(element):
            raise HeaderError("If-Match", 'not "*" or a list of entity tags ("7")')
        tags.append(element.decode("ascii"))
    if not tags:
        raise HeaderError("If-Match", 'not "*" or a list of entity tags ("7")')
    return tuple(tags)


def of(request) -> RequestHeaders:
    """The parsed headers of a request (a Starlette ``Request`` or an ASGI scope) that went through the
    middleware."""
    scope = getattr(request, "scope", request)
    return scope["state"]["headers"]
