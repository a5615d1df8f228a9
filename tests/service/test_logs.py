"""The log format: text for a person at a terminal, JSON for a collector, and the setting wins over both."""

from __future__ import annotations

import io
import logging
import os
import pty

import orjson
import pytest

from service.ops import logs
from service.settings import Settings


class _Stream(io.StringIO):
    def __init__(self, tty: bool):
        super().__init__()
        self.tty = tty

    def isatty(self) -> bool:
        return self.tty


@pytest.mark.parametrize("setting, tty, expected", [
    ("auto", True, "text"), ("auto", False, "json"),
    ("json", True, "json"), ("json", False, "json"), ("text", True, "text"), ("text", False, "text")])
def test_the_format_follows_the_terminal_unless_set(setting, tty, expected):
    assert logs.resolved_format(setting, _Stream(tty)) == expected


def test_a_real_terminal_is_recognised():
    leader, follower = pty.openpty()
    try:
        with os.fdopen(follower, "w", closefd=False) as terminal:
            assert logs.resolved_format("auto", terminal) == "text"
    finally:
        os.close(leader)
        os.close(follower)
    assert logs.resolved_format("auto", io.StringIO()) == "json"


def test_the_default_setting_is_auto(monkeypatch):
    monkeypatch.delenv("PASSIVE_LOCATOR_LOG_FORMAT", raising=False)
    assert Settings().log_format == "auto"
    monkeypatch.setenv("PASSIVE_LOCATOR_LOG_FORMAT", "json")
    assert Settings().log_format == "json"


@pytest.mark.parametrize("tty", [True, False])
def test_configure_writes_what_the_stream_calls_for(monkeypatch, tty):
    stream = _Stream(tty)
    monkeypatch.setattr("sys.stderr", stream)
    logger = logging.getLogger("passive_locator")
    saved = logger.handlers[:], logger.level, logger.propagate
    try:
        logs.configure("info", "auto")
        logger.info("hello", extra={"request_id": "r-1"})
    finally:
        logger.handlers, logger.level, logger.propagate = saved
    line = stream.getvalue().strip()
    if tty:
        assert " INFO passive_locator [r-1] hello" in line
        with pytest.raises(orjson.JSONDecodeError):
            orjson.loads(line)
    else:
        assert orjson.loads(line)["message"] == "hello" and orjson.loads(line)["request_id"] == "r-1"
    formatter = logs.uvicorn_log_config("info", "auto")["formatters"]["default"]
    assert ("()" in formatter) is not tty
