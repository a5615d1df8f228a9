"""Every compiled (numba) kernel of the core, compiled or loaded from numba's on-disk cache in one call.

The kernels: :func:`core.linalg.jacobi_svd`, the point conversions of
:mod:`core.geodesy`, :func:`core.measurements.measure_point`,
:func:`core.estimators.loss.loss_point` and the ML iteration
(:func:`core.estimators.ml.levenberg_marquardt`). :func:`compile_kernels` runs
each once on the argument types the estimators pass, so that no fix pays for
a compilation.
"""

from __future__ import annotations

import numpy as np


def compile_kernels() -> None:
    """Compile (or load from the cache) every kernel: called at install and image build time (which fill the
    cache) and in the service's lifespan."""
    from core.estimators import SolveOptions, solve
    from core.linalg import jacobi_svd
    from core.problem import Bearing, GeodeticPoint, LocalPoint, TimeOfArrival, build_problem

    jacobi_svd(np.eye(4, 3)[None], np.ones((1, 4, 1)))
    local = [(name, LocalPoint(east, north, 0.0)) for name, east, north in
             (("a", 0.0, 0.0), ("b", 10_000.0, 0.0), ("c", 0.0, 10_000.0), ("d", 10_000.0, 10_000.0))]
    target = np.array([4_000.0, 6_000.0, 1_000.0])
    bearings = []
    for name, point in local:
        d = target - [point.east_m, point.north_m, point.up_m]
        bearings.append(Bearing(name, float(np.arctan2(d[0], d[1])), float(np.arctan2(d[2], np.hypot(d[0], d[1]))),
                                1e-3, 1e-3))
    solve(build_problem(local, bearings))
    solve(build_problem(local, bearings), "ml", SolveOptions(loss="huber"))
    geodetic = [(name, GeodeticPoint(0.6 + 1e-3 * k, 1.9 + 1e-3 * (k % 2), 100.0)) for k, name in enumerate("abcd")]
    toas = [TimeOfArrival(name, 1e-4 * k, 1e-8) for k, name in enumerate("abcd")]
    solve(build_problem(geodetic, toas, altitude_m=500.0))
