"""Record the session filters' golden vectors (``tests/core/tracking/golden/``) for ``test_regression``.

Run from the repository root::

    .venv/bin/python -m tests.core.tracking.record_golden

It runs the session filters of :mod:`core.tracking` on the scenarios below and writes one gzipped
JSON file per run (the committed files were recorded from the old filters instead, see
``golden/README.md``; record again only after a deliberate change of the filter, and say why in the
commit). JSON floats are Python's ``repr``, which reads back to the same bits, and every state is
:meth:`core.tracking.TrackState.to_dict`, so ``from_dict`` restores it exactly. A file holds

- ``config``: the :class:`~core.tracking.TrackerConfig` fields;
- ``epochs``: every epoch of the run, ``[time_s, azimuth_rad, elevation_rad, azimuth_rate_rad_s, toa_s]``;
- ``steps``: the indices of the recorded epochs (see :func:`recorded_epochs`);
- ``states``: ``{i: state}``, the filter's state *before* epoch ``i`` (``"0"`` is ``new_state``), for
  every ``i`` in ``steps`` and ``i + 1``: each recorded epoch has its input and its output;
- ``resets``: ``{i: state}``, a state planted before epoch ``i`` (the covariance-repair scenario): the
  input of that epoch, from which every run continues;
- ``sensitivity``: the yardstick of the whole-run check, the filter's own largest deviation
  (``test_regression.deviation``) from itself when every azimuth is moved one unit in the last place,
  taken over the states recorded.
"""

from __future__ import annotations

import gzip
import json
import math
from dataclasses import asdict, replace
from pathlib import Path

import numpy as np

from core.simulation.emitter import paper_001_scenario, simulate_emitter
from core.tracking import new_state, step
from core.simulation.tracking import paper_config

GOLDEN_DIR = Path(__file__).with_name("golden")

#: The configurations recorded: (model, period known, other TrackerConfig fields).
CONFIGS = [
    ("velocity_kinematic", True, {}),
    ("velocity_kinematic", False, {}),
    ("velocity_kinematic", True, {"pseudo_range_errors": "independent"}),
    ("velocity_kinematic", False, {"pseudo_range_errors": "independent"}),
    ("joint_ukf", True, {"joint_initial_range": "kinematic"}),
    ("joint_ukf", False, {"joint_initial_range": "kinematic"}),
]

#: Every ``EVERY``-th epoch is recorded besides those of :func:`recorded_epochs`' events.
EVERY = 50
#: The first ``PER_CODE`` epochs raising each warning code are recorded.
PER_CODE = 2


def config_id(case) -> str:
    model, known, extra = case
    return f"{model}-{'known' if known else 'unknown'}" + "".join(f"-{v}" for v in extra.values())


def paper_run(config, seed):
    """The paper-001 track (200 s, constant velocity) with noise seed ``seed``."""
    return list(simulate_emitter(paper_001_scenario(), np.random.default_rng(seed)).epochs), None


def gaps_bad_toa_and_turn_run(config):
    """Missed epochs (a 13 s gap and a 3 s one), TOAs off by half a period before and after initialisation,
    then a turn onto a line 1 degree off the line of sight (range unobservable)."""
    p = np.array(paper_001_scenario().initial_position_enu_m) + 119.0 * np.array((-300.0, 100.0, 2.0))
    inward = -p / np.linalg.norm(p)
    off = np.cross(inward, (0.0, 0.0, 1.0))
    velocity = 300.0 * (np.cos(np.radians(1.0)) * inward + np.sin(np.radians(1.0)) * off / np.linalg.norm(off))
    scenario = paper_001_scenario(epochs=181, turn_epoch=120, velocity_after_turn_enu_mps=tuple(velocity),
                                  missed_epochs=tuple(range(70, 82)) + (100, 101))
    epochs = list(simulate_emitter(scenario, np.random.default_rng(77)).epochs)
    for i in (8, 90):
        epochs[i] = replace(epochs[i], toa_s=epochs[i].toa_s + 0.5 * config.period_s)
    return epochs, None


