"""The session filters give the numbers recorded from the old implementation (``golden/``).

The hot path of ``core.tracking`` was rewritten for speed (scalar arithmetic, fewer numpy calls, the
step-1 Joseph update written as the equivalent rank-one downdate); the filter itself was not meant to
change. The old filters (commit ed7cbfd) were run on fixed scenarios that visit every branch of a step
(start, bootstrap, tracking, range unobservable, missed epochs, a TOA off by half a period, a turn to
near-radial flight, a covariance repair), for each model with a known and an unknown period, and their
states recorded (``golden/README.md``). Two states are compared by

- stage, update count and warning codes exactly;
- each mean component relative to ``|x_i| + sigma_i``, each covariance entry relative to
  ``sigma_i sigma_j`` (i.e. the correlation matrix, absolute), the period and the range
  pseudo-measurement relative to themselves; the largest of these is the deviation.

Two checks, because the problem itself amplifies rounding:

- One step from the same input state (the recorded one, at each recorded epoch): the deviation is
  rounding only, at most ``STEP_TOLERANCE``. It is ~1e-13 and below with a known period; with an unknown
  period the step-1 state (line-of-sight velocity and period error, measured almost only in one
  combination at first) is badly conditioned, and the two algebraically equal updates differ by up
  to ~3.4e-12 there, each within ~2e-12 of an 80-bit evaluation of the old formula (measured on the
  step-1 update alone).
- A whole run from ``new_state``, compared at the recorded epochs: rounding differences then propagate
  like any perturbation, and the bootstrap (a covariance collapsing from the 500 m/s prior) amplifies
  them. The yardstick was recorded with the states: the old filter against itself with every azimuth
  moved by one unit in the last place, over the same epochs. The current one must stay within
  ``RUN_FACTOR`` times that (it is about 1e-10 with a known period and 1e-7 with an unknown one on the
  paper scenario: 1e-12 over a whole run is below what the problem preserves from its own inputs).
"""

from __future__ import annotations

import gzip
import json
from pathlib import Path

import numpy as np
import pytest

from core.tracking import Epoch, TrackerConfig, TrackState, new_state, step

GOLDEN = sorted(Path(__file__).with_name("golden").glob("*.json.gz"))

#: Largest deviation of one step from the same input state (3.4e-12 is the largest seen, see above).
STEP_TOLERANCE = 1e-11
#: A whole run may deviate from the recording by this factor times the old filter's one-ulp sensitivity.
RUN_FACTOR = 10.0


def deviation(now: TrackState, then: TrackState) -> float:
    """Largest normalised difference between two states of the same layout (see the module docstring)."""
    assert (now.model, now.stage, now.updates, now.time_s, now.toa_s) == (
        then.model, then.stage, then.updates, then.time_s, then.toa_s)
    assert [code for code, _ in now.warnings] == [code for code, _ in then.warnings]
    assert now.mean.shape == then.mean.shape and now.covariance.shape == then.covariance.shape
    assert (now.last_range_measurement_m is None) == (then.last_range_measurement_m is None)
    sigma = np.sqrt(np.diag(then.covariance))
    worst = [
        float(np.max(np.abs(now.mean - then.mean) / (np.abs(then.mean) + sigma))),
        float(np.max(np.abs(now.covariance - then.covariance) / np.outer(sigma, sigma))),
        abs(now.pulse_period_s - then.pulse_period_s) / then.pulse_period_s,
    ]
    if then.last_range_measurement_m is not None:
        worst.append(abs(now.last_range_measurement_m / then.last_range_measurement_m - 1.0))
    return max(worst)


def load(path: Path):
    """A recorded run: config, epochs, recorded epoch indices, states before each epoch ``{i: state}``,
    planted states ``{i: state}``, the one-ulp sensitivity (see ``record_golden``)."""
    data = json.loads(gzip.decompress(path.read_bytes()))
    states = {int(i): TrackState.from_dict(s) for i, s in data["states"].items()}
    resets = {int(i): TrackState.from_dict(s) for i, s in data["resets"].items()}
    return (TrackerConfig(**data["config"]), [Epoch(*values) for values in data["epochs"]], data["steps"], states,
            resets, data["sensitivity"])


def test_the_recordings_cover_every_branch():
    assert len(GOLDEN) == 30
    codes, stages = set(), set()
    models = set()
    for path in GOLDEN:
        config, _, steps, states, _, _ = load(path)
        models.add((config.model, config.period_known, config.pseudo_range_errors))
        for i in steps:
            codes |= {code for code, _ in states[i + 1].warnings}
            stages.add((states[i].stage, states[i + 1].stage))
    assert len(models) == 6
    assert {"pulse_count_ambiguous", "range_unobservable", "covariance_repaired", "innovation_outlier"} <= codes
    assert {("velocity", "velocity"), ("velocity", "tracking"), ("tracking", "tracking")} <= stages


@pytest.mark.parametrize("path", GOLDEN, ids=lambda p: p.name.removesuffix(".json.gz"))
def test_each_step_and_each_run_give_the_recorded_states(path):
    config, epochs, steps, states, resets, sensitivity = load(path)
    worst_step = 0.0
    for i in steps:
        worst_step = max(worst_step, deviation(step(resets.get(i, states[i]), epochs[i], config), states[i + 1]))
    assert worst_step <= STEP_TOLERANCE

    now = new_state(config)
    assert deviation(now, states[0]) == 0.0
    worst_run = 0.0
    for i, epoch in enumerate(epochs):
        now = step(resets.get(i, now), epoch, config)
        if i + 1 in states:
            worst_run = max(worst_run, deviation(now, states[i + 1]))
    assert worst_run <= RUN_FACTOR * max(sensitivity, 1e-13), (worst_run, sensitivity)
