"""Fix options through the API: outlier exclusion, relative sigmas, validated option values."""

from __future__ import annotations

import copy

import pytest

from tests.service.conftest import STATIONS_300KM, TARGET, bearing_request
from tests.service.test_fixes_api import assert_problem


def _with_gross_azimuth(**options) -> dict:
    request = bearing_request(STATIONS_300KM, TARGET, sigma_deg=0.05, options=options)
    request["measurements"][1]["azimuth_deg"] += 20.0
    return request


def test_exclude_names_and_marks_the_gross_bearing(client):
    body = client.post("/v1/fixes", json=_with_gross_azimuth(outliers="exclude")).json()
    flagged = [(r["measurement_index"], r["used"], r["excluded"]) for r in body["residuals"]]
    assert {(i, used, excluded) for i, used, excluded in flagged if i == 1} == {(1, False, True)}
    assert all(used and not excluded for i, used, excluded in flagged if i != 1)
    assert any(w["code"] == "measurement_excluded" and "measurement 1" in w["message"] for w in body["warnings"])
    assert body["fit"]["dof"] == 2 * 3 - 3


def test_report_keeps_it_and_warns(client):
    body = client.post("/v1/fixes", json=_with_gross_azimuth()).json()
    assert all(r["used"] and not r["excluded"] for r in body["residuals"])
    assert "outlier_suspected" in {w["code"] for w in body["warnings"]}


def test_relative_sigma_scales_the_covariance(client):
    request = _with_gross_azimuth()
    absolute = client.post("/v1/fixes", json=request).json()
    relative = client.post("/v1/fixes", json=request | {"options": {"absolute_sigma": False}}).json()
    scale = relative["fit"]["sigma_scale"] ** 2
    assert relative["covariance_source"] == "information_scaled"
    # to rounding: each is turned into the fix's axes after its scaling
    assert relative["covariance_enu_m2"][0][0] == pytest.approx(absolute["covariance_enu_m2"][0][0] * scale, rel=1e-12)


def test_unknown_option_values_are_422_with_their_path(client):
    base = bearing_request(STATIONS_300KM, TARGET)
    for options, loc in (({"variant": "bogus"}, ["options", "variant"]),
                         ({"outliers": "drop"}, ["options", "outliers"]),
                         ({"absolute_sigma": "no"}, ["options", "absolute_sigma"])):
        assert_problem(client.post("/v1/fixes", json=base | {"options": options}), 422, loc)
    ml_with_variant = copy.deepcopy(base) | {"method": "ml", "options": {"variant": "newton"}}
    assert_problem(client.post("/v1/fixes", json=ml_with_variant), 422, ["options", "variant"])


def test_a_robust_loss_sets_the_gross_bearing_aside(client):
    report = client.post("/v1/fixes", json=_with_gross_azimuth()).json()
    robust = client.post("/v1/fixes", json=_with_gross_azimuth(loss="cauchy", loss_scale=2.0)).json()
    assert robust["covariance_source"] == "robust"
    assert any(w["code"] == "measurement_downweighted" and w["message"].startswith("measurement 1 ")
               for w in robust["warnings"])
    assert robust["fit"]["chi2"] > robust["fit"]["sigma_scale"] ** 2 * robust["fit"]["dof"]  # chi2 stays the plain sum
    # The culprit barely pulls the robust fit: its residual is the whole 20 deg, the others' are small.
    others = [abs(r["normalized"]) for r in robust["residuals"] if r["measurement_index"] != 1]
    assert max(others) < 5.0 < max(abs(r["normalized"]) for r in report["residuals"] if r["measurement_index"] != 1)


def test_bad_loss_values_are_422_with_their_path(client):
    base = bearing_request(STATIONS_300KM, TARGET)
    for options, loc in (({"loss": "l1"}, ["options", "loss"]),
                         ({"loss": ["huber"]}, ["options", "loss"]),
                         ({"loss_scale": 0.0}, ["options", "loss_scale"]),
                         ({"loss_scale": "2"}, ["options", "loss_scale"])):
        assert_problem(client.post("/v1/fixes", json=base | {"options": options}), 422, loc)
    eove_with_loss = copy.deepcopy(base) | {"method": "weighted_eove", "options": {"loss": "huber"}}
    assert_problem(client.post("/v1/fixes", json=eove_with_loss), 422, ["options", "loss"])
