"""The association tracker against a Stone Soup global-nearest-neighbour tracker on the same unlabelled bearings
(a yardstick): mean GOSPA of the multi-emitter scene's variants, the same runs, epochs and measure.

The Stone Soup tracker (``bench/multi_stonesoup.py``) is its UKF with core's measurement model, GNN with the
Mahalanobis distance gated at the tracker's gate, the tracker's own track starts and management: the two
differ in the association (JPDA against GNN) and the filter's unscented rule.
"""

from __future__ import annotations

import numpy as np
import pytest

pytest.importorskip("stonesoup")
pytest.importorskip("sklearn")

from bench.multi_stonesoup import stonesoup_gospa  # noqa: E402
from core.simulation.multi_emitter import evaluate_multi, multi_emitter_scene  # noqa: E402

#: Every variant of the scene (the held-out ones too), one run each that both trackers see.
VARIANTS = tuple(range(8))
TRIALS = 1
SEED = 40


@pytest.mark.slow
def test_mean_gospa_no_worse_than_stonesoup_gnn_on_the_same_bearings():
    ours, theirs = [], []
    for variant in VARIANTS:
        scene = multi_emitter_scene(variant)
        ours.extend(evaluate_multi(scene, TRIALS, SEED).gospa_per_trial.tolist())
        theirs.extend(stonesoup_gospa(scene, TRIALS, SEED).tolist())
    ours, theirs = np.array(ours), np.array(theirs)
    # Paired runs: the mean over all of them, each run's GOSPA the mean over its 300 epochs.
    assert ours.mean() <= theirs.mean(), (ours.round(1).tolist(), theirs.round(1).tolist())
