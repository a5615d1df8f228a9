"""The session-filter API: configuration, epochs, state round trips and the errors a caller can act on."""

from __future__ import annotations

import json
import math
import subprocess
import sys
from dataclasses import replace

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from core.errors import InvalidInput
from core.simulation.emitter import paper_001_scenario, simulate_emitter
from core.angles import line_of_sight_enu
from core.tracking import (MODELS, WARNING_CODES, Epoch, TimeNotIncreasing, TrackerConfig, TrackState, new_state,
                           step, step_many)
from core.tracking.config import DEFAULT_RANGE_PRIOR_M, DEFAULT_RANGE_PRIOR_SIGMA_M
from core.simulation.tracking import paper_config


def test_models_are_the_two_the_api_names():
    assert set(MODELS) == {"velocity_kinematic", "joint_ukf"}


@pytest.mark.parametrize("model", sorted(MODELS))
def test_new_state_is_not_initialised_and_has_no_position(model):
    state = new_state(paper_config(model, False))
    assert not state.initialized
    assert state.position_enu_m is None and state.velocity_enu_mps is None
    assert state.range_m is None and state.covariance_enu is None
    assert state.updates == 0 and state.warnings == ()
    assert state.pulse_period_s == paper_config(model, False).period_s


def test_unknown_model_raises_invalid_input_naming_the_field():
    with pytest.raises(InvalidInput) as raised:
        paper_config("kalman_magic", True)
    assert raised.value.loc == ("model",)


@pytest.mark.parametrize("field, value", [
    ("period_s", 0.0),
    ("period_s", -1e-3),
    ("period_s", math.nan),
    ("sigma_azimuth_rad", 0.0),
    ("sigma_elevation_rad", math.inf),
    ("sigma_azimuth_rate_rad_s", -1e-4),
    ("sigma_toa_s", "1e-8"),
    ("accel_sigma_mps2", -0.1),
    ("pulses_per_observation", 0),
    ("pulses_per_observation", 10.0),
    ("pulses_per_observation", True),
    ("period_known", "false"),
    ("period_known", 1),
    ("velocity_prior_sigma_mps", 0.0),
    ("period_prior_sigma_s", 0.0),
    ("max_initial_range_fraction", 1.5),
    ("pseudo_range_errors", "sometimes"),
    ("sigma_azimuth_rad", 1.0),
    ("joint_initial_range", "guess"),
    ("range_prior_m", 0.0),
    ("range_prior_sigma_m", -1.0),
    ("range_prior_sigma_m", math.inf),
    ("range_min_m", 0.0),
    ("range_max_m", 5e3),
    ("imm_accel_sigmas_mps2", (0.5,)),
    ("imm_accel_sigmas_mps2", (0.5, 0.1)),
    ("imm_accel_sigmas_mps2", (0.1, 0.2, 0.3, 0.4, 0.5)),
    ("imm_accel_sigmas_mps2", (0.1, math.nan)),
    ("imm_accel_sigmas_mps2", "0.1,1"),
    ("imm_mean_sojourn_s", 0.0),
])
def test_bad_config_values_raise_invalid_input_naming_the_field(field, value):
    fields = {**paper_config("velocity_kinematic", True).to_dict(), field: value}
    with pytest.raises(InvalidInput) as raised:
        TrackerConfig(**fields)
    assert raised.value.loc == (field,)


def test_an_imm_needs_the_joint_model():
    with pytest.raises(InvalidInput) as raised:
        paper_config("velocity_kinematic", True, imm_accel_sigmas_mps2=(0.05, 1.0))
    assert raised.value.loc == ("imm_accel_sigmas_mps2",)


def test_imm_config_round_trips_through_json_and_reports_mode_probabilities():
    config = paper_config("joint_ukf", False, imm_accel_sigmas_mps2=[0.05, 1.0])
    assert config.imm_accel_sigmas_mps2 == (0.05, 1.0)
    assert TrackerConfig.from_dict(json.loads(json.dumps(config.to_dict()))) == config
    track = simulate_emitter(paper_001_scenario(epochs=120, accel_sigma_mps2=0.05), np.random.default_rng(6))
    state = new_state(config)
    for epoch in track.epochs:
        state = step(state, epoch, config)
        assert (state.mode_probabilities is None) == (state.stage != "imm")
    assert state.stage == "imm"
    assert len(state.mode_probabilities) == 2 and sum(state.mode_probabilities) == pytest.approx(1.0)
    assert state.mode_probabilities[0] > 0.5  # the quiet level, on a quiet target


def test_config_round_trips_through_json():
    config = paper_config("joint_ukf", False, period_prior_sigma_s=5e-8)
    again = TrackerConfig.from_dict(json.loads(json.dumps(config.to_dict())))
    assert again == config


def test_config_from_dict_rejects_unknown_and_missing_fields():
    data = paper_config("joint_ukf", False).to_dict()
    with pytest.raises(InvalidInput):
        TrackerConfig.from_dict({**data, "colour": "blue"})
    del data["sigma_toa_s"]
    with pytest.raises(InvalidInput):
        TrackerConfig.from_dict(data)


