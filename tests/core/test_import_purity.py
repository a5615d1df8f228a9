"""The core knows nothing about HTTP: importing it loads no web framework."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[2]
WEB_FRAMEWORKS = ("fastapi", "starlette", "pydantic", "pydantic_core", "uvicorn")

PROBE = """
import importlib, json, sys
for name in sys.argv[1:]:
    importlib.import_module(name)
print(json.dumps(sorted(m for m in sys.modules if m.split(".")[0] in {frameworks!r})))
"""


def modules_loaded_by(*imports: str) -> list[str]:
    """Web-framework modules present in ``sys.modules`` after importing ``imports`` in a fresh interpreter."""
    result = subprocess.run(
        [sys.executable, "-c", PROBE.format(frameworks=set(WEB_FRAMEWORKS)), *imports],
        cwd=REPO, env={"PYTHONPATH": str(REPO), "PATH": ""}, capture_output=True, text=True, timeout=60,
    )
    assert result.returncode == 0, result.stderr
    return json.loads(result.stdout.strip().splitlines()[-1])


@pytest.mark.parametrize("imports", [
    ("core",),
    ("core.estimators",),
    ("core.geodesy", "core.measurements", "core.problem.build", "core.crlb", "core.error_summary",
     "core.simulation.measurements"),
])
def test_core_imports_no_web_framework(imports):
    assert modules_loaded_by(*imports) == []


def test_the_probe_sees_a_web_framework_when_one_is_imported():
    """The check has teeth: the same probe reports the service's imports."""
    pytest.importorskip("pydantic")
    assert "pydantic" in modules_loaded_by("core", "pydantic")
