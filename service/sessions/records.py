"""What every session record gives, whichever kind of session it holds: its ETag and the If-Match check
against it, its CoT options, its times as the API writes them, and its decoded filter state (cached by
version).

Both :mod:`service.sessions.observer` (paper-001 sessions) and :mod:`service.sessions.network` use these, so they
live below both.
"""

from __future__ import annotations

import collections
import threading
from datetime import datetime, timezone
from typing import Callable, TypeVar

from service.renderings.points import utc_timestamp
from service.stores import SessionRecord

T = TypeVar("T")


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
    """Whether ``If-Match``'s entity tags (as :func:`service.web.headers.parse_if_match` gives them) name this
    version (``*`` names any; weak tags never match)."""
    return "*" in tags or f'"{version}"' in tags


class DecodedStates:
    """The decoded filter state (and settings) of the records this process read or wrote last, by session id
    and decoder.

    A session's ``state`` is JSON in its record; a post steps the filter from the decoded value (a core state
    object with its arrays), and decoding thousands of numbers costs about as much as the filter step. A
    record's ``(id, version)`` names one state for the session's life (every write bumps the version by
    compare-and-set), and core states are immutable values, so the value decoded for a version, or made by
    the write that produced it, serves every later use of that version in this process.

    Parameters
    ----------
    size : int
        Values kept (least recently used dropped first).
    """

    def __init__(self, size: int = 256):
        self.size = size
        self._values: collections.OrderedDict[tuple[str, Callable], tuple[int, object]] = collections.OrderedDict()
        self._lock = threading.Lock()

    def get(self, record: SessionRecord, decode: Callable[[SessionRecord], T], fixed: bool = False) -> T:
        """``decode(record)``, or the value it gave (or :meth:`remember` was told) for this record's version;
        ``fixed``: ``decode`` reads only what a session never changes (its config), so any version's value
        serves."""
        key = (record.id, decode)
        with self._lock:
            found = self._values.get(key)
            if found is not None and (fixed or found[0] == record.version):
                self._values.move_to_end(key)
                return found[1]  # type: ignore[return-value]
        value = decode(record)
        self.remember(record, decode, value)
        return value

    def remember(self, record: SessionRecord, decode: Callable[[SessionRecord], T], value: T) -> None:
        """``value`` is what ``decode(record)`` gives: call only with a record as stored (read, or written and
        committed), never with one a write has yet to commit."""
        key = (record.id, decode)
        with self._lock:
            found = self._values.get(key)
            if found is not None and found[0] > record.version:
                return
            self._values[key] = (record.version, value)
            self._values.move_to_end(key)
            while len(self._values) > self.size:
                self._values.popitem(last=False)


#: This process's decoded session states.
decoded_states = DecodedStates()


class PrepareFirst(Exception):
    """Raised by a change, within the store's update call, that must not be decided there because its cost
    depends on the session rather than on the post's size (an auto network session re-runs its reorder window
    on every post): the route prepares it on a worker thread, under the request deadline, and applies it
    again. Nothing is written."""
