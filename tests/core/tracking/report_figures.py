"""Print the figures quoted for the session filters: ``python -m tests.core.tracking.report_figures [runs]``
(``bound [runs] [switching runs]``: against the PCRB; ``sweep [runs]``: the default model over q = 0.01..2;
``oracle [runs] [q,q,...]``: the PCRB, each run's own bound, the batch oracle and the filter on the same truths).

Not a test module: it measures, it asserts nothing. The tests in this package
assert bounds on the same quantities.
"""

from __future__ import annotations

import sys
import timeit

import numpy as np
from scipy.stats import chi2

from core.simulation.emitter import paper_001_scenario, simulate_emitter
from core.tracking import new_state, step
from core.tracking.config import DEFAULT_RANGE_PRIOR_SIGMA_M
from core.simulation.tracking import PAPER_ACCEL_SIGMA_MPS2, PAPER_FIRST_RANGE_M, paper_config, run_monte_carlo

TIMES_S = (10, 25, 50, 100, 150, 200)
CONVERGENCE_PERCENT = 5.0

#: The filters compared: label, model, config changes.
FILTERS = (
    ("velocity_kinematic", "velocity_kinematic", {}),
    ("velocity_kinematic indep.", "velocity_kinematic", {"pseudo_range_errors": "independent"}),
    ("joint_ukf prior 150+-50 km", "joint_ukf", {"joint_initial_range": "prior"}),
    ("joint_ukf kinematic (dflt)", "joint_ukf", {"joint_initial_range": "kinematic"}),
)

#: Range priors of the direct joint UKF for the sensitivity table: label, config changes.
PRIORS = (
    ("150 km +- 50 km (default)", {}),
    ("150 km +- 25 km (sigma / 2)", {"range_prior_sigma_m": 25e3}),
    ("150 km +- 100 km (sigma x 2)", {"range_prior_sigma_m": 100e3}),
    ("100 km +- 50 km", {"range_prior_m": 100e3}),
    ("200 km +- 50 km", {"range_prior_m": 200e3}),
)
#: Prior means at the truth + k sigma (sigma 50 km) for the sweep.
OFFSETS_SIGMA = (-2.5, -2.0, -1.5, -1.0, -0.5, 0.0, 0.5, 1.0, 1.5, 2.0, 2.5)


def partial_rmse(mc, t: int) -> str:
    """RMSE (% of range) at epoch ``t`` over the runs initialised by then, with their share when not all."""
    errors = mc.position_errors_m[:, t]
    ready = ~np.isnan(errors)
    if not ready.any():
        return "      -      "
    value = 100.0 * np.sqrt(np.mean(errors[ready] ** 2)) / mc.ranges_m[:, t].mean()
    share = "" if ready.all() else f"({ready.mean():.0%})"
    return f"{value:6.2f}{share:>7s}"


def tail_rmse(mc) -> float:
    """Position RMSE over runs and the last 50 s (% of the mean range there)."""
    return 100.0 * float(np.sqrt(np.mean(mc.position_errors_m[:, -51:] ** 2)) / mc.ranges_m[:, -51:].mean())


def nees_figures(mc, runs: int) -> str:
    low, high = chi2.ppf([0.005, 0.995], 6 * runs) / runs
    mean_nees = mc.nees[:, -100:].mean(axis=0)
    inside = np.mean((mean_nees >= low) & (mean_nees <= high))
    return f"mean {mean_nees.mean():6.2f}  min {mean_nees.min():6.2f}  max {mean_nees.max():6.2f}  inside {inside:5.0%}"


