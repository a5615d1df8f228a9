"""Paper 004 (Taylor-series WLS with bearing-error estimation) on its own scenario.

One sensor moving along y = -0.2 x + 14 km, x from 15 to 30 km every 0.1 km
(151 bearings, each sensor position a station of a flat local frame), target
at (30, 35) km, the same sigma on every bearing.

Theory behind the bars:

- ``taylor_wls`` is Gauss-Newton on the ML cost: its RMSE should be the CRLB's
  ``sqrt(trace)``; 500 trials put the Monte Carlo RMSE within about 3 % (1
  sigma) of its expectation, so the bar is 10 %.
- The estimated bearing errors are ``Z - A dX``; to first order their error
  is the projection of the noise on the 2-D column space of ``A``, with mean
  square ``sigma^2 * 2 / N`` per bearing. The pooled RMS over trials should be
  ``sigma sqrt(2/N)`` (within 10 %). No unbiased position gives the
  conventional estimates (measured minus the fix's azimuth) of TLS and CTLS a
  smaller error, which is the bar for those (less 3.5 Monte Carlo sigmas:
  the RMS of T trials scatters by at most ``1 / sqrt(2 T)``).
- The estimated sigma uses N - 2 degrees of freedom: its square is unbiased,
  and one estimate scatters about ``1 / sqrt(2 (N - 2))`` = 5.8 %; the mean
  over trials must be within 2 % and the rms relative error below 10 %.
"""

from __future__ import annotations

import numpy as np
import pytest

from core.crlb import information_at
from core.estimators import SolveOptions, solve
from core.measurements import Kind

from core.simulation import scenarios as sc

SIGMAS_DEG = [1.0, 3.0, 5.0, 10.0]
BEARINGS = 151
TRIALS = 500
BASELINE_TRIALS = {"tls": 200, "ctls newton": 200, "ctls projected": 60}


def draws(scene: sc.Scene, trials: int, seed: int):
    rng = np.random.default_rng(seed)
    truth = scene.true_values()
    for _ in range(trials):
        measurements = scene.measurements(rng)
        yield measurements, np.array([m.azimuth_rad for m in measurements]) - truth


def crlb_rmse_m(sigma_deg: float) -> float:
    scene = sc.paper_004(sigma_deg)
    problem = scene.template()
    return float(np.sqrt(np.trace(information_at(problem, scene.target_enu_m(problem)).covariance_enu_m2[0])))


def first_order_error_rms_rad(sigma_deg: float) -> float:
    return np.deg2rad(sigma_deg) * np.sqrt(2.0 / BEARINGS)


@pytest.mark.slow
@pytest.mark.parametrize("sigma_deg", SIGMAS_DEG)
def test_taylor_wls_is_efficient_and_estimates_errors_and_sigma(sigma_deg):
    scene = sc.paper_004(sigma_deg, sigma_known=False)
    target = scene.target_enu_m()
    errors_m, sigma_ratio, error_squares = [], [], []
    for measurements, noise in draws(scene, TRIALS, seed=4000 + int(sigma_deg)):
        fix = solve(sc.build(scene, measurements), "taylor_wls")
        assert fix.converged
        assert any(w.code == "sigma_estimated" for w in fix.warnings)
        assert fix.estimated_bearing_errors_rad.shape == (BEARINGS,)
        errors_m.append(fix.position_enu_m - target)
        sigma_ratio.append(fix.details["estimated_sigma_azimuth_rad"] / np.deg2rad(sigma_deg))
        error_squares.append(np.mean((fix.estimated_bearing_errors_rad - noise) ** 2))
    rmse = np.sqrt(np.mean(np.sum(np.square(errors_m), axis=1)))
    bound = crlb_rmse_m(sigma_deg)
    error_rms = np.sqrt(np.mean(error_squares))
    sigma_ratio = np.array(sigma_ratio)
    print(f"sigma {sigma_deg:4.1f} deg: rmse/crlb {rmse / bound:.3f}, bearing-error rms / first order "
          f"{error_rms / first_order_error_rms_rad(sigma_deg):.3f}, sigma_hat/sigma mean {sigma_ratio.mean():.4f} "
          f"rms {np.sqrt(np.mean((sigma_ratio - 1) ** 2)):.4f}")
    assert abs(rmse / bound - 1) < 0.10
    assert abs(error_rms / first_order_error_rms_rad(sigma_deg) - 1) < 0.10
    assert abs(sigma_ratio.mean() - 1) < 0.02
    assert np.sqrt(np.mean((sigma_ratio - 1) ** 2)) < 0.10


@pytest.mark.slow
@pytest.mark.parametrize("sigma_deg", SIGMAS_DEG)
def test_bearing_error_estimates_beside_tls_and_ctls(sigma_deg):
    """Pooled RMS error of the estimated bearing errors, per method, on the same draws (printed)."""
    scene = sc.paper_004(sigma_deg)
    methods = {"taylor_wls": ("taylor_wls", None), "tls": ("tls", None),
               "ctls newton": ("ctls", "newton"), "ctls projected": ("ctls", "projected")}
    trials = max(BASELINE_TRIALS.values())
    squares = {label: [] for label in methods}
    for k, (measurements, noise) in enumerate(draws(scene, trials, seed=4100 + int(sigma_deg))):
        problem = sc.build(scene, measurements)
        for label, (name, variant) in methods.items():
            if k >= BASELINE_TRIALS.get(label, trials):
                continue
            fix = solve(problem, name, SolveOptions(variant=variant))
            estimate = fix.estimated_bearing_errors_rad
            if estimate is None:
                estimate = fix.residuals[problem.kinds == Kind.AZIMUTH]
            squares[label].append(np.mean((estimate - noise) ** 2))
    reference = first_order_error_rms_rad(sigma_deg)
    ratios = {label: np.sqrt(np.mean(values)) / reference for label, values in squares.items()}
    print(f"sigma {sigma_deg:4.1f} deg, bearing-error rms / (sigma sqrt(2/N)): "
          + ", ".join(f"{label} {ratio:.3f} ({len(squares[label])} trials)" for label, ratio in ratios.items()))
    for label, ratio in ratios.items():
        assert ratio > 1 - 3.5 / np.sqrt(2 * len(squares[label])), label
