"""One tree's core fix times, for comparing two commits side by side.

``python -m bench.core_fix_times [label]`` prints the mean time of one four-station ML fix (reading the
request into the frame and ``solve_many``, a batch of one; 300 problems after 30 to warm up) and the best
of three ``solve_many`` runs over 10,000 such problems. To compare commits, check the other one out in a
worktree and run this module alternately in both (``PYTHONPATH=<tree>``), in one session on one machine.
"""

from __future__ import annotations

import sys
import time

import numpy as np

from bench.scenarios import four_station_requests
from core.estimators import solve_many
from service.fixes.read import read_fix_requests


def single_fix_us(count: int = 300, warm: int = 30) -> float:
    """Mean microseconds of read + solve for one problem at a time."""
    requests = four_station_requests(count, np.random.default_rng(13))

    def one(request):
        read = read_fix_requests([request])
        return solve_many(read.batch, read.methods, read.options)

    for request in requests[:warm]:
        one(request)
    start = time.perf_counter()
    for request in requests:
        one(request)
    return (time.perf_counter() - start) / count * 1e6


def batch_s(size: int = 10_000, repeats: int = 3) -> float:
    """Best seconds of ``solve_many`` over ``size`` problems (the reading excluded)."""
    read = read_fix_requests(four_station_requests(size, np.random.default_rng(22)))
    solve_many(read.batch, read.methods, read.options)
    best = np.inf
    for _ in range(repeats):
        start = time.perf_counter()
        solve_many(read.batch, read.methods, read.options)
        best = min(best, time.perf_counter() - start)
    return best


def main(argv=None) -> int:
    label = (argv if argv is not None else sys.argv[1:])[:1] or ["this tree"]
    print(f"{label[0]}: one fix (read + solve) {single_fix_us():,.0f} us; 10,000 ml fixes in core {batch_s():.3f} s")
    return 0


if __name__ == "__main__":
    sys.exit(main())