@pytest.mark.parametrize("field, value", [
    ("azimuth_rad", math.nan),
    ("toa_s", math.inf),
    ("time_s", "12"),
    ("elevation_rad", math.pi / 2),
    ("azimuth_rate_rad_s", None),
])
def test_bad_epoch_values_raise_invalid_input_naming_the_field(field, value):
    config = paper_config("velocity_kinematic", True)
    epoch = simulate_emitter(paper_001_scenario(epochs=2), np.random.default_rng(1)).epochs[0]
    values = {name: getattr(epoch, name) for name in ("time_s", "azimuth_rad", "elevation_rad",
                                                      "azimuth_rate_rad_s", "toa_s")}
    values[field] = value
    with pytest.raises(InvalidInput) as raised:
        step(new_state(config), Epoch(**values), config)
    assert raised.value.loc == (field,)


def test_time_not_increasing_is_its_own_invalid_input():
    config = paper_config("velocity_kinematic", True)
    first, second = simulate_emitter(paper_001_scenario(epochs=2), np.random.default_rng(1)).epochs
    state = step(step(new_state(config), first, config), second, config)
    for time_s in (second.time_s, first.time_s):
        with pytest.raises(TimeNotIncreasing) as raised:
            step(state, Epoch(time_s, second.azimuth_rad, second.elevation_rad, second.azimuth_rate_rad_s,
                              second.toa_s + 1.0), config)
        assert isinstance(raised.value, InvalidInput)
        assert raised.value.code == "time_not_increasing" and raised.value.loc == ("time_s",)


def test_state_of_another_model_or_period_setting_is_refused():
    known = paper_config("velocity_kinematic", True)
    epoch = simulate_emitter(paper_001_scenario(epochs=1), np.random.default_rng(1)).epochs[0]
    with pytest.raises(InvalidInput):
        step(new_state(known), epoch, paper_config("joint_ukf", True))
    with pytest.raises(InvalidInput):
        step(new_state(known), epoch, paper_config("velocity_kinematic", False))


@pytest.mark.parametrize("data", [
    None,
    {},
    {"format": 99},
    {"format": 1, "model": "nope"},
])
def test_from_dict_refuses_what_is_not_a_state(data):
    with pytest.raises(InvalidInput):
        TrackState.from_dict(data)


def test_from_dict_refuses_a_state_with_a_bad_field():
    good = new_state(paper_config("joint_ukf", False)).to_dict()
    for key, value in [("stage", "flying"), ("updates", -1), ("mean", [1.0, "x"]), ("covariance", [[1.0]]),
                       ("pulse_period_s", 0.0), ("warnings", [["code"]]), ("time_s", math.nan)]:
        with pytest.raises(InvalidInput):
            TrackState.from_dict({**good, key: value})


@pytest.mark.parametrize("model, changes, stages", [
    ("velocity_kinematic", {}, {"velocity", "tracking"}),
    ("joint_ukf", {"joint_initial_range": "kinematic"}, {"velocity", "tracking"}),
    ("joint_ukf", {"joint_initial_range": "prior"}, {"tracking"}),
    ("joint_ukf", {"joint_initial_range": "range_mixture"}, {"mixture", "tracking"}),
])
def test_state_round_trips_through_json_exactly_at_every_stage(model, changes, stages):
    """The prior-seeded joint UKF tracks from its first epoch: it has no velocity stage after new_state."""
    config = paper_config(model, False, **changes)
    track = simulate_emitter(paper_001_scenario(epochs=60), np.random.default_rng(4))
    state = new_state(config)
    seen_stages = set()
    for epoch in track.epochs:
        state = step(state, epoch, config)
        data = state.to_dict()
        text = json.dumps(data, allow_nan=False)
        again = TrackState.from_dict(json.loads(text))
        assert again == state
        assert again.to_dict() == data
        seen_stages.add(state.stage)
    assert seen_stages == stages


def test_the_direct_joint_ukf_starts_from_the_range_prior():
    """joint_initial_range="prior" (the paper's baseline, on the raw measurements alone): after the first
    epoch the position is range_prior_m along the measured angles, with range_prior_sigma_m along the line of
    sight and r sigma_angle across it; the velocity is zero with velocity_prior_sigma_mps. The default is the
    range-mixture start (see TrackerConfig)."""
    assert paper_config("joint_ukf", True).joint_initial_range == "range_mixture"
    config = paper_config("joint_ukf", True, joint_initial_range="prior")
    assert (config.range_prior_m, config.range_prior_sigma_m) == (DEFAULT_RANGE_PRIOR_M, DEFAULT_RANGE_PRIOR_SIGMA_M)
    epoch = simulate_emitter(paper_001_scenario(epochs=1), np.random.default_rng(1)).epochs[0]
    state = step(new_state(config), epoch, config)
    assert state.initialized and state.updates == 1
    los = line_of_sight_enu(epoch.azimuth_rad, epoch.elevation_rad)
    np.testing.assert_allclose(state.position_enu_m, config.range_prior_m * los, rtol=1e-15)
    np.testing.assert_array_equal(state.velocity_enu_mps, 0.0)
    assert state.range_sigma_m == pytest.approx(config.range_prior_sigma_m, rel=1e-12)
    position = state.covariance_enu[:3, :3]
    across = np.linalg.eigvalsh(position)[:2]
    np.testing.assert_allclose(np.sqrt(across), config.range_prior_m * config.sigma_azimuth_rad *
                               np.array([np.cos(epoch.elevation_rad), 1.0]), rtol=1e-9)
    np.testing.assert_allclose(np.diag(state.covariance_enu)[3:], config.velocity_prior_sigma_mps**2)


