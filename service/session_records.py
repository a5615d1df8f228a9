"""What every session record gives, whichever kind of session it holds: its ETag and the If-Match check
against it, its CoT options, and its times as the API writes them.

Both :mod:`service.sessions` (paper-001 sessions) and :mod:`service.network_sessions` use these, so they
live below both.
"""

from __future__ import annotations

from datetime import datetime, timezone

from service.renderings import utc_timestamp
from service.stores import SessionRecord


def timestamp(unix_s: float) -> str:
    """A record's time (Unix seconds) as the API writes times: RFC 3339 UTC."""
    return utc_timestamp(datetime.fromtimestamp(unix_s, timezone.utc))


def cot_options(record: SessionRecord):
    """The session's :class:`service.schemas.CotOptions`, or None."""
    from service.schemas import CotOptions

    found = record.config["request"].get("cot")
    return None if found is None else CotOptions.model_validate(found)


def etag(record: SessionRecord) -> str:
    return f'"{record.version}"'


def if_match_accepts(tags: tuple[str, ...], version: int) -> bool:
    """Whether ``If-Match``'s entity tags (as :func:`service.headers.parse_if_match` gives them) name this
    version (``*`` names any; weak tags never match)."""
    return "*" in tags or f'"{version}"' in tags
