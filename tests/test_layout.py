"""The layout shows what each module is for: routes reach core only through the service's modules, and every
package says what lives in it."""

from __future__ import annotations

import ast
from pathlib import Path

from tests.test_import_cycles import import_graph

REPO = Path(__file__).resolve().parents[1]


def test_routes_reach_core_only_through_the_service():
    graph = import_graph()
    direct = {route: sorted(t for t in targets if t == "core" or t.startswith("core."))
              for route, targets in graph.items() if route.startswith("service.routes")}
    assert {route: targets for route, targets in direct.items() if targets} == {}


def test_the_checker_sees_a_route_import():
    assert "service.fixes.pipeline" in import_graph()["service.routes.batch"]


def test_every_package_has_its_map():
    bare = [str(init.relative_to(REPO)) for package in ("core", "service")
            for init in sorted((REPO / package).rglob("__init__.py"))
            if not ast.get_docstring(ast.parse(init.read_text()))]
    assert bare == []
