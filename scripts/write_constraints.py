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


#: Python versions the image may have: the official python:3.11-slim (newest 3.11.x) and Debian bookworm's
#: 3.11.2 (the stand-in base), whose markers differ (redis needs async-timeout below 3.11.3).
IMAGE_PYTHONS = ("3.11.2", "3.11.99")


def closure(name: str = "passive-locator") -> tuple[dict[str, str], set[str]]:
    """``{canonical name: version}`` of every distribution ``name`` needs at run time, and those needed
    on one of :data:`IMAGE_PYTHONS` that this venv does not have (so it cannot pin them)."""
    environments = [{**default_environment(), "sys_platform": "linux", "platform_system": "Linux",
                     "python_full_version": version} for version in IMAGE_PYTHONS]
    found: dict[str, str] = {}
    missing: set[str] = set()
    pending = [(name, frozenset())]
    seen = set()
    while pending:
        dist_name, extras = pending.pop()
        if (dist_name, extras) in seen:
            continue
        seen.add((dist_name, extras))
        try:
            dist = metadata.distribution(dist_name)
        except metadata.PackageNotFoundError:
            missing.add(canonicalize_name(dist_name))
            continue
        if canonicalize_name(dist_name) != canonicalize_name(name):
            found[canonicalize_name(dist.metadata["Name"])] = dist.version
        for text in dist.requires or []:
            requirement = Requirement(text)
            marker = requirement.marker
            if marker is not None and not any(marker.evaluate({**environment, "extra": e})
                                              for environment in environments for e in extras or {""}):
                continue
            pending.append((requirement.name, frozenset(requirement.extras)))
    return found, missing


def render() -> str:
    pins, missing = closure()
    lines = ["# Exact runtime dependencies of the image (scripts/write_constraints.py; regenerate with "
             "`make constraints`).", f"# Resolved on Python {sys.version_info.major}.{sys.version_info.minor}, "
             "Linux."]
    lines += [f"{name}=={version}" for name, version in sorted(pins.items())]
    lines += [f"# {name}: needed on another 3.11.x, not installed here, so not pinned" for name in sorted(missing)]
    return "\n".join(lines) + "\n"


if __name__ == "__main__":
    TARGET.write_text(render())
    print(f"wrote {TARGET.relative_to(ROOT)}")
