"""Every compiled (numba) kernel of the core, compiled or loaded from numba's on-disk cache in one call.

The per-problem inner loops are compiled: the point conversions of
:mod:`core.geodesy`, the altitude surface and local axes of :mod:`core.problem.frame`,
the frame and station placement and the padding of :mod:`core.problem.batch_build`,
the model values and weights of :mod:`core.problem.batch`, the measurement model and TOA offset of :mod:`core.measurements`, the robust
losses, the small SVD and eigen-decomposition of :mod:`core.linalg`, the
information pieces of :mod:`core.crlb`, the error summaries, the
orthogonal-vector passes, the ML iteration, the finisher and the tracking
filters' kernels. :func:`compile_kernels` runs
every estimator on a few small problems (every measurement kind, a known
altitude, a robust loss) and the network tracker over a few simulated reports,
so that each kernel meets the argument types its callers pass and no fix or
session post pays for a compilation.
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
    from core.problem.build import Bearing, Range, TimeOfArrival, build_problem
    from core.problem.frame import GeodeticPoint, LocalPoint
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
    _run_network_tracker()


def _run_network_tracker() -> None:
    """Run the network tracker over a few reports of each simulated scene, with one motion model and with an
    IMM, late reports and a reload included, so that its kernels meet the argument types a session's posts
    pass (a kernel compiled on a post takes seconds, beyond a store call's deadline)."""
    from dataclasses import replace

    from core.simulation.network import SCENES, simulate_network
    from core.tracking.network import NetworkState, apply_reports, new_network_state, predict_tracks

    for _, scene_of in sorted(SCENES.items()):
        scene = scene_of()
        posted = simulate_network(scene, np.random.default_rng(0)).posted[:12]
        for config in (scene.config, replace(scene.config, imm_accel_sigmas_mps2=(0.1, 5.0))):
            state = new_network_state(config)
            for item in posted:
                state = apply_reports(state, [item.report], config).state
            state = apply_reports(state, [p.report for p in posted[:2]], config).state
            predict_tracks(NetworkState.from_dict(state.to_dict()), posted[-1].report.time_s + 1.0, config)