def covariance_repair_run(config):
    """90 s of the paper track; a velocity correlation beyond 1 is planted in the state before epoch 50."""
    epochs = list(simulate_emitter(paper_001_scenario(epochs=90), np.random.default_rng(7)).epochs)

    def tamper(i, state):
        if i != 50:
            return None
        assert state.initialized
        broken = state.covariance.copy()
        broken[3, 4] = broken[4, 3] = 2.0 * np.sqrt(broken[3, 3] * broken[4, 4])
        return replace(state, covariance=broken)

    return epochs, tamper


#: The scenarios recorded for each configuration: name -> (config -> (epochs, tamper)).
SCENARIOS = {
    "paper-1000": lambda config: paper_run(config, 1000),
    "paper-1001": lambda config: paper_run(config, 1001),
    "paper-1002": lambda config: paper_run(config, 1002),
    "gaps-bad-toa-turn": gaps_bad_toa_and_turn_run,
    "covariance-repair": covariance_repair_run,
}


def recorded_epochs(epochs, outputs, resets) -> list[int]:
    """The epochs whose input and output are recorded: every one up to three after the filter started
    (start and bootstrap); each one whose warning codes differ from the previous epoch's, and the first
    :data:`PER_CODE` raising each code, each with the epoch after; each one after missed reports; each
    planted state and the epoch after; every :data:`EVERY`-th and the last."""
    steps = set(range(0, len(epochs), EVERY)) | {len(epochs) - 1}
    started = next((i for i, state in enumerate(outputs) if state.initialized), len(epochs) - 1)
    steps |= set(range(min(started + 4, len(epochs))))
    nominal = epochs[1].time_s - epochs[0].time_s
    seen: dict[str, int] = {}
    previous: set = set()
    for i, state in enumerate(outputs):
        codes = {code for code, _ in state.warnings}
        first = any(seen.get(code, 0) < PER_CODE for code in codes)
        for code in codes:
            seen[code] = seen.get(code, 0) + 1
        if (first or codes != previous or i in resets
                or (i > 0 and epochs[i].time_s - epochs[i - 1].time_s > 1.5 * nominal)):
            steps |= {i, i + 1}
        previous = codes
    return sorted(i for i in steps if i < len(epochs))


def record(case, name):
    """Run the filter on one configuration and scenario; the JSON-able record (see the module docstring)."""
    from tests.core.tracking.test_regression import deviation

    model, known, extra = case
    config = paper_config(model, known, **extra)
    epochs, tamper = SCENARIOS[name](config)
    then = off = new_state(config)
    outputs, off_outputs, resets = [then], [off], {}
    for i, epoch in enumerate(epochs):
        changed = None if tamper is None else tamper(i, then)
        if changed is not None:
            then = off = resets[i] = changed
        then = step(then, epoch, config)
        off = step(off, replace(epoch, azimuth_rad=math.nextafter(epoch.azimuth_rad, math.inf)), config)
        outputs.append(then)
        off_outputs.append(off)
    steps = recorded_epochs(epochs, outputs[1:], resets)
    kept = sorted({i for i in steps} | {i + 1 for i in steps})
    sensitivity = max(deviation(off_outputs[i], outputs[i]) for i in kept)
    return {
        "config": asdict(config),
        "scenario": name,
        "epochs": [[e.time_s, e.azimuth_rad, e.elevation_rad, e.azimuth_rate_rad_s, e.toa_s] for e in epochs],
        "steps": steps,
        "states": {str(i): outputs[i].to_dict() for i in kept},
        "resets": {str(i): state.to_dict() for i, state in resets.items()},
        "sensitivity": sensitivity,
    }


def main() -> None:
    GOLDEN_DIR.mkdir(exist_ok=True)
    for case in CONFIGS:
        for name in SCENARIOS:
            data = record(case, name)
            path = GOLDEN_DIR / f"{config_id(case)}--{name}.json.gz"
            path.write_bytes(gzip.compress(json.dumps(data, separators=(",", ":")).encode(), mtime=0))
            print(f"{path.name}: {len(data['steps'])} of {len(data['epochs'])} epochs, "
                  f"sensitivity {data['sensitivity']:.3g}, {path.stat().st_size // 1024} KiB")


if __name__ == "__main__":
    main()
