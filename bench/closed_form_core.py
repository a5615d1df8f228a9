"""Core-only speed of closed-form estimators over a batch of four-station problems.

``python -m bench.closed_form_core [-r repeats] [size] [method ...]`` builds ``size``
(default 10,000) four-station bearing problems (the batch row's scenario) and times, per
method, the estimator alone (``spec.estimate``) and estimator plus finisher
(``spec.solve_batch``); median of ``repeats`` (default 5) runs, GC frozen as the batch route does.
"""

from __future__ import annotations

import gc
import sys
import time

import numpy as np

from bench.scenarios import four_station_requests
from core.estimators import SolveOptions
from core.estimators.base import get_estimator
from service.translate import read_fix_requests


def _median_s(run, repeats: int) -> float:
    times = []
    for _ in range(repeats):
        t = time.perf_counter()
        run()
        times.append(time.perf_counter() - t)
    return float(np.median(times))


def main(argv=None) -> int:
    argv = list(sys.argv[1:] if argv is None else argv)
    repeats = 5
    if argv[:1] == ["-r"]:
        repeats, argv = int(argv[1]), argv[2:]
    size = int(argv[0]) if argv else 10_000
    methods = argv[1:] or ["weighted_eove", "eove"]
    read = read_fix_requests(four_station_requests(size, np.random.default_rng(22)))
    batch = read.batch
    assert not read.errors and batch.size == size
    options = SolveOptions()
    gc.collect()
    gc.freeze()
    for method in methods:
        spec = get_estimator(method)
        estimate_s = _median_s(lambda: spec.estimate(batch, options), repeats)
        solve_s = _median_s(lambda: spec.solve_batch(batch, options), repeats)
        print(f"{method:14s} estimate {size / estimate_s:12,.0f} fixes/s ({estimate_s * 1e6 / size:7.2f} us/fix)   "
              f"estimate+finish {size / solve_s:10,.0f} fixes/s ({solve_s * 1e6 / size:7.2f} us/fix)")
    gc.unfreeze()
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
