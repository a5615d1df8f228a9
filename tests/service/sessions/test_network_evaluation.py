"""A network tracking scene evaluated through ``POST /v1/evaluations`` and ``passive-locator evaluate``: per-epoch
RMSE and NEES against the posterior CRLB, core's numbers for the same seeds."""

from __future__ import annotations

import json

import numpy as np
import pytest
from fastapi.testclient import TestClient

from core.simulation.network import SCENES, evaluate_network
from service.app import create_app
from service.schemas.sessions import NetworkEvaluationResponse
from service.settings import Settings
from tests.service.test_cli_tools import run_cli


@pytest.fixture
def client(tmp_path):
    with TestClient(create_app(Settings(store=f"sqlite:///{tmp_path}/s.db"))) as c:
        yield c


def test_a_network_scene_evaluates_to_cores_numbers(client):
    response = client.post("/v1/evaluations", json={"network": {"scene": "toa_network", "trials": 3, "seed": 9}})
    assert response.status_code == 200, response.text
    body = response.json()
    NetworkEvaluationResponse.model_validate(body)
    core = evaluate_network(SCENES["toa_network"](), 3, 9)
    epochs = body["epochs"]
    assert len(epochs["time_s"]) == core.times_s.size == len(epochs["pcrb_position_m"]) == len(epochs["nees_position"])
    assert np.allclose(epochs["rmse_position_m"], core.rmse_position_m, rtol=1e-12)
    assert np.allclose([np.inf if v is None else v for v in epochs["pcrb_position_m"]], core.pcrb_position_m,
                       rtol=1e-12)
    assert body["rmse_over_pcrb"] == pytest.approx(core.rmse_over_pcrb, rel=1e-12)
    assert body["nees_interval_99"] == pytest.approx(list(core.nees_interval_99))
    assert (body["scene"], body["trials"], body["seed"]) == ("toa_network", 3, 9)


def test_the_tracker_settings_of_a_request_are_used(client):
    plain = client.post("/v1/evaluations", json={"network": {"scene": "toa_network", "trials": 2}}).json()
    noisy = client.post("/v1/evaluations", json={"network": {"scene": "toa_network", "trials": 2,
                                                             "process_noise": {"accel_sigma_mps2": 20.0}}}).json()
    assert noisy["epochs"]["rmse_position_m"] != plain["epochs"]["rmse_position_m"]
    assert noisy["epochs"]["pcrb_position_m"] == plain["epochs"]["pcrb_position_m"]  # the bound is the truth's


@pytest.mark.parametrize("body, code, loc", [
    ({"network": {"scene": "sea"}}, "invalid_input", ["network", "scene"]),
    ({"network": {"scene": "df_network", "trials": 0}}, "invalid_input", ["network", "trials"]),
    ({"network": {"scene": "df_network", "trials": 500}}, "over_limit", ["network", "trials"]),
    ({"network": {"scene": "df_network", "reorder_window_s": 100.0}}, "invalid_input", ["network", "end_after_s"]),
])
def test_bad_network_evaluations_are_422_with_the_field_path(client, body, code, loc):
    response = client.post("/v1/evaluations", json=body)
    assert response.status_code == 422, response.text
    assert response.json()["code"] == code and loc in [e["loc"] for e in response.json()["errors"]]


def test_evaluate_a_network_scene_from_the_command_line(tmp_path):
    path = tmp_path / "net.json"
    path.write_text(json.dumps({"network": {"scene": "airborne_df", "trials": 2, "seed": 4}}))
    done = run_cli("evaluate", str(path), "--out", str(tmp_path / "out"))
    assert done.returncode == 0, done.stderr[-3000:]
    body = json.loads((tmp_path / "out" / "evaluation.json").read_text())
    assert body["scene"] == "airborne_df" and len(body["epochs"]["time_s"]) == 240
    text = (tmp_path / "out" / "evaluation.md").read_text()
    assert "sqrt tr PCRB" in text and "RMSE / PCRB" in text
    assert (tmp_path / "out" / "rmse.png").read_bytes()[:4] == b"\x89PNG"
    path.write_text(json.dumps({"network": {"scene": "nowhere"}}))
    assert run_cli("evaluate", str(path), "--out", str(tmp_path / "bad")).returncode == 2