def accuracy(runs: int) -> None:
    scenario = paper_001_scenario()
    print(f"Paper-001 scenario, {runs} runs x 200 s, truth at constant velocity, filter accel_sigma "
          f"{PAPER_ACCEL_SIGMA_MPS2} m/s^2.\nPosition RMSE over runs, % of the true range (over the runs initialised "
          "by then, with their share, when not all; '-': none yet)")
    header = "model                         period   " + " ".join(f"t={t:>3d}s       " for t in TIMES_S)
    print(header + "last 50 s  converged(<=5%)  first position (min/median/max)")
    for label, model, extra in FILTERS:
        for known in (True, False):
            mc = run_monte_carlo(paper_config(model, known, **extra), scenario, runs, seed=1000)
            cells = " ".join(partial_rmse(mc, t) for t in TIMES_S)
            first = mc.times_s[np.argmax(~np.isnan(mc.position_errors_m), axis=1)]
            print(f"{label:29s} {'known  ' if known else 'unknown'}  {cells}   {tail_rmse(mc):6.2f}    "
                  f"{mc.convergence_time_s(CONVERGENCE_PERCENT):5.0f} s        "
                  f"{first.min():.0f} / {np.median(first):.0f} / {first.max():.0f} s")


def consistency(runs: int) -> None:
    scenario = paper_001_scenario(accel_sigma_mps2=PAPER_ACCEL_SIGMA_MPS2)
    low, high = chi2.ppf([0.005, 0.995], 6 * runs) / runs
    print(f"\nNEES (6 dof) over the last 100 s, {runs} runs, truth with the filter's acceleration noise; "
          f"99 % interval of the run-mean: [{low:.2f}, {high:.2f}]")
    for label, model, extra in FILTERS:
        for known in (True, False):
            mc = run_monte_carlo(paper_config(model, known, **extra), scenario, runs, seed=5000)
            print(f"{label:29s} {'known  ' if known else 'unknown'}  {nees_figures(mc, runs)}")


def prior_sensitivity(runs: int) -> None:
    """The direct joint UKF (joint_initial_range="prior") under other range priors; the emitter starts at
    156.4 km. Accuracy on the constant-velocity truth (seeds 1000+), NEES on the truth with the filter's
    acceleration noise (seeds 5000+)."""
    scenario = paper_001_scenario()
    noisy = paper_001_scenario(accel_sigma_mps2=PAPER_ACCEL_SIGMA_MPS2)
    print(f"\nDirect joint UKF: sensitivity to the range prior (true first range {PAPER_FIRST_RANGE_M / 1e3:.1f} km), "
          f"{runs} runs; RMSE % of range")
    print("range prior                    period   " + " ".join(f"t={t:>3d}s       " for t in TIMES_S[1:4])
          + "last 50 s  converged(<=5%)  NEES last 100 s")
    for label, changes in PRIORS:
        for known in (True, False):
            config = paper_config("joint_ukf", known, joint_initial_range="prior", **changes)
            mc = run_monte_carlo(config, scenario, runs, seed=1000)
            consistent = run_monte_carlo(config, noisy, runs, seed=5000)
            cells = " ".join(partial_rmse(mc, t) for t in TIMES_S[1:4])
            print(f"{label:30s} {'known  ' if known else 'unknown'}  {cells}   {tail_rmse(mc):6.2f}    "
                  f"{mc.convergence_time_s(CONVERGENCE_PERCENT):5.0f} s         {nees_figures(consistent, runs)}")

    print("\nPrior mean at the truth + k sigma (sigma 50 km): the same filter started short or long; the last "
          "line weights the mean squared error by the normal density of k (what a prior of that width gives "
          "on average)")
    print("k      prior (km)  period   " + " ".join(f"t={t:>3d}s       " for t in TIMES_S[1:4])
          + "last 50 s  converged(<=5%)  mean NEES at 200 s")
    for known in (True, False):
        weights, squared, ranges = [], [], None
        for k in OFFSETS_SIGMA:
            prior = PAPER_FIRST_RANGE_M + k * DEFAULT_RANGE_PRIOR_SIGMA_M
            config = paper_config("joint_ukf", known, joint_initial_range="prior", range_prior_m=prior)
            mc = run_monte_carlo(config, scenario, runs, seed=1000)
            weights.append(np.exp(-0.5 * k * k))
            squared.append(np.mean(mc.position_errors_m[:, -51:] ** 2))
            ranges = mc.ranges_m[:, -51:].mean()
            cells = " ".join(partial_rmse(mc, t) for t in TIMES_S[1:4])
            print(f"{k:+4.1f}   {prior / 1e3:8.1f}    {'known  ' if known else 'unknown'}  {cells}   "
                  f"{tail_rmse(mc):6.2f}    {mc.convergence_time_s(CONVERGENCE_PERCENT):5.0f} s        "
                  f"{np.mean(mc.nees[:, -1]):8.2f}")
        expected = 100.0 * np.sqrt(np.dot(weights, squared) / np.sum(weights)) / ranges
        print(f"normal-weighted over k       {'known  ' if known else 'unknown'}  last 50 s {expected:6.2f}")


