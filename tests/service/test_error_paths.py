"""Core errors name core fields; the service reports the API's field paths."""

from __future__ import annotations

from service.problems import api_loc


def test_api_paths_of_core_error_locations():
    assert api_loc(("measurements", 3, "sigma_azimuth_rad")) == ["measurements", 3, "sigma_azimuth_deg"]
    assert api_loc(("stations", 0, "position", "lat_rad")) == ["stations", 0, "position", "lat_deg"]
    assert api_loc(("initial_guess", "lon_rad")) == ["options", "initial_guess", "lon_deg"]
    assert api_loc(("altitude_m",)) == ["constraints", "altitude_m"]
    assert api_loc(("measurements", 0, "range_m")) == ["measurements", 0, "range_m"]
