"""POST /v1/evaluations, and the committed OpenAPI document against the app's."""

from __future__ import annotations

import json
import pathlib

import numpy as np
import pytest
from scipy.stats import chi2

from service import schemas
from tests.service.conftest import STATIONS_300KM, TARGET
from tests.service.test_fixes_api import assert_problem

ROOT = pathlib.Path(__file__).resolve().parents[2]


def _scenario(**sensor) -> dict:
    sensors = [{"station_id": sid, "sigma_azimuth_deg": 1.0, "sigma_elevation_deg": 1.0, **sensor}
               for sid in STATIONS_300KM]
    return {"stations": [{"id": k, "position": v} for k, v in STATIONS_300KM.items()], "sensors": sensors,
            "target": TARGET}


def test_evaluation_ml_is_efficient_and_honest(client):
    trials = 600
    body = {"scenario": _scenario(), "methods": ["ml", "eove"], "trials": trials, "seed": 11}
    response = client.post("/v1/evaluations", json=body)
    assert response.status_code == 200, response.text
    result = schemas.EvaluationResponse.model_validate(response.json())
    ml = result.methods["ml"]
    assert ml.failures == 0
    assert 0.9 < ml.rmse_m / ml.crlb_rmse_m < 1.1
    low, high = chi2.ppf([0.005, 0.995], 3 * trials) / trials
    assert low < ml.nees_mean < high
    assert result.methods["eove"].rmse_m >= ml.rmse_m * 0.98  # the ML is the reference


def test_an_evaluation_says_why_trials_failed(client):
    body = {"scenario": _scenario(), "methods": ["tls", "ml"], "trials": 20, "seed": 3}
    result = client.post("/v1/evaluations", json=body).json()["methods"]
    (reason,) = result["tls"]["failure_reasons"]
    assert result["tls"]["failures"] == reason["trials"] == 20 and reason["code"] == "too_few_measurements"
    assert "constraints.altitude_m" in reason["example"]
    assert result["ml"]["failures"] == 0 and result["ml"]["failure_reasons"] == []


def test_evaluation_is_reproducible_by_seed(client):
    body = {"scenario": _scenario(), "methods": ["ml"], "trials": 50, "seed": 3}
    first = client.post("/v1/evaluations", json=body).json()
    assert client.post("/v1/evaluations", json=body).json() == first
    body["seed"] = 4
    assert client.post("/v1/evaluations", json=body).json() != first


def test_uniform_noise_has_the_stated_sigma(client):
    body = {"scenario": _scenario(), "methods": ["ml"], "trials": 600, "seed": 5, "noise": "uniform"}
    ml = client.post("/v1/evaluations", json=body).json()["methods"]["ml"]
    assert 0.85 < ml["rmse_m"] / ml["crlb_rmse_m"] < 1.15


def test_evaluation_of_unobservable_scenario(client):
    scenario = _scenario(elevation=False)
    scenario["sensors"] = scenario["sensors"][:2]
    for s in scenario["sensors"]:
        del s["sigma_elevation_deg"]
    assert_problem(client.post("/v1/evaluations", json={"scenario": scenario, "methods": ["ml"], "trials": 5}),
                   422, code="unobservable")


def test_committed_openapi_matches_the_app():
    from scripts.write_openapi import render

    committed = (ROOT / "openapi" / "openapi.json").read_text()
    assert committed == render(), "openapi/openapi.json is stale: run `make openapi`"
    spec = json.loads(committed)
    operation_ids = [op["operationId"] for path in spec["paths"].values() for op in path.values()]
    assert len(operation_ids) == len(set(operation_ids))
    assert all("-" in op for op in operation_ids)  # {tag}-{name}, for generated clients


def test_evaluation_with_outlier_noise_shows_the_exclusion(client):
    """Contaminated-gaussian noise: with exclusion on, a good share of the trials drop a measurement (a
    trial has a gross error with probability 1 - 0.95^M) and the RMSE falls below that of reporting only."""
    body = {"scenario": _scenario(), "methods": ["ml"], "trials": 300, "seed": 4, "noise": "outlier"}
    report = client.post("/v1/evaluations", json=body)
    exclude = client.post("/v1/evaluations", json={**body, "options": {"outliers": "exclude"}})
    assert report.status_code == exclude.status_code == 200, exclude.text
    report, exclude = report.json()["methods"]["ml"], exclude.json()["methods"]["ml"]
    assert report["excluded_trials"] == 0 and exclude["excluded_trials"] > 0.15 * 300
    assert exclude["rmse_m"] < 0.8 * report["rmse_m"]


def test_exclusion_prices_its_refits(make_client):
    client = make_client(max_evaluation_cost=10_000)
    body = {"scenario": _scenario(), "methods": ["ml"], "trials": 1000}
    rows = 2 * len(STATIONS_300KM)
    assert rows * 1000 <= 10_000 < rows * 1000 * 9  # the same evaluation fits only without exclusion
    assert client.post("/v1/evaluations", json={**body, "trials": 10_000 // rows}).status_code == 200
    refused = client.post("/v1/evaluations", json={**body, "trials": 10_000 // rows, "options": {"outliers": "exclude"}})
    assert refused.status_code == 422 and refused.json()["code"] == "over_limit"


@pytest.mark.slow
def test_evaluation_on_the_configured_dask_scheduler_answers_the_in_process_body(make_client):
    distributed = pytest.importorskip("distributed")
    body = {"scenario": _scenario(), "methods": ["ml", "eove"], "trials": 300, "seed": 12}
    here = make_client().post("/v1/evaluations", json=body)
    with distributed.LocalCluster(n_workers=2, threads_per_worker=1, processes=True,
                                  dashboard_address=None) as cluster:
        there = make_client(dask_scheduler=cluster.scheduler_address).post("/v1/evaluations", json=body)
    assert here.status_code == there.status_code == 200, there.text
    assert here.json() == there.json()
