"""Service settings from the environment (prefix ``PASSIVE_LOCATOR_``)."""

from __future__ import annotations

import pathlib
import re
from typing import Literal

from pydantic import Field, field_validator
from pydantic_settings import BaseSettings, SettingsConfigDict

_SHA256_HEX = re.compile(r"[0-9a-f]{64}")
#: Default ``inline_fix_cost``: see :class:`Settings`.
INLINE_FIX_COST = 128


class Settings(BaseSettings):
    """Runtime configuration (README, "Configuration", lists each with its environment variable).

    Attributes
    ----------
    store : str
        Session store URL: ``sqlite:///path`` (embedded default) or
        ``redis://host:port/db``.
    store_timeout_s : float
        The backend's own timeout: Redis connect and read; a SQLite write's wait for its turn (this process's
        writers in order, then another process's lock), each wait.
    store_call_timeout_s : float
        A store call not done by then answers 503 (with ``Retry-After``).
    store_workers : int
        Threads that make store calls (at most this many touch the store at once).
    store_breaker_failures, store_breaker_cooldown_s
        After this many store failures in a row, calls fail at once (503) for the cooldown.
    sqlite_integrity_interval_s : float
        ``/readyz`` runs SQLite's ``quick_check`` at most this often.
    events_poll_s : float
        Without Redis, an event stream looks in the store this often for what other server processes wrote
        (this process's writes are pushed at once), and sends a keep-alive comment when idle.
    max_body_bytes : int
        Larger request bodies get 413 (declared or streamed).
    header_timeout_s : float
        A request's line and headers must arrive within this of the connection opening (or of an idle
        connection's first byte); else 408 and the connection is closed.
    body_timeout_s : float
        A request's whole body must arrive within this of its headers (else 408, connection closed): at
        the default max_body_bytes, 32 MiB in 30 s is about 1.1 MB/s.
    max_connections : int
        Open connections per server process; one more closes the one that has waited longest for its
        client (503 too_many_connections). Keep it below the open-file limit (ulimit -n).
    api_key_hashes : str
        Comma-separated SHA-256 hex digests of the accepted bearer keys (``sha256sum`` of the key without a
        newline); empty with no file disables authentication.
    api_key_hashes_file : str
        A file with more digests, one per line (``#`` comments allowed).
    allow_anonymous : bool
        Needed to serve without keys on a non-loopback address.
    rate_limit_per_s : float
        Sustained requests per second per client (the authenticated key, else the client address); 0 disables.
    rate_limit_burst : int
    cors_allow_origins : list of str
        Origins whose browser pages may call the API (a JSON list, ``["*"]`` for any); empty (the
        default) sends no CORS headers, so browsers refuse cross-origin calls.
    rate_limit_clients : int
        Buckets kept (least recently seen dropped first): the limiter's memory is bounded.
    request_deadline_s : float
        Longest computation of one request (evaluations, fixes and batches stop between chunks; 503
        ``deadline_exceeded``).
    max_evaluation_cost : int
        Largest ``trials x measurement rows x method weights`` of one evaluation (422 ``over_limit`` above).
    max_batch_cost : int
        Largest sum over a batch's problems of ``measurements x method weight`` (batched methods 1, others
        25: service.limits).
    max_fix_cost : int
        Largest ``stations x measurements`` of one fix (also of each batch problem).
    inline_fix_cost : int
        ``POST /v1/fixes`` solves a fix whose cost estimate (``stations x measurements``, as ``max_fix_cost``
        counts it) is at most this on the event loop, larger ones on a worker thread (watched for the deadline);
        0 sends every fix to the worker. The default, 8 stations x 16 bearings, is about where an ML fix starts
        to cost more than its fixed per-call overhead (``python -m bench.inline_threshold``: 270 us of thread
        CPU at 16, 310 us at 128, 630 us at 576, on a loaded two-core machine). The estimate weighs every method
        alike: a small los_intersection fix costs about four times an ML fix of the same estimate.
    max_grid_cost : int
        Largest ``cells x measurement rows`` of one coverage map (``POST /v1/crlb/grid``; 422 ``over_limit``).
    dask_scheduler : str or None
        Address of a Dask distributed scheduler (``tcp://host:8786``; needs the ``distributed`` extra) that runs
        the chunks of evaluations and coverage maps (also the default of the ``evaluate``, ``reproduce`` and
        ``map`` commands); None (the default) runs the same chunks in this process, on the CPU pool. The result
        for a seed is the same either way.
    cpu_workers : int
        Threads for the CPU-bound evaluations, apart from everything else.
    graceful_timeout_s : float
        On SIGTERM, in-flight requests get this long before they are cancelled.
    log_format : {"auto", "json", "text"}
        Log lines as JSON objects or as text; ``auto``: text when stderr is a terminal, JSON otherwise.
    """

    model_config = SettingsConfigDict(env_prefix="PASSIVE_LOCATOR_", extra="ignore")

    store: str = "sqlite:///./var/sessions.db"
    store_timeout_s: float = Field(0.5, gt=0.0, le=60.0)
    store_call_timeout_s: float = Field(2.0, gt=0.0, le=120.0)
    store_workers: int = Field(8, ge=1, le=256)
    store_breaker_failures: int = Field(3, ge=1)
    store_breaker_cooldown_s: float = Field(1.0, gt=0.0, le=300.0)
    sqlite_integrity_interval_s: float = Field(60.0, ge=0.0)
    events_poll_s: float = Field(2.0, gt=0.0, le=3600.0)
    max_body_bytes: int = Field(32 * 1024 * 1024, gt=0)
    header_timeout_s: float = Field(10.0, gt=0.0, le=300.0)
    body_timeout_s: float = Field(30.0, gt=0.0, le=3600.0)
    max_connections: int = Field(1000, ge=1)
    api_key_hashes: str = ""
    api_key_hashes_file: str | None = None
    allow_anonymous: bool = False
    rate_limit_per_s: float = Field(0.0, ge=0.0)
    rate_limit_burst: int = Field(100, ge=1)
    rate_limit_clients: int = Field(10_000, ge=1)
    request_deadline_s: float = Field(30.0, gt=0.0)
    max_evaluation_cost: int = Field(400_000, ge=1)
    max_batch_cost: int = Field(200_000, ge=1)
    max_fix_cost: int = Field(256 * 1024, ge=1)
    inline_fix_cost: int = Field(INLINE_FIX_COST, ge=0)
    max_grid_cost: int = Field(200_000, ge=1)
    dask_scheduler: str | None = None
    cpu_workers: int = Field(2, ge=1, le=64)
    graceful_timeout_s: float = Field(10.0, gt=0.0)
    log_level: str = "info"
    cors_allow_origins: list[str] = Field(default_factory=list)
    log_format: Literal["auto", "json", "text"] = "auto"

    api_keys: str | None = Field(None, description="gone: plain keys in configuration are refused")

    @field_validator("api_keys")
    @classmethod
    def _no_plain_keys(cls, value: str | None) -> None:
        if value is not None:
            raise ValueError("PASSIVE_LOCATOR_API_KEYS (plain keys) is no longer read: configure their SHA-256 "
                             "digests in PASSIVE_LOCATOR_API_KEY_HASHES or PASSIVE_LOCATOR_API_KEY_HASHES_FILE")
        return None

    @field_validator("api_key_hashes")
    @classmethod
    def _digests(cls, value: str) -> str:
        for digest in _split(value):
            if not _SHA256_HEX.fullmatch(digest):
                raise ValueError("PASSIVE_LOCATOR_API_KEY_HASHES holds SHA-256 hex digests (64 of 0-9a-f), "
                                 "comma-separated, not keys")
        return value

    def key_digests(self) -> frozenset[bytes]:
        """Every configured SHA-256 digest (lower-case hex, as bytes); empty = authentication off.

        Raises
        ------
        ValueError
            A digest in the file that is not 64 hex digits.
        """
        digests = set(_split(self.api_key_hashes))
        if self.api_key_hashes_file:
            for number, line in enumerate(pathlib.Path(self.api_key_hashes_file).read_text().splitlines(), 1):
                line = line.split("#", 1)[0].strip().lower()
                if not line:
                    continue
                if not _SHA256_HEX.fullmatch(line):
                    raise ValueError(f"{self.api_key_hashes_file}:{number}: not a SHA-256 hex digest")
                digests.add(line)
        return frozenset(d.encode() for d in digests)


def _split(value: str) -> list[str]:
    return [part.strip().lower() for part in value.split(",") if part.strip()]
