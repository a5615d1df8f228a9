"""Over HTTP: a hybrid whose crossing is unique is answered; one whose line of sight crosses twice is 422.

The scene of tests/core/estimators/test_ambiguity.py (azimuth at a, TOAs at b and c, altitude 0 known) sent
as a WGS84 request with exact measurements.
"""

from __future__ import annotations

import math

import numpy as np
import pytest

from core.simulation.measurements import true_values
from tests.core.estimators.test_ambiguity import (
    GROUND,
    SIGMA_RAD,
    SIGMA_TOA_S,
    ground_scene,
)
from tests.service.test_fixes_api import assert_problem


def _request(east_m: float, north_m: float) -> tuple[dict, np.ndarray]:
    """The exact request for a target at ``(east_m, north_m)`` of the scene's frame, and the target's ECEF."""
    problem, target = ground_scene(east_m, north_m)
    azimuth_rad, *toas_s = true_values(problem, target)
    stations = [{"id": s, "position": {"lat_deg": math.degrees(p.lat_rad), "lon_deg": math.degrees(p.lon_rad),
                                       "alt_m": p.alt_m}} for s, p in GROUND]
    measurements = [{"type": "bearing", "station_id": "a", "azimuth_deg": math.degrees(azimuth_rad),
                     "sigma_azimuth_deg": math.degrees(SIGMA_RAD)}]
    measurements += [{"type": "toa", "station_id": s, "toa_s": float(t), "sigma_s": SIGMA_TOA_S}
                     for s, t in zip("bc", toas_s)]
    body = {"frame": "wgs84", "constraints": {"altitude_m": 0.0}, "stations": stations,
            "measurements": measurements}
    return body, problem.frame.to_ecef(target)


def test_the_unique_crossing_is_answered_at_the_target(client):
    body, target_ecef_m = _request(8e3, 8e3)
    response = client.post("/v1/fixes", json=body)
    assert response.status_code == 200, response.text
    fix = response.json()
    assert fix["converged"]
    assert np.linalg.norm(np.array(fix["position_ecef_m"]) - target_ecef_m) < 1e-2  # 1 cm
    assert "ambiguous_solution" not in {w["code"] for w in fix["warnings"]}


@pytest.mark.parametrize("east_m, north_m", [(3e3, 25e3), (20e3, -3e3)])
def test_two_exact_crossings_are_422_ambiguous_geometry(client, east_m, north_m):
    body, _ = _request(east_m, north_m)
    problem = assert_problem(client.post("/v1/fixes", json=body), 422, code="ambiguous_geometry")
    assert problem["detail"].count("lat ") == 2
