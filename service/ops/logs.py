"""Log lines as JSON objects (timestamp, level, logger, message, the request id, any exception), or as text.

The format ``auto`` (the default) is text when stderr is a terminal (a person
reads it) and JSON otherwise (a log collector reads it); ``json`` or ``text``
chooses one whatever stderr is.

The request id is a context variable the middleware sets, so every line logged
while a request is served names it (also from threads the request's work runs
on, when the work was started with the context copied, as asyncio's executor
helpers and Starlette's thread pool do). Nothing logs measurement values at INFO.
"""

from __future__ import annotations

import contextvars
import logging
import sys
import time

import orjson

request_id_var: contextvars.ContextVar[str | None] = contextvars.ContextVar("request_id", default=None)

#: Attributes of every LogRecord; anything else passed with ``extra=`` becomes a field of the line.
_STANDARD = frozenset(vars(logging.LogRecord("", 0, "", 0, "", (), None))) | {"message", "asctime", "taskName"}


class JsonFormatter(logging.Formatter):
    """One JSON object per line (RFC 3339 UTC timestamps with milliseconds)."""

    def format(self, record: logging.LogRecord) -> str:
        seconds = int(record.created)
        line = {
            "timestamp": time.strftime("%Y-%m-%dT%H:%M:%S", time.gmtime(seconds)) + f".{record.msecs:03.0f}Z",
            "level": record.levelname.lower(),
            "logger": record.name,
            "message": record.getMessage(),
        }
        request_id = getattr(record, "request_id", None) or request_id_var.get()
        if request_id:
            line["request_id"] = request_id
        for key, value in vars(record).items():
            if key not in _STANDARD and key not in line and not key.startswith("_"):
                line[key] = value
        if record.exc_info:
            line["exception"] = self.formatException(record.exc_info)
        return orjson.dumps(line, default=str).decode()


class _RequestIdFilter(logging.Filter):
    def filter(self, record: logging.LogRecord) -> bool:
        if not getattr(record, "request_id", None):
            record.request_id = request_id_var.get() or "-"
        return True


def resolved_format(fmt: str, stream=None) -> str:
    """``json`` or ``text``: ``fmt`` itself, or for ``auto`` text when ``stream`` (default stderr) is a terminal."""
    if fmt != "auto":
        return fmt
    stream = sys.stderr if stream is None else stream
    try:
        return "text" if stream.isatty() else "json"
    except (AttributeError, ValueError):  # no stream, or a closed one
        return "json"


def configure(level: str = "info", fmt: str = "auto") -> None:
    """Give the service's logger one stderr handler in the chosen format (replacing the one it had)."""
    handler = logging.StreamHandler()
    if resolved_format(fmt, handler.stream) == "json":
        handler.setFormatter(JsonFormatter())
    else:
        handler.setFormatter(logging.Formatter("%(asctime)s %(levelname)s %(name)s [%(request_id)s] %(message)s"))
        handler.addFilter(_RequestIdFilter())
    handler._passive_locator = True  # type: ignore[attr-defined]
    logger = logging.getLogger("passive_locator")
    logger.handlers = [h for h in logger.handlers if not getattr(h, "_passive_locator", False)] + [handler]
    logger.propagate = False
    logger.setLevel(level.upper())


def uvicorn_log_config(level: str, fmt: str) -> dict:
    """A ``log_config`` for uvicorn with its loggers in the service's format."""
    formatter = {"()": "service.ops.logs.JsonFormatter"} if resolved_format(fmt) == "json" else \
        {"format": "%(asctime)s %(levelname)s %(name)s %(message)s"}
    return {
        "version": 1,
        "disable_existing_loggers": False,
        "formatters": {"default": formatter},
        "handlers": {"default": {"class": "logging.StreamHandler", "formatter": "default",
                                 "stream": "ext://sys.stderr"}},
        "loggers": {
            "uvicorn": {"handlers": ["default"], "level": level.upper(), "propagate": False},
            "uvicorn.error": {"level": level.upper()},
            "uvicorn.access": {"handlers": [], "level": "WARNING", "propagate": False},
        },
    }
