"""Large problems stay bounded in a batch: the parts a batch is solved in, and the start search's candidates.

A batch is solved in parts (the unit a deadline or a gone client waits for, and what the pairwise methods
hold in memory at once); a start search runs ML from every candidate over all of a problem's measurements.
Both grow with the size of the problems, which the cost model (the sum of measurements) does not see.
"""

from __future__ import annotations

import copy

import numpy as np

import core.estimators as estimators
from bench.scenarios import four_station_requests, largest_fix_request
from core.estimators.base import EstimatorSpec
from service.translate import read_fix_requests


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
    solved = estimators.solve_many(read.batch, read.methods, read.options)
    assert sum(size for size, _ in parts) == 304
    for size, rows in parts:
        assert size == 1 or size * rows**2 <= estimators.PART_PAIRS, parts
    assert sorted(parts) == [(1, 2048)] * 4 + [(300, 8)]
    assert all(not isinstance(fixes, Exception) and fixes.ok.all() for _, fixes in solved)