def speed(repeats: int = 7) -> None:
    from filterpy.kalman import MerweScaledSigmaPoints, UnscentedKalmanFilter

    track = simulate_emitter(paper_001_scenario(), np.random.default_rng(3))

    def fx(x, dt):
        y = x.copy()
        y[:3] += dt * x[3:6]
        return y

    def polar(x):
        rho = np.hypot(x[0], x[1])
        return np.array([np.linalg.norm(x[:3]), np.arctan2(x[0], x[1]), np.arctan2(x[2], rho)])

    def raw(x):
        p, v = x[:3], x[3:6]
        rho2 = p[0] ** 2 + p[1] ** 2
        return np.array([np.arctan2(p[0], p[1]), np.arctan2(p[2], np.sqrt(rho2)),
                         np.linalg.norm(p) - np.linalg.norm(p - v) + 1000.0 * x[6] - x[7],
                         (p[1] * v[0] - p[0] * v[1]) / rho2])

    def filterpy_step(dim, dim_z, hx, x, p_diag, r_diag):
        ukf = UnscentedKalmanFilter(dim, dim_z, 1.0, hx, fx, MerweScaledSigmaPoints(dim, 1.0, 0.0, 0.0))
        ukf.x, ukf.P, ukf.R, ukf.Q = np.array(x), np.diag(p_diag), np.diag(r_diag), np.eye(dim) * 1e-3
        z = hx(ukf.x)

        def one():
            ukf.predict()
            ukf.update(z)
        return one

    six = filterpy_step(6, 3, polar, [120e3, 100e3, 8e3, -300, 100, 2], [1e6] * 3 + [10] * 3, [1e6, 2.5e-5, 2.5e-5])
    eight = filterpy_step(8, 4, raw, [120e3, 100e3, 8e3, -300, 100, 2, 0, 0], [1e6] * 3 + [10] * 3 + [1, 9],
                          [2.5e-5, 2.5e-5, 9.0, 4e-8])
    subjects = {"filterpy UKF 6 states / 3 measurements": six, "filterpy UKF 8 states / 4 measurements": eight}
    for model in ("velocity_kinematic", "joint_ukf"):
        for known in (True, False):
            config = paper_config(model, known)
            state = new_state(config)
            for epoch in track.epochs[:150]:
                state = step(state, epoch, config)
            epoch = track.epochs[150]
            subjects[f"core {model}, period {'known' if known else 'unknown'}"] = (
                lambda s=state, e=epoch, c=config: step(s, e, c))
    best = {name: float("inf") for name in subjects}
    for _ in range(repeats):
        for name, call in subjects.items():
            best[name] = min(best[name], timeit.timeit(call, number=400) / 400)
    print("\nOne filter step (best of interleaved repeats, same process):")
    for name, seconds in best.items():
        print(f"  {name:45s} {seconds * 1e6:7.1f} us")
    six_s = best["filterpy UKF 6 states / 3 measurements"]
    eight_s = best["filterpy UKF 8 states / 4 measurements"]
    for name, seconds in best.items():
        if name.startswith("core velocity"):
            print(f"  ratio {name} / filterpy 6x3: {seconds / six_s:.3f}")
        elif name.startswith("core joint"):
            print(f"  ratio {name} / filterpy 8x4: {seconds / eight_s:.3f}  (/ 6x3: {seconds / six_s:.3f})")


