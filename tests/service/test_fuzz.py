"""Schemathesis against a live app from the committed spec: every operation, positive and negative data,
a bounded number of examples. No 5xx, no response that violates the spec (bodies, every status and its
content type declared), negative data rejected, 405 with a complete Allow for undeclared methods; the stateful
phase follows the sessions' links. Each server-sent event of ``/v1/sessions/{id}/events`` is checked against
the event schema; schemathesis reads the first event (the catch-up state) and hangs up (schemathesis.toml)."""

from __future__ import annotations

import pathlib
import shutil
import subprocess
import sys

import pytest

from tests.service.sessions.helpers import REPO
from tests.service.test_faults import App

pytestmark = pytest.mark.slow  # about a minute

EXAMPLES_PER_OPERATION = 25


def test_schemathesis_finds_no_server_error_and_no_schema_violation(tmp_path):
    executable = shutil.which("schemathesis", path=str(pathlib.Path(sys.executable).parent)) or \
        shutil.which("schemathesis")
    if executable is None:
        pytest.fail("schemathesis is not installed: `make install` (dev extras)")
    # Small cost limits keep generated evaluations and batches cheap; they are part of what is tested.
    app = App(tmp_path, f"sqlite:///{tmp_path}/sessions.db", max_evaluation_cost=20_000, max_batch_cost=2_000,
              request_deadline_s=5)
    try:
        run = subprocess.run(
            [executable, "--no-color", "--config-file", str(REPO / "tests" / "service" / "schemathesis.toml"),
             "run", str(REPO / "openapi" / "openapi.json"), "--url", app.url, "--mode", "all",
             "--max-examples", str(EXAMPLES_PER_OPERATION), "--seed", "20261201", "--workers", "2",
             "--request-timeout", "20", "--suppress-health-check", "all", "--generation-database", "none"],
            cwd=tmp_path, capture_output=True, text=True, timeout=600)
    finally:
        app.stop()
    assert run.returncode == 0, run.stdout[-8000:] + run.stderr[-2000:]
    assert "Server error" not in run.stdout
    log = app.log.read_text()
    assert "Traceback" not in log, log[-4000:]
