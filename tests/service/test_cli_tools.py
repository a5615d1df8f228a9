"""``passive-locator evaluate`` and ``reproduce`` through the installed entry point's module.

``reproduce --quick`` is the CI run of the five papers' claims at reduced size: the command fails (exit
status 1) when an asserted claim does not hold, so this test fails with it.
"""

from __future__ import annotations

import json
import pathlib
import subprocess
import sys

import pytest

ROOT = pathlib.Path(__file__).resolve().parents[2]


def run_cli(*args: str, timeout: float = 300.0) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, "-m", "service.cli", *args], cwd=ROOT, capture_output=True, text=True,
                          timeout=timeout, check=False)


@pytest.mark.slow
def test_reproduce_quick_asserts_every_claim_and_writes_the_report(tmp_path):
    done = run_cli("reproduce", "--quick", "--out", str(tmp_path))
    assert done.returncode == 0, done.stderr[-3000:]
    text = (tmp_path / "papers.md").read_text()
    for paper in ("000", "001", "002", "003", "004"):
        assert f"## Paper {paper}:" in text
    report = json.loads((tmp_path / "papers.json").read_text())
    assert [r["paper"] for r in report] == ["000", "001", "002", "003", "004"]
    assert all(r["passed"] for r in report)
    assert all(any(c["asserted"] for c in r["checks"]) for r in report)
    for png in ("p000_rmse.png", "p001_pcrb.png", "p002_efficiency.png", "p003_rmse.png", "p004_efficiency.png"):
        assert (tmp_path / png).read_bytes()[:8] == b"\x89PNG\r\n\x1a\n", png


def test_evaluate_writes_markdown_json_and_a_png(tmp_path):
    scenario = json.loads((ROOT / "examples" / "three_stations.json").read_text())
    scenario.update(trials=64, methods=["ml", "eove"], noise="outlier", options={"outliers": "exclude"})
    path = tmp_path / "small.json"
    path.write_text(json.dumps(scenario))
    done = run_cli("evaluate", str(path), "--out", str(tmp_path / "out"))
    assert done.returncode == 0, done.stderr[-3000:]
    body = json.loads((tmp_path / "out" / "evaluation.json").read_text())
    assert set(body["methods"]) == {"ml", "eove"} and body["trials"] == 64 and body["noise"] == "outlier"
    assert body["options"]["outliers"] == "exclude"
    assert "| ml |" in (tmp_path / "out" / "evaluation.md").read_text()
    assert (tmp_path / "out" / "rmse.png").read_bytes()[:4] == b"\x89PNG"
    assert "] 1/1 " in done.stderr  # the progress bar (per chunk of trials) reached the end


def test_evaluate_a_session_filter_against_the_pcrb(tmp_path):
    path = tmp_path / "track.json"
    path.write_text(json.dumps({"tracking": {"model": "velocity_kinematic", "period_known": True, "runs": 2,
                                             "seed": 5, "scenario": {"epochs": 60, "accel_sigma_mps2": 0.05},
                                             "config": {"accel_sigma_mps2": 0.05}}}))
    done = run_cli("evaluate", str(path), "--out", str(tmp_path / "out"))
    assert done.returncode == 0, done.stderr[-3000:]
    body = json.loads((tmp_path / "out" / "evaluation.json").read_text())
    assert len(body["epochs"]["time_s"]) == 60 and len(body["epochs"]["pcrb_rmse_m"]) == 60
    assert all(b > 0 for b in body["epochs"]["pcrb_rmse_m"])
    assert "sqrt tr PCRB" in (tmp_path / "out" / "evaluation.md").read_text()


def test_evaluate_refuses_an_invalid_file_with_status_2(tmp_path):
    path = tmp_path / "bad.json"
    path.write_text(json.dumps({"scenario": {"stations": []}, "methods": ["ml"]}))
    done = run_cli("evaluate", str(path), "--out", str(tmp_path / "out"))
    assert done.returncode == 2
    assert "not a valid evaluation" in done.stderr
    assert not (tmp_path / "out").exists()


@pytest.mark.slow
def test_evaluate_on_a_two_worker_cluster_writes_the_in_process_numbers(tmp_path):
    distributed = pytest.importorskip("distributed")
    scenario = json.loads((ROOT / "examples" / "three_stations.json").read_text())
    scenario.update(trials=300, methods=["ml", "eove"])
    path = tmp_path / "s.json"
    path.write_text(json.dumps(scenario))
    here = run_cli("evaluate", str(path), "--out", str(tmp_path / "here"))
    assert here.returncode == 0, here.stderr[-3000:]
    with distributed.LocalCluster(n_workers=2, threads_per_worker=1, processes=True,
                                  dashboard_address=None) as cluster:
        there = run_cli("evaluate", str(path), "--out", str(tmp_path / "there"), "--scheduler",
                        cluster.scheduler_address)
    assert there.returncode == 0, there.stderr[-3000:]
    assert (tmp_path / "here" / "evaluation.json").read_text() == (tmp_path / "there" / "evaluation.json").read_text()


def test_map_writes_the_geojson_cells_and_a_png_of_the_requested_size(tmp_path):
    from tests.service.test_crlb_grid import cells, local_request, png_size

    grid = tmp_path / "grid.json"
    grid.write_text(json.dumps({**local_request(step_m=2000.0), "image": {"width_px": 120, "height_px": 90}}))
    run = run_cli("map", str(grid), "--out", str(tmp_path / "out"))
    assert run.returncode == 0, run.stderr
    found = cells(json.loads((tmp_path / "out" / "coverage.geojson").read_text()))
    assert len(found) == 11 * 11 and sum(c["unobservable"] for c in found) < len(found)
    assert png_size((tmp_path / "out" / "coverage.png").read_bytes()) == (120, 90)
    bad = tmp_path / "bad.json"
    bad.write_text(json.dumps(local_request(step_m=-1.0)))
    assert run_cli("map", str(bad)).returncode == 2
