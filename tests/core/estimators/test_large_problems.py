"""Large problems stay bounded in a batch: the parts a batch is solved in, and the start search's candidates.

A batch is solved in parts (the unit a deadline or a gone client waits for, and what the pairwise methods
hold in memory at once); a start search runs ML from every candidate over all of a problem's measurements.
Both grow with the size of the problems, which the cost model (the sum of measurements) does not see.
"""

from __future__ import annotations

import copy
import random

import numpy as np

from bench.scenarios import four_station_requests, largest_fix_request
from core import estimators
from core.estimators.base import EstimatorSpec
from core.estimators.search import SEARCH_PAIRS, candidates
from service.fixes.read import read_fix_requests


def test_a_part_holds_at_most_part_pairs_or_one_problem(monkeypatch):
    """Four problems of 1,024 bearings (2,048 rows) and 300 of four: every large one is a part of its own
    (ws3d held about 90 MB per such problem at once, and a part of 195 of them was within max_batch_cost),
    the small ones stay in one part."""
    large = largest_fix_request("ws3d")
    bodies = [copy.deepcopy(large) for _ in range(4)] + four_station_requests(300, np.random.default_rng(2),
                                                                             method="ws3d")
    read = read_fix_requests(bodies)
    parts = []
    real = EstimatorSpec.solve_batch

    def recording(self, batch, options, excluded=None):
        parts.append((batch.size, int(batch.n_measurements.max())))
        return real(self, batch, options, excluded)

    monkeypatch.setattr(EstimatorSpec, "solve_batch", recording)
    monkeypatch.setattr(estimators, "confirm_outliers", lambda spec, batch, options, fixes: fixes)  # not parts
    solved = estimators.solve_many(read.batch, read.methods, read.options)
    assert sum(size for size, _ in parts) == 304
    for size, rows in parts:
        assert size == 1 or size * rows**2 <= estimators.PART_PAIRS, parts
    assert sorted(parts) == [(1, 2048)] * 4 + [(300, 8)]
    assert all(not isinstance(fixes, Exception) and fixes.ok.all() for _, fixes in solved)


def test_the_start_search_of_a_large_problem_is_thinned_to_its_budget():
    """The largest fix with bearings that fit no point (so ML searches for a start): 3,328 candidates before,
    each an LM run over 2,048 rows (12.5 s for one problem); 1,024 TOAs from its 256 stations: 338 around the
    centroid (14.5 s with outlier exclusion). Now each is within SEARCH_PAIRS candidate-rows, and a
    four-station problem keeps a candidate on every line of sight, a TOA-only one every direction."""
    rng = random.Random(1)
    bearings = largest_fix_request("ml")
    for m in bearings["measurements"]:
        m["azimuth_deg"] = rng.uniform(0.0, 360.0)
    toas = largest_fix_request("ml")
    toas["measurements"] = [{"type": "toa", "station_id": s["id"], "toa_s": 1000.0 + rng.uniform(0.0, 1e-3),
                             "sigma_s": 1e-8} for s in toas["stations"] for _ in range(4)]
    small = four_station_requests(1, np.random.default_rng(3))[0]
    small_toas = copy.deepcopy(small)
    small_toas["measurements"] = [{"type": "toa", "station_id": s["id"], "toa_s": 1000.0 + 1e-5 * k,
                                   "sigma_s": 1e-8} for k, s in enumerate(small["stations"])]
    batch = read_fix_requests([bearings, toas, small, small_toas]).batch
    found = np.isfinite(candidates(batch)).all(axis=-1).sum(axis=-1)
    rows = batch.n_measurements
    assert (0 < found[:2]).all() and (found[:2] * rows[:2] <= SEARCH_PAIRS).all(), (found, rows)
    assert found[2] == 4 * 13  # four stations' lines, 13 distances each
    assert found[3] == 26 * 13  # every direction of the sphere around the centroid, 13 distances each