#: Filters compared against the PCRB: label, model, config changes.
BOUND_FILTERS = (
    ("joint_ukf range_mixture (dflt)", "joint_ukf", {}),
    ("joint_ukf kinematic start", "joint_ukf", {"joint_initial_range": "kinematic"}),
    ("joint_ukf prior 150+-50 km", "joint_ukf", {"joint_initial_range": "prior"}),
    ("velocity_kinematic", "velocity_kinematic", {}),
)
#: The switching target: quiet 70 s, manoeuvring 40 s, quiet 50 s, manoeuvring 40 s (m/s^2).
QUIET_MPS2, MANOEUVRE_MPS2 = 0.05, 1.0
SWITCHING_SCHEDULE = (QUIET_MPS2,) * 70 + (MANOEUVRE_MPS2,) * 40 + (QUIET_MPS2,) * 50 + (MANOEUVRE_MPS2,) * 40


def bound(runs: int, block: int = 50) -> None:
    """Ratio of the position RMSE over the last 50 reports to the PCRB, and the mean position NEES, on truths
    drawn from the filter's model, in blocks of ``block`` runs (seeds 30000 + 100 b), then pooled."""
    from core.simulation.tracking import against_bound

    blocks = max(1, runs // block)
    print(f"\nAgainst the PCRB: {blocks} x {block} runs, truth with the filter's acceleration noise, last 50 of "
          "200 reports; ratio = RMSE / PCRB (per block, pooled), position NEES (3 dof) mean")
    for q in (0.05, 0.5):
        for label, model, extra in BOUND_FILTERS:
            for known in (True, False):
                config = paper_config(model, known, accel_sigma_mps2=q, **extra)
                results = [against_bound(config, paper_001_scenario(accel_sigma_mps2=q), block, 30000 + 100 * b)
                           for b in range(blocks)]
                ratios = [r.ratio(slice(-50, None)) for r in results]
                pooled = np.sqrt(np.mean(np.square(ratios)))
                nees = [float(np.nanmean(r.nees[:, -50:])) for r in results]
                print(f"q={q:<4} {label:31s} {'known  ' if known else 'unknown'}  ratio "
                      + " ".join(f"{x:5.2f}" for x in ratios) + f"  pooled {pooled:5.2f}   NEES "
                      + " ".join(f"{x:5.2f}" for x in nees), flush=True)


def switching(runs: int) -> None:
    """The IMM and the single-level joint UKFs on the switching target, against the PCRB of the true model."""
    from core.simulation.tracking import against_bound

    scenario = paper_001_scenario(accel_sigma_by_interval_mps2=SWITCHING_SCHEDULE)
    print(f"\nSwitching target ({runs} runs, seeds 40000+): quiet {QUIET_MPS2} / manoeuvring {MANOEUVRE_MPS2} m/s^2 "
          "legs of 70/40/50/40 s; RMSE from 60 s on over the PCRB of the true switching model")
    filters = (("IMM (0.05, 1), sojourn 120 s", {"accel_sigma_mps2": MANOEUVRE_MPS2,
                                                  "imm_accel_sigmas_mps2": (QUIET_MPS2, MANOEUVRE_MPS2)}),
               ("single level 0.05", {"accel_sigma_mps2": QUIET_MPS2}),
               ("single level 1.0", {"accel_sigma_mps2": MANOEUVRE_MPS2}))
    for label, changes in filters:
        result = against_bound(paper_config("joint_ukf", True, **changes), scenario, runs, 40000)
        legs = [result.ratio(slice(a, b)) for a, b in ((60, 70), (70, 110), (110, 160), (160, 201))]
        print(f"  {label:30s} ratio {result.ratio(slice(60, None)):5.2f} (legs " + " ".join(f"{x:.2f}" for x in legs)
              + f")  position NEES {np.nanmean(result.nees[:, 60:]):5.2f}", flush=True)


#: Process-noise levels of the sweep (m/s^2): the issue's range 0.01..2.
SWEEP_MPS2 = (0.01, 0.05, 0.2, 0.5, 1.0, 2.0)


def sweep(runs: int) -> None:
    """The default model against the PCRB over the process-noise range, truths from the model (seed 30000)."""
    from core.simulation.tracking import against_bound

    print(f"\nDefault model (joint_ukf, range mixture) over q, {runs} runs, seed 30000, last 50 of 200 reports; "
          "ratio of the RMSE to the PCRB and to the RMS of each run's own bound")
    for q in SWEEP_MPS2:
        for known in (True, False):
            result = against_bound(paper_config("joint_ukf", known, accel_sigma_mps2=q),
                                   paper_001_scenario(accel_sigma_mps2=q), runs, 30000)
            print(f"q={q:<5} {'known  ' if known else 'unknown'}  ratio {result.ratio(slice(-50, None)):6.2f}  "
                  f"own {result.own_ratio(slice(-50, None)):5.2f}  position NEES "
                  f"{np.nanmean(result.nees[:, -50:]):5.2f}", flush=True)


#: Reports at which the oracle is computed (the last 50 of 200, every 25th).
ORACLE_EPOCHS = (150, 175, 200)


def oracle(runs: int, levels=(0.05, 0.5, 1.0, 2.0)) -> None:
    """The default filter, the PCRB, each run's own bound and the batch oracle (:mod:`batch_map`: the MMSE
    estimate over the range offset, Laplace-marginalised, every report up to then) on the same truths
    (seeds 30000 + r), at reports :data:`ORACLE_EPOCHS`."""
    from core.simulation.tracking import against_bound
    from tests.core.tracking.batch_map import offset_marginal

    at = list(ORACLE_EPOCHS)
    print(f"\nOracle: {runs} runs, seed 30000, reports {at}; RMS of the position error (m) and ratios to the PCRB; "
          "own bound = RMS over runs of each run's bound (the recursion on that truth alone)")
    for q in levels:
        for known in (True, False):
            config = paper_config("joint_ukf", known, accel_sigma_mps2=q)
            scenario = paper_001_scenario(accel_sigma_mps2=q)
            result = against_bound(config, scenario, runs, 30000)
            pcrb = float(np.sqrt(np.mean(result.bound_m2[at])))
            filter_rmse = float(np.sqrt(np.mean(result.squared_errors_m2[:, at])))
            squared, nees = [], []
            for r in range(runs):
                track = simulate_emitter(scenario, np.random.default_rng(30000 + r))
                for k in at:
                    mean, cov, _ = offset_marginal(track, config, k)
                    error = mean[:3] - track.states_enu[k, :3]
                    squared.append(error @ error)
                    nees.append(error @ np.linalg.solve(cov[:3, :3], error))
            own_bound = float(np.sqrt(np.mean(result.own_bound_m2[:, at])))
            oracle_rmse = float(np.sqrt(np.mean(squared)))
            print(f"q={q:<5} {'known  ' if known else 'unknown'}  PCRB {pcrb:7.0f}  own bound {own_bound:7.0f}  "
                  f"oracle {oracle_rmse:7.0f} (NEES {np.mean(nees):4.2f})  filter {filter_rmse:7.0f} (NEES "
                  f"{np.nanmean(result.nees[:, at]):4.2f})   ratios to the PCRB: own bound {own_bound / pcrb:5.2f}  "
                  f"oracle {oracle_rmse / pcrb:5.2f}  filter {filter_rmse / pcrb:5.2f}", flush=True)


if __name__ == "__main__":
    if len(sys.argv) > 1 and sys.argv[1] == "oracle":
        oracle(int(sys.argv[2]) if len(sys.argv) > 2 else 50,
               tuple(float(q) for q in sys.argv[3].split(",")) if len(sys.argv) > 3 else (0.05, 0.5, 1.0, 2.0))
        sys.exit(0)
    if len(sys.argv) > 1 and sys.argv[1] == "sweep":
        sweep(int(sys.argv[2]) if len(sys.argv) > 2 else 50)
        sys.exit(0)
    if len(sys.argv) > 1 and sys.argv[1] == "bound":
        bound(int(sys.argv[2]) if len(sys.argv) > 2 else 200)
        switching(int(sys.argv[3]) if len(sys.argv) > 3 else 40)
        sys.exit()
    n_runs = int(sys.argv[1]) if len(sys.argv) > 1 else 100
    accuracy(n_runs)
    consistency(n_runs)
    prior_sensitivity(n_runs)
    speed()