def test_config_stored_before_joint_initial_range_existed_keeps_the_kinematic_start():
    """A stored session's config without the field was made when joint_ukf always started from the kinematic
    range: loading it must not switch a running session to the range prior."""
    data = paper_config("joint_ukf", False, joint_initial_range="prior").to_dict()
    del data["joint_initial_range"], data["range_prior_m"], data["range_prior_sigma_m"]
    assert TrackerConfig.from_dict(data).joint_initial_range == "kinematic"


@settings(max_examples=60, deadline=None)
@given(st.lists(st.floats(allow_nan=False, allow_infinity=False), min_size=16, max_size=16),
       st.floats(min_value=1e-12, max_value=10.0))
def test_any_finite_floats_round_trip_bit_for_bit(values, period_s):
    state = TrackState("joint_ukf", "velocity", 3, -0.0, 1e300, period_s, np.array(values[:4]),
                       np.array(values).reshape(4, 4), None, (("pulse_count_mismatch", "é ünïcode"),))
    again = TrackState.from_dict(json.loads(json.dumps(state.to_dict())))
    assert again == state
    assert [math.copysign(1.0, v) for v in again.covariance.ravel()] == [math.copysign(1.0, v) for v in values]
    assert math.copysign(1.0, again.time_s) == -1.0


def test_state_arrays_are_read_only():
    state = new_state(paper_config("velocity_kinematic", True))
    with pytest.raises(ValueError):
        state.mean[0] = 1.0
    with pytest.raises(ValueError):
        state.covariance[0, 0] = 1.0


def test_step_many_gathers_the_warnings_of_the_batch():
    config = paper_config("velocity_kinematic", True)
    scenario = paper_001_scenario(epochs=40, velocity_enu_mps=(-250.0, -250.0 * 100 / 120, 0.0))
    epochs = simulate_emitter(scenario, np.random.default_rng(2)).epochs
    one_by_one = new_state(config)
    codes = []
    for epoch in epochs:
        one_by_one = step(one_by_one, epoch, config)
        codes += [code for code, _ in one_by_one.warnings]
    batch = step_many(new_state(config), epochs, config)
    assert batch.mean.tolist() == one_by_one.mean.tolist()
    assert [code for code, _ in batch.warnings] == sorted(set(codes), key=codes.index)
    (message,) = [m for code, m in batch.warnings if code == "range_unobservable"]
    assert f"and {codes.count('range_unobservable') - 1} more epochs" in message


@pytest.mark.parametrize("model", MODELS)
def test_toas_sent_since_a_distant_epoch_are_named_when_float64_cannot_carry_their_sigma(model):
    """The same epochs, sent as Unix times (1.7e9 s: float64 spacing 2.4e-7 s, 71 m, against sigma_toa_s 1e-8 s)
    and as seconds since the track began; only the first are named, once per epoch."""
    config = paper_config(model, True)
    epochs = simulate_emitter(paper_001_scenario(epochs=5), np.random.default_rng(4)).epochs
    shifted = [replace(e, toa_s=e.toa_s + 1.7e9) for e in epochs]
    for sent, warned in ((epochs, False), (shifted, True)):
        state = new_state(config)
        for epoch in sent:
            state = step(state, epoch, config)
            codes = [code for code, _ in state.warnings]
            assert ("toa_resolution" in codes) is warned
    message = dict(state.warnings)["toa_resolution"]
    assert "2.4e-07 s (71 m)" in message and "1.0e-08 s" in message


def test_every_warning_code_raised_is_documented():
    config = paper_config("velocity_kinematic", False)
    track = simulate_emitter(paper_001_scenario(epochs=60, velocity_enu_mps=(-1.0, 1.0, 0.0)),
                             np.random.default_rng(3))
    state = new_state(config)
    for epoch in track.epochs:
        state = step(state, epoch, config)
        assert {code for code, _ in state.warnings} <= set(WARNING_CODES)


def test_importing_the_tracking_core_loads_no_web_framework():
    code = ("import sys, core.tracking, core.simulation.emitter; "
            "print(sorted(m for m in sys.modules if m.split('.')[0] in ('fastapi', 'pydantic', 'starlette')))")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True).stdout
    assert out.strip() == "[]"
