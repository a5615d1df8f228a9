"""``service.fixes.pipeline.compile_kernels`` (run at install, image build and in the lifespan) compiles every kernel
a fix or a session step can reach, the core's and the service's, with the argument types the estimators,
filters and the reader and writer pass, so that no request pays numba's compilation (seconds). Checked in a
fresh process: after it, a varied workload adds no compiled signature anywhere."""

from __future__ import annotations

import subprocess
import sys
import textwrap

from tests.service.sessions.helpers import REPO

_WORKLOAD = textwrap.dedent('''
    import importlib, pkgutil
    import numpy as np
    import core
    import service
    from numba.core.registry import CPUDispatcher

    def signatures():
        out = {}
        for info in [*pkgutil.walk_packages(core.__path__, "core."),
                     *pkgutil.walk_packages(service.__path__, "service.")]:
            module = importlib.import_module(info.name)
            for name, value in vars(module).items():
                if isinstance(value, CPUDispatcher) and value.__module__ == module.__name__:
                    out[f"{module.__name__}.{name}"] = len(value.signatures)
        return out

    from service.fixes.pipeline import compile_kernels
    compile_kernels()
    before = signatures()

    from core.crlb import information_at
    from core.errors import LocalizationError
    from core.estimators import REGISTRY, SolveOptions, solve
    from core.estimators.loss import LOSSES
    from core.problem.build import Bearing, GeodeticPoint, Range, TimeOfArrival, build_problem

    rng = np.random.default_rng(5)
    stations = [(f"s{k}", GeodeticPoint(0.59 + 0.004 * rng.standard_normal(), 1.89 + 0.004 * rng.standard_normal(),
                                        200.0 * k)) for k in range(5)]
    bearings = [Bearing(sid, float(rng.uniform(0, 6.28)), float(rng.uniform(0.0, 0.2)), 0.01, 0.01)
                for sid, _ in stations]
    azimuths = [Bearing(sid, float(rng.uniform(0, 6.28)), None, 0.01) for sid, _ in stations]
    mixes = [bearings, azimuths, bearings[:2] + [Range("s0", 3e4, 30.0), Range("s1", 2.5e4, 30.0)],
             [TimeOfArrival(sid, 1e-5 * k, 1e-8) for k, (sid, _) in enumerate(stations)] + bearings[:1]]
    for measurements in mixes:
        for altitude in (None, 3000.0):
            problem = build_problem(stations, measurements, altitude_m=altitude)
            information_at(problem, problem.stations_enu_m[0] + 1e4)
            for method in sorted(REGISTRY):
                for options in [SolveOptions()] + [SolveOptions(loss=loss) for loss in LOSSES[1:]] * (method == "ml"):
                    try:
                        solve(problem, method, options)
                    except LocalizationError:
                        pass
    from core.error_summary import error_summary
    error_summary(np.tile(np.diag([4.0, 1.0, 9.0]), (3, 1, 1))[:, ::-1])
    error_summary(np.eye(3), exact=True)
    from core.simulation.emitter import paper_001_scenario, simulate_emitter
    from core.simulation.tracking import paper_config
    from core.tracking import new_state, step

    track = simulate_emitter(paper_001_scenario(), np.random.default_rng(5))
    for config in (paper_config("joint_ukf", False), paper_config("joint_ukf", True, joint_initial_range="kinematic"),
                   paper_config("joint_ukf", False, imm_accel_sigmas_mps2=(0.05, 1.0)),
                   paper_config("velocity_kinematic", False)):
        state = new_state(config)
        for epoch in track.epochs:
            state = step(state, epoch, config)
    from service.fixes.pipeline import fix_results
    from service.fixes.decode import decode_batch
    rng = np.random.default_rng(9)
    bodies = [{"frame": "wgs84", "method": method, "formats": formats,
               "stations": [{"id": sid, "position": {"lat_deg": 33.8 + 0.2 * k, "lon_deg": 108.1 - 0.1 * k}}
                            for k, sid in enumerate("pqrs")],
               "measurements": [{"type": "bearing", "station_id": sid, "azimuth_deg": float(rng.uniform(0, 360)),
                                 "sigma_azimuth_deg": 1.0} for sid in "pqrs"]}
              for method in ("ml", "weighted_eove", "ws3d") for formats in ([], ["cot"])]
    fix_results(bodies)
    fix_results(bodies[:1])
    fix_results(decode_batch(__import__("orjson").dumps({"problems": bodies})))
    after = signatures()
    grew = sorted(name for name in after if after[name] > before.get(name, 0))
    print("GREW", grew)
''')


def test_no_fix_compiles_a_kernel_after_compile_kernels():
    run = subprocess.run([sys.executable, "-c", _WORKLOAD], cwd=REPO, capture_output=True, text=True, timeout=600)
    assert run.returncode == 0, run.stderr[-4000:]
    assert "GREW []" in run.stdout, run.stdout[-2000:]


def test_every_kernel_divides_as_numpy_does():
    """numba's default error model raises ZeroDivisionError where numpy gives inf or nan (a degenerate
    geometry would then be a 500); every kernel of the core uses numpy's."""
    import importlib
    import pkgutil

    import numpy as np
    from numba.core.registry import CPUDispatcher

    import core
    from core.estimators.lm import _solve_small

    kernels = {}
    for info in pkgutil.walk_packages(core.__path__, "core."):
        module = importlib.import_module(info.name)
        kernels.update({f"{module.__name__}.{name}": value for name, value in vars(module).items()
                        if isinstance(value, CPUDispatcher) and value.__module__ == module.__name__})
    assert len(kernels) >= 20
    assert not [name for name, kernel in kernels.items() if kernel.targetoptions.get("error_model") != "numpy"]
    out = np.empty(4)
    _solve_small(np.zeros((4, 4)), np.ones(4), out)
    assert np.all(np.isnan(out))
