"""Measured accuracy of the bearing-only estimators against the Cramer-Rao bound.

Prints one table, with fixed seeds, of RMSE, sqrt(trace CRLB) at the true
target, their ratio, the mean NEES with each method's own covariance (3 for
an honest 3D covariance, 2 with a known altitude) and the number of trials
without a fix, per method and scenario:

1. Paper 000 (EOVE): two stations on the target's meridian, 2 deg on both
   angles; N = 2, the first station moved to 108.8E giving azimuth only, and
   N = 4 as 2 stations x 2 looks (the paper's "each point takes 2
   measurements").
2. The generic 4-station scene with 1 deg on both angles, and its
   azimuth-only variant with the target altitude known.
3. Paper 004 (Taylor-series WLS): 151 bearings from a sensor on
   y = -0.2 x + 14 km, target (30, 35) km, sigma 1/3/5/10 deg. ``taylor_wls``
   runs without sigmas (it estimates them); the last columns give the RMS
   error of each method's estimated bearing errors against the true errors,
   over ``sigma sqrt(2/N)`` (the first-order value for an efficient fix), and
   taylor_wls's mean estimated sigma over the true one.

Usage: ``.venv/bin/python scripts/accuracy_bearing_only.py [--trials N] [--trials-004 N]``.
"""

from __future__ import annotations

import argparse
import sys
import time
from collections import Counter
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from core.crlb import information_at  # noqa: E402
from core.errors import LocalizationError  # noqa: E402
from core.estimators import SolveOptions, solve  # noqa: E402
from core.measurements import Kind  # noqa: E402
from core.simulation.measurements import evaluate  # noqa: E402
from core.simulation import scenarios as sc  # noqa: E402

HEADER = (f"{'scenario':42s} {'method':16s} {'trials':>6s} {'rmse_m':>10s} {'crlb_m':>10s} {'ratio':>7s} "
          f"{'nees':>6s} {'dof':>3s} {'fail':>5s}  notes")


def row(scenario, method, trials, rmse, crlb, nees, dof, failures, notes=""):
    ratio = rmse / crlb if np.isfinite(rmse) else float("nan")
    return (f"{scenario:42s} {method:16s} {trials:6d} {rmse:10.1f} {crlb:10.1f} {ratio:7.3f} "
            f"{nees:6.2f} {dof:3d} {failures:5d}  {notes}")


def failure_note(scene, name, variant):
    try:
        solve(scene.problem(), name, SolveOptions(variant=variant))
    except LocalizationError as error:
        return f"noise-free: {type(error).__name__}"
    return ""


def evaluated(scene, methods, trials, seed):
    """Rows for methods run by core.simulation.measurements.evaluate on one scene (same draws for all)."""
    problem = scene.template()
    target = scene.target_enu_m(problem)
    dof = 2 if scene.altitude_m is not None else 3
    lines = []
    for label, (name, variant) in methods.items():
        result = evaluate(problem, target, [name], trials, seed,
                          options=SolveOptions(variant=variant))[name]
        note = failure_note(scene, name, variant) if result.failures else ""
        lines.append(row(scene.name, label, trials, result.rmse_m, result.crlb_rmse_m, result.nees_mean, dof,
                         result.failures, note))
    return lines


def paper_004_rows(sigma_deg, methods, trials, seed):
    """Rows for paper 004 at one sigma: a loop of our own, since taylor_wls runs without sigmas."""
    known = sc.paper_004(sigma_deg)
    unknown = sc.paper_004(sigma_deg, sigma_known=False)
    problem = known.template()
    target = known.target_enu_m(problem)
    crlb = float(np.sqrt(np.trace(information_at(problem, target).covariance_enu_m2[0])))
    truth = known.true_values()
    first_order = np.deg2rad(sigma_deg) * np.sqrt(2.0 / truth.size)
    rng = np.random.default_rng(seed)
    noisy = [known.measurements(rng) for _ in range(trials)]
    lines = []
    for label, (name, variant) in methods.items():
        scene = unknown if name == "taylor_wls" else known
        errors, nees, squares, sigmas, failures = [], [], [], [], Counter()
        for measurements in noisy:
            p = sc.build(known, measurements)
            if scene is unknown:
                p = p.with_sigmas(np.full(p.n_measurements, np.nan))
            try:
                fix = solve(p, name, SolveOptions(variant=variant))
            except LocalizationError as error:
                failures[type(error).__name__] += 1
                continue
            e = fix.position_enu_m - target
            errors.append(e)
            nees.append(e @ np.linalg.pinv(fix.covariance_enu_m2, rcond=1e-12, hermitian=True) @ e)
            estimate = fix.estimated_bearing_errors_rad
            if estimate is None:
                estimate = fix.residuals[p.kinds == Kind.AZIMUTH]
            squares.append(np.mean((estimate - (p.values - truth)) ** 2))
            if "estimated_sigma_azimuth_rad" in fix.details:
                sigmas.append(fix.details["estimated_sigma_azimuth_rad"])
        rmse = float(np.sqrt(np.mean(np.sum(np.square(errors), axis=1)))) if errors else float("nan")
        notes = f"bearing-error rms / (sigma sqrt(2/N)) {np.sqrt(np.mean(squares)) / first_order:.3f}" \
            if squares else ""
        if sigmas:
            notes += f"; sigma_hat/sigma {np.mean(sigmas) / np.deg2rad(sigma_deg):.4f}"
        if failures:
            notes += "; " + ", ".join(f"{k} x{v}" for k, v in failures.items())
        lines.append(row(known.name, label, trials, rmse, crlb, float(np.mean(nees)) if nees else float("nan"),
                         2, sum(failures.values()), notes))
    return lines


def main(argv=None):
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--trials", type=int, default=1000, help="trials per paper-000 and generic scenario")
    parser.add_argument("--trials-004", type=int, default=500, help="trials per paper-004 sigma")
    args = parser.parse_args(argv)
    start = time.perf_counter()

    closed_3d = {"eove": ("eove", None), "weighted_eove": ("weighted_eove", None), "ove": ("ove", None),
                 "ple3d": ("ple3d", None), "ws3d": ("ws3d", None), "los_intersection": ("los_intersection", None),
                 "taylor_wls": ("taylor_wls", None), "ml": ("ml", None)}
    azimuth_only = {"taylor_wls": ("taylor_wls", None), "tls": ("tls", None), "ctls newton": ("ctls", "newton"),
                    "ctls projected": ("ctls", "projected"), "eove": ("eove", None),
                    "weighted_eove": ("weighted_eove", None), "ple3d": ("ple3d", None), "ws3d": ("ws3d", None),
                    "ml": ("ml", None)}
    print(HEADER)
    print("-" * len(HEADER))
    for seed, scene in enumerate([sc.paper_000(), sc.paper_000(moved_azimuth_only=True), sc.paper_000(looks=2),
                                  sc.generic_3d(1.0)], start=1):
        for line in evaluated(scene, closed_3d, args.trials, seed):
            print(line, flush=True)
    for line in evaluated(sc.generic_azimuth_only(1.0), azimuth_only, args.trials, 5):
        print(line, flush=True)
    for sigma_deg in (1.0, 3.0, 5.0, 10.0):
        for line in paper_004_rows(sigma_deg, azimuth_only, args.trials_004, 40 + int(sigma_deg)):
            print(line, flush=True)
    print(f"\n{time.perf_counter() - start:.0f} s")


if __name__ == "__main__":
    main()
