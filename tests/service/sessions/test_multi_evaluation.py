"""The multi-emitter scene evaluated through ``POST /v1/evaluations`` and ``passive-locator evaluate``: GOSPA of
the association tracker beside the intersection + DBSCAN baseline, core's numbers for the same seeds; priced,
and stopped between trials at the request deadline."""

from __future__ import annotations

import json
from dataclasses import replace

import numpy as np
import pytest
from fastapi.testclient import TestClient

from core.simulation.multi_emitter import evaluate_multi, multi_emitter_scene
from service.app import create_app
from service.schemas.sessions import MultiEmitterEvaluationResponse
from service.settings import Settings
from tests.service.test_cli_tools import run_cli

pytest.importorskip("sklearn")


@pytest.fixture
def client(tmp_path):
    with TestClient(create_app(Settings(store=f"sqlite:///{tmp_path}/s.db"))) as c:
        yield c


def test_a_multi_emitter_scene_evaluates_to_cores_numbers(client):
    response = client.post("/v1/evaluations", json={"multi_emitter": {"variant": 2, "trials": 2, "seed": 1,
                                                                      "duration_s": 60.0}})
    assert response.status_code == 200, response.text
    body = response.json()
    MultiEmitterEvaluationResponse.model_validate(body)
    core = evaluate_multi(replace(multi_emitter_scene(2), duration_s=60.0), 2, 1)
    assert (body["variant"], body["trials"], body["seed"], body["duration_s"]) == (2, 2, 1, 60.0)
    assert body["tracker"]["gospa_m"] == pytest.approx(core.gospa_m, rel=1e-12)
    assert body["baseline"]["gospa_m"] == pytest.approx(core.baseline_gospa_m, rel=1e-12)
    assert [body["tracker"][k] for k in ("localisation_m2", "missed_m2", "false_m2")] == pytest.approx(
        [core.localisation_m2, core.missed_m2, core.false_m2], rel=1e-12)
    assert [body["baseline"][k] for k in ("localisation_m2", "missed_m2", "false_m2")] == pytest.approx(
        list(core.baseline_parts_m2), rel=1e-12)
    # GOSPA^2 is the sum of its parts, per epoch; the means of the distance and of its square differ, so only
    # the bound holds for the means: mean GOSPA <= sqrt(mean GOSPA^2).
    assert body["tracker"]["gospa_m"] <= np.sqrt(sum(body["tracker"][k] for k in ("localisation_m2", "missed_m2",
                                                                               "false_m2"))) + 1e-9
    assert body["emitters"] == ["e1", "e2", "e3", "e4"]
    delays = np.array([[np.inf if v is None else v for v in row] for row in body["confirm_delay_s"]])
    assert np.array_equal(delays, core.confirm_delay_s)
    assert body["false_tracks"] == core.false_tracks.tolist()
    assert body["identity_switches"] == core.identity_switches.tolist()
    assert body["gospa_over_baseline"] == pytest.approx(core.gospa_m / core.baseline_gospa_m, rel=1e-12)


@pytest.mark.parametrize("body, code, loc", [
    ({"multi_emitter": {"trials": 0}}, "invalid_input", ["multi_emitter", "trials"]),
    ({"multi_emitter": {"duration_s": 5.0}}, "invalid_input", ["multi_emitter", "duration_s"]),
    ({"multi_emitter": {"variant": -1}}, "invalid_input", ["multi_emitter", "variant"]),
    ({"multi_emitter": {"scene": "sea"}}, "invalid_input", ["multi_emitter", "scene"]),
    ({"multi_emitter": {"trials": 200}}, "over_limit", ["multi_emitter", "trials"]),
])
def test_bad_multi_emitter_evaluations_are_422_with_the_field_path(client, body, code, loc):
    response = client.post("/v1/evaluations", json=body)
    assert response.status_code == 422, response.text
    assert response.json()["code"] == code and loc in [e["loc"] for e in response.json()["errors"]]


@pytest.mark.parametrize("body", [
    {"multi_emitter": {"variant": 0, "trials": 3}},
    {"network": {"scene": "df_network", "trials": 50}},
])
def test_scene_evaluations_past_the_request_deadline_are_503(tmp_path, body):
    settings = Settings(store=f"sqlite:///{tmp_path}/s.db", request_deadline_s=0.2)
    with TestClient(create_app(settings)) as client:
        response = client.post("/v1/evaluations", json=body)
    assert response.status_code == 503, response.text
    assert response.json()["code"] == "deadline_exceeded"


def test_scene_evaluations_stop_between_trials():
    from core.parallel import Stopped
    from core.simulation.network import SCENES, evaluate_network

    asked = []

    def stop_at_second():
        asked.append(True)
        return len(asked) > 1

    with pytest.raises(Stopped):
        evaluate_multi(replace(multi_emitter_scene(0), duration_s=20.0), 5, 0, should_stop=stop_at_second)
    assert len(asked) == 2
    asked.clear()
    with pytest.raises(Stopped):
        evaluate_network(SCENES["toa_network"](), 5, 0, should_stop=stop_at_second)
    assert len(asked) == 2


def test_evaluate_a_multi_emitter_scene_from_the_command_line(tmp_path):
    path = tmp_path / "multi.json"
    path.write_text(json.dumps({"multi_emitter": {"variant": 0, "trials": 1, "seed": 3, "duration_s": 40.0}}))
    done = run_cli("evaluate", str(path), "--out", str(tmp_path / "out"))
    assert done.returncode == 0, done.stderr[-3000:]
    body = json.loads((tmp_path / "out" / "evaluation.json").read_text())
    core = evaluate_multi(replace(multi_emitter_scene(0), duration_s=40.0), 1, 3)
    assert body["tracker"]["gospa_m"] == pytest.approx(core.gospa_m, rel=1e-12)
    text = (tmp_path / "out" / "evaluation.md").read_text()
    assert "mean GOSPA (m)" in text and "identity switches" in text and "intersections + DBSCAN" in text
    path.write_text(json.dumps({"multi_emitter": {"trials": 0}}))
    assert run_cli("evaluate", str(path), "--out", str(tmp_path / "bad")).returncode == 2
