"""Every compiled (numba) kernel of the core, compiled or loaded from numba's on-disk cache in one call.

The per-problem inner loops are compiled: the point conversions of
:mod:`core.geodesy`, the altitude surface and local axes of :mod:`core.problem_frame`,
the frame and station placement and the padding of :mod:`core.problem_batch_build`,
the model values and weights of :mod:`core.problem_batch`, the measurement model and TOA offset of :mod:`core.measurements`, the robust
losses, the small SVD and eigen-decomposition of :mod:`core.linalg`, the
information pieces of :mod:`core.crlb`, the error summaries, the
orthogonal-vector passes, the ML iteration, the finisher and the tracking
filters' kernels. :func:`compile_kernels` runs
every estimator on a few small problems (every measurement kind, a known
altitude, a robust loss), so that each kernel meets the argument types the
estimators pass and no fix pays for a compilation.
"""

from __future__ import annotations

import numpy as np


def compile_kernels() -> None:
    """Compile (or load from the cache) every kernel: called at install and image build time (which fill the
    cache) and in the service's lifespan."""
    from core.crlb import gdop
    from core.error_summary import error_summary
    from core.errors import LocalizationError
    from core.estimators import REGISTRY, SolveOptions, solve
    from core.problem import Bearing, GeodeticPoint, LocalPoint, Range, TimeOfArrival, build_problem
    from core.tracking import unscented

    local = [(name, LocalPoint(east, north, 0.0)) for name, east, north in
             (("a", 0.0, 0.0), ("b", 10_000.0, 0.0), ("c", 0.0, 10_000.0), ("d", 10_000.0, 10_000.0))]
    target = np.array([4_000.0, 6_000.0, 1_000.0])
    bearings = []
    for name, point in local:
        d = target - [point.east_m, point.north_m, point.up_m]
        bearings.append(Bearing(name, float(np.arctan2(d[0], d[1])), float(np.arctan2(d[2], np.hypot(d[0], d[1]))),
                                1e-3, 1e-3))
    ranged = bearings + [Range("a", float(np.linalg.norm(target)), 10.0)]
    geodetic = [(name, GeodeticPoint(0.6 + 1e-3 * k, 1.9 + 1e-3 * (k % 2), 100.0)) for k, name in enumerate("abcd")]
    toas = [TimeOfArrival(name, 1e-4 * k, 1e-8) for k, name in enumerate("abcd")]
    problems = [build_problem(local, bearings), build_problem(local, ranged),
                build_problem(local, bearings, altitude_m=1_000.0), build_problem(geodetic, toas, altitude_m=500.0)]
    for method in sorted(REGISTRY):
        for problem in problems:
            try:
                solve(problem, method)
            except LocalizationError:
                pass
    solve(problems[0], "ml", SolveOptions(loss="huber"))
    error_summary(np.eye(3))
    error_summary(np.eye(3), exact=True)
    gdop(np.eye(3)[None], np.ones(1))  # the planning routes' (a fix's GDOP comes from the finisher's kernel)
    unscented.compile_kernels()
    _compile_network_tracker()


def _compile_network_tracker() -> None:
    """Compile (or load from numba's cache) the network tracker's kernels (:mod:`core.tracking.network_kernel`)
    with the argument types the tracker passes: a track started from a bearing, updated with bearings and with
    a TOA group, and predicted. Run through the tracker itself, which imports the kernels (so the kernel module
    does not import the tracker back)."""
    from core.measurements import AZIMUTH, TOA
    from core.tracking.network import NetworkConfig, NetworkState, Report, apply_reports, predict_tracks

    config = NetworkConfig()
    eye = np.tile(np.eye(3), (4, 1, 1))
    stations = np.array([[0.0, 0.0, 0.0], [0.0, 0.0, 0.0], [2e4, 0.0, 0.0], [0.0, 2e4, 0.0]])
    bearing = Report(0, 0.0, "e", ("a", "a"), stations[:2], eye[:2], [AZIMUTH, 1], [0.8, 0.0], [0.01, 0.01])
    toas = Report(1, 1.0, "e", ("a", "b", "c"), stations[1:], eye[1:], [TOA] * 3, [1e-4, 2e-4, 1.5e-4], [3e-8] * 3)
    state = apply_reports(NetworkState(), [bearing, toas], config).state
    predict_tracks(state, 2.0, config)
