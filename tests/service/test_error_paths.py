"""Core errors name core fields; the service reports the API's field paths."""

from __future__ import annotations

from service.web.problems import api_loc


def test_api_paths_of_core_error_locations():
    assert api_loc(("measurements", 3, "sigma_azimuth_rad")) == ["measurements", 3, "sigma_azimuth_deg"]
    assert api_loc(("stations", 0, "position", "lat_rad")) == ["stations", 0, "position", "lat_deg"]
    assert api_loc(("initial_guess", "lon_rad")) == ["options", "initial_guess", "lon_deg"]
    assert api_loc(("altitude_m",)) == ["constraints", "altitude_m"]
    assert api_loc(("measurements", 0, "range_m")) == ["measurements", 0, "range_m"]


def test_every_core_error_location_names_core_fields():
    """A core error's loc is in core names; the API's path prefixes (``constraints``, ``options``) are the
    service's to add, so a loc that already carries one comes out doubled."""
    import ast
    import pathlib

    from service.web.problems import API_PATH

    prefixes = {path[0] for path in API_PATH.values() if len(path) > 1}
    found = []
    for source in pathlib.Path(__file__).resolve().parents[2].joinpath("core").rglob("*.py"):
        for node in ast.walk(ast.parse(source.read_text())):
            if isinstance(node, ast.Tuple) and node.elts and all(isinstance(e, ast.Constant) for e in node.elts):
                values = [e.value for e in node.elts]
                if values[0] in prefixes and len(values) > 1 and all(isinstance(v, str) for v in values):
                    found.append(f"{source.name}:{node.lineno} {tuple(values)}")
    assert not found, found


def test_an_azimuth_only_method_without_altitude_points_at_constraints_altitude_m():
    import numpy as np

    from bench.scenarios import four_station_requests
    from service.fixes.pipeline import fix_results

    (result,) = fix_results(four_station_requests(1, np.random.default_rng(3), method="tls", with_altitude=False))
    assert not result["ok"]
    assert result["error"]["errors"][0]["loc"] == ["constraints", "altitude_m"]
