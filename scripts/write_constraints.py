"""Write constraints.txt: exact versions of the service's runtime dependencies (no dev extras), as installed.

The image installs ``pip install -c constraints.txt`` so that a rebuild gets the versions that were tested,
not whatever is newest that day. Run in the project's venv after `make install` (``make constraints``);
it walks ``passive-locator``'s own requirements (with the extras they name, e.g. ``uvicorn[standard]``) and
their requirements, evaluating environment markers for Linux and this Python.
"""

from __future__ import annotations

import importlib.metadata as metadata
import pathlib
import sys

from packaging.markers import default_environment
from packaging.requirements import Requirement
from packaging.utils import canonicalize_name

ROOT = pathlib.Path(__file__).resolve().parents[1]
TARGET = ROOT / "constraints.txt"


def closure(name: str = "passive-locator") -> dict[str, str]:
    """``{canonical name: version}`` of every distribution ``name`` needs at run time."""
    environment = {**default_environment(), "sys_platform": "linux", "platform_system": "Linux"}
    found: dict[str, str] = {}
    pending = [(name, frozenset())]
    seen = set()
    while pending:
        dist_name, extras = pending.pop()
        if (dist_name, extras) in seen:
            continue
        seen.add((dist_name, extras))
        dist = metadata.distribution(dist_name)
        if canonicalize_name(dist_name) != canonicalize_name(name):
            found[canonicalize_name(dist.metadata["Name"])] = dist.version
        for text in dist.requires or []:
            requirement = Requirement(text)
            marker = requirement.marker
            if marker is not None and not any(marker.evaluate({**environment, "extra": e}) for e in extras or {""}):
                continue
            pending.append((requirement.name, frozenset(requirement.extras)))
    return found


def render() -> str:
    pins = closure()
    lines = ["# Exact runtime dependencies of the image (scripts/write_constraints.py; regenerate with "
             "`make constraints`).", f"# Resolved on Python {sys.version_info.major}.{sys.version_info.minor}, "
             "Linux."]
    lines += [f"{name}=={version}" for name, version in sorted(pins.items())]
    return "\n".join(lines) + "\n"


if __name__ == "__main__":
    TARGET.write_text(render())
    print(f"wrote {TARGET.relative_to(ROOT)}")
