"""Core-only speed of closed-form estimators over a batch of four-station problems.

``python -m bench.closed_form_core [-r REPEATS] [--stated-sigma DEG] [size] [method ...]`` builds ``size``
(default 10,000) four-station bearing problems per method (the batch row's scenario: with a range
for ``angle_range``, the target altitude for ``tls`` and ``ctls``) and times, per method, the
estimator alone (``spec.estimate``) and estimator plus finisher (``spec.solve_batch``); median of
``repeats`` (default 5) runs, GC frozen as the batch route does. ``--stated-sigma`` states the bearings'
sigmas as given (the noise stays :data:`bench.scenarios.SIGMA_DEG`): sigmas stated too small, as real data
often has them, make every fit implausible and flag it.
"""

from __future__ import annotations

import argparse
import gc
import time

import numpy as np

from bench.scenarios import SIGMA_DEG, four_station_requests
from core.estimators import SolveOptions
from core.estimators.base import get_estimator
from service.fixes.read import read_fix_requests


def _median_s(run, repeats: int) -> float:
    times = []
    for _ in range(repeats):
        t = time.perf_counter()
        run()
        times.append(time.perf_counter() - t)
    return float(np.median(times))


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(prog="python -m bench.closed_form_core", description=__doc__.split("\n\n")[0])
    parser.add_argument("-r", "--repeats", type=int, default=5)
    parser.add_argument("--stated-sigma", type=float, default=SIGMA_DEG, metavar="DEG")
    parser.add_argument("size", type=int, nargs="?", default=10_000)
    parser.add_argument("methods", nargs="*", default=["weighted_eove", "eove"])
    args = parser.parse_args(argv)
    size, repeats, stated, methods = args.size, args.repeats, args.stated_sigma, args.methods
    options = SolveOptions()
    for method in methods:
        read = read_fix_requests(four_station_requests(size, np.random.default_rng(22), method,
                                                         stated_sigma_deg=stated))
        batch = read.batch
        assert not read.errors and batch.size == size
        gc.collect()
        gc.freeze()
        spec = get_estimator(method)
        estimate_s = _median_s(lambda: spec.estimate(batch, options), repeats)
        solve_s = _median_s(lambda: spec.solve_batch(batch, options), repeats)
        print(f"{method:14s} estimate {size / estimate_s:12,.0f} fixes/s ({estimate_s * 1e6 / size:7.2f} us/fix)   "
              f"estimate+finish {size / solve_s:10,.0f} fixes/s ({solve_s * 1e6 / size:7.2f} us/fix)")
        gc.unfreeze()
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
