"""The default session model through the HTTP API against the posterior CRLB (core.tracking.bound).

Paper 001's sensor and emitter, truths drawn from the session's own white-acceleration model; the create
request names no model, so this is the API's default (joint_ukf with its range-mixture start). The last
50 reports are posted 5 at a time and the state read after each post: the position RMSE over runs and
those 10 reports over the RMS of the PCRB there, and the position NEES (3 dof) against its 99 % interval.
tests/core/tracking/test_at_the_bound.py has the same in the core and the measured figures.
"""

from __future__ import annotations

import numpy as np
import pytest
from fastapi.testclient import TestClient
from scipy.stats import chi2

from core.simulation.emitter import paper_001_scenario, simulate_emitter
from core.tracking.bound import session_pcrb
from service.app import create_app
from service.settings import Settings
from core.simulation.tracking import paper_config

from .helpers import api_epochs, create_body

RUNS = 30
LAST = 50
EVERY = 5


def run_through_the_api(q: float, seed: int):
    scenario = paper_001_scenario(accel_sigma_mps2=q)
    tracks = [simulate_emitter(scenario, np.random.default_rng(seed + r)) for r in range(RUNS)]
    squared, nees = np.empty((RUNS, LAST // EVERY)), np.empty((RUNS, LAST // EVERY))
    with TestClient(create_app(Settings(store="sqlite:///:memory:"))) as client:
        for r, track in enumerate(tracks):
            body = create_body(period_known=True, accel_sigma_mps2=q)
            del body["model"]
            created = client.post("/v1/sessions", json=body)
            assert created.status_code == 201, created.text
            assert created.json()["model"] == "joint_ukf"
            url = f"/v1/sessions/{created.json()['id']}/measurements"
            epochs = api_epochs(track)
            head = len(epochs) - LAST
            for start in range(0, head, 50):
                assert client.post(url, json={"measurements": epochs[start:min(start + 50, head)]}).status_code == 200
            for i in range(LAST // EVERY):
                last = head + (i + 1) * EVERY
                state = client.post(url, json={"measurements": epochs[last - EVERY:last]}).json()
                p = state["position_local"]
                error = np.array([p["east_m"], p["north_m"], p["up_m"]]) - track.states_enu[last - 1, :3]
                squared[r, i] = error @ error
                nees[r, i] = error @ np.linalg.solve(np.array(state["covariance_enu"])[:3, :3], error)
    bound = session_pcrb(np.array([t.states_enu for t in tracks]), tracks[0].emission_times_s,
                         paper_config("joint_ukf", True, accel_sigma_mps2=q))
    read = np.arange(len(tracks[0].epochs) - LAST + EVERY - 1, len(tracks[0].epochs), EVERY)
    ratio = float(np.sqrt(squared.mean() / np.mean(bound.position_rmse_m[read] ** 2)))
    return ratio, nees.mean(axis=0)


@pytest.mark.slow
@pytest.mark.parametrize("q, ceiling", [(0.05, 1.1), (0.5, 1.1)])
def test_the_default_session_model_is_near_the_bound_and_consistent(q, ceiling):
    ratio, mean_nees = run_through_the_api(q, seed=2000)
    assert 0.8 < ratio <= ceiling, ratio
    low, high = chi2.ppf([0.005, 0.995], 3 * RUNS) / RUNS
    assert low <= mean_nees.mean() <= high, mean_nees.mean()
    assert ((mean_nees >= low) & (mean_nees <= high)).mean() >= 0.8
