"""The Cramer-Rao bound, ML efficiency and consistency by Monte Carlo, and the error summaries.

Statistical checks use fixed seeds and compare with the CRLB or with
chi-square / binomial intervals computed here, never with numbers taken
from an earlier run. Print the Monte Carlo figures with::

    PYTHONPATH=. .venv/bin/python -m tests.core.test_crlb_accuracy
"""

from __future__ import annotations

import numpy as np
import pymap3d
import pytest
from scipy.stats import chi2, norm

from core.error_summary import error_summary
from core.crlb import information_at
from core.estimators import SolveOptions, solve_batch
from core.measurements import SPEED_OF_LIGHT_MPS
from core.problem.build import Bearing, TimeOfArrival, build_problem
from core.problem.frame import GeodeticPoint
from core.parallel import chunk_seeds, chunk_slices
from core.simulation.measurements import DRAW_BLOCK_TRIALS, evaluate, measure

d2r = np.deg2rad
ONE_DEG = d2r(1.0)

# Four receivers at the corners of a ~28 x 28 km box, a target at 8 km in the middle.
STATIONS_DEG = {"n1": (34.60, 108.80, 400.0), "n2": (34.60, 109.10, 600.0),
                "n3": (34.35, 108.80, 500.0), "n4": (34.35, 109.10, 450.0)}
TARGET_DEG = (34.50, 108.95, 8000.0)
TRIALS = 2000
SEED = 20240602


def scenario():
    stations = [(k, GeodeticPoint(d2r(a), d2r(b), h)) for k, (a, b, h) in STATIONS_DEG.items()]
    # Values are placeholders: every trial measures the target afresh.
    problem = build_problem(stations, [Bearing(k, 0.0, 0.0, ONE_DEG, ONE_DEG) for k in STATIONS_DEG])
    target = problem.frame.from_geodetic(d2r(TARGET_DEG[0]), d2r(TARGET_DEG[1]), TARGET_DEG[2])
    return problem, target


def independent_crlb_ecef(sigmas=(ONE_DEG, ONE_DEG), toa_sigma_s=None, emission_known=False):
    """CRLB in ECEF from pymap3d's az/el/range, differentiated numerically at the true target."""
    x0 = np.array(pymap3d.geodetic2ecef(*TARGET_DEG))
    step = 0.5  # m: central differences, truncation ~(0.5 m / 20 km)^2 relative

    def values(x):
        out = []
        for lat, lon, h in STATIONS_DEG.values():
            az, el, r = pymap3d.ecef2aer(*x, lat, lon, h)
            if toa_sigma_s is None:
                out += [d2r(az), d2r(el)]
            else:
                out.append(r)
        return np.array(out)

    def derivative(e):
        diff = values(x0 + step * e) - values(x0 - step * e)
        return np.angle(np.exp(1j * diff)) / (2 * step) if toa_sigma_s is None else diff / (2 * step)

    jac = np.stack([derivative(e) for e in np.eye(3)], axis=-1)
    if toa_sigma_s is None:
        weights = np.tile(1.0 / np.square(sigmas), len(STATIONS_DEG))
    else:
        if not emission_known:
            jac = np.column_stack([jac, np.ones(len(jac))])  # emission offset, marginalised
        weights = np.full(len(jac), 1.0 / (toa_sigma_s * SPEED_OF_LIGHT_MPS) ** 2)
    return np.linalg.inv(jac.T @ (jac * weights[:, None]))[:3, :3]


def test_crlb_matches_an_independent_computation_from_pymap3d():
    problem, target = scenario()
    bound = information_at(problem, target)
    assert bound.observable[0]
    expected = independent_crlb_ecef()
    # 1e-4 of the trace: ~0.5 m^2 on a bound of ~5e4 m^2 per axis (numerical differentiation is far better).
    np.testing.assert_allclose(problem.frame.covariance_to_ecef(bound.covariance_enu_m2[0]), expected,
                               rtol=0, atol=1e-4 * np.trace(expected))


def test_toa_crlb_marginalises_the_emission_time():
    stations = [(k, GeodeticPoint(d2r(a), d2r(b), h)) for k, (a, b, h) in STATIONS_DEG.items()]
    problem = build_problem(stations, [TimeOfArrival(k, 12.0, 1e-8) for k in STATIONS_DEG])
    target = problem.frame.from_geodetic(d2r(TARGET_DEG[0]), d2r(TARGET_DEG[1]), TARGET_DEG[2])
    expected = independent_crlb_ecef(toa_sigma_s=1e-8)
    got = problem.frame.covariance_to_ecef(information_at(problem, target).covariance_enu_m2[0])
    np.testing.assert_allclose(got, expected, rtol=0, atol=1e-4 * np.trace(expected))  # 1e-4 of the trace
    # The teeth: forgetting the unknown emission time would give a much smaller bound.
    known_time = independent_crlb_ecef(toa_sigma_s=1e-8, emission_known=True)
    assert np.trace(known_time) < 0.5 * np.trace(got)


def monte_carlo(trials=TRIALS, seed=SEED):
    """ML on noisy draws of the scenario: the figures the test checks (and the module prints)."""
    problem, target = scenario()
    rng = np.random.default_rng(seed)
    noisy = [measure(problem, target, rng) for _ in range(trials)]
    fixes = solve_batch(noisy, "ml")
    errors = np.array([f.position_enu_m - target for f in fixes])
    nees = np.array([e @ np.linalg.solve(f.covariance_enu_m2, e) for e, f in zip(errors, fixes)])
    crlb = information_at(problem, target).covariance_enu_m2[0]
    dof = fixes[0].dof
    return {
        "trials": trials,
        "failures": sum(not f.converged for f in fixes),
        "rmse_m": float(np.sqrt(np.mean(np.sum(errors**2, axis=1)))),
        "crlb_rmse_m": float(np.sqrt(np.trace(crlb))),
        "mean_nees": float(nees.mean()),
        "nees_interval": chi2.ppf([0.005, 0.995], 3 * trials) / trials,
        "chi2_per_dof": float(np.mean([f.chi2 for f in fixes]) / dof),
        "chi2_interval": chi2.ppf([0.005, 0.995], dof * trials) / (dof * trials),
        "dof": dof,
        "bias_m": errors.mean(axis=0),
        "bias_sd_m": np.sqrt(np.diag(crlb) / trials),
    }


@pytest.fixture(scope="module")
def figures():
    return monte_carlo()


def test_ml_rmse_reaches_the_crlb(figures):
    print(format_figures(figures))
    assert figures["failures"] == 0
    ratio = figures["rmse_m"] / figures["crlb_rmse_m"]
    # 2000 trials: the RMSE estimate itself scatters by ~2 %; 10 % is the efficiency claim.
    assert 0.9 < ratio < 1.1


def test_ml_nees_with_its_own_covariance_is_chi_square(figures):
    low, high = figures["nees_interval"]
    assert low < figures["mean_nees"] < high


def test_fit_chi2_per_dof_is_chi_square(figures):
    assert figures["dof"] == 5  # 8 angles, 3 unknowns
    low, high = figures["chi2_interval"]
    assert low < figures["chi2_per_dof"] < high


def test_ml_is_unbiased_within_sampling_error(figures):
    # 99.99 % per axis (|z| < 3.9): nonlinearity bias at 1 deg is far below the sampling error here.
    assert np.all(np.abs(figures["bias_m"]) < 3.9 * figures["bias_sd_m"])


def test_evaluate_reports_what_an_independent_loop_measures():
    """core.simulation.evaluate (behind /v1/evaluations) against the same draws solved here."""
    problem, target = scenario()
    trials = 500
    report = evaluate(problem, target, ["ml"], trials, 99)["ml"]
    clean = measure(problem, target).values
    blocks = chunk_slices(trials, DRAW_BLOCK_TRIALS)
    draws = np.concatenate([clean + np.random.default_rng(seed).standard_normal((b.stop - b.start, clean.size))
                            * problem.sigmas for seed, b in zip(chunk_seeds(99, len(blocks)), blocks)])
    fixes = solve_batch([problem.with_values(v) for v in draws], "ml")
    errors = np.array([f.position_enu_m - target for f in fixes])
    nees = [e @ np.linalg.solve(f.covariance_enu_m2, e) for e, f in zip(errors, fixes)]
    assert report.failures == 0
    assert report.rmse_m == pytest.approx(np.sqrt(np.mean(np.sum(errors**2, axis=1))), rel=1e-9)
    assert report.nees_mean == pytest.approx(np.mean(nees), rel=1e-6)
    assert report.crlb_rmse_m == pytest.approx(np.sqrt(np.trace(information_at(problem, target).covariance_enu_m2[0])),
                                               rel=1e-12)
    assert report.efficiency == pytest.approx((report.rmse_m / report.crlb_rmse_m) ** 2, rel=1e-12)


def format_figures(f):
    return (f"ML Monte Carlo, {f['trials']} trials, seed {SEED}: RMSE {f['rmse_m']:.1f} m, "
            f"sqrt(trace CRLB) {f['crlb_rmse_m']:.1f} m, ratio {f['rmse_m'] / f['crlb_rmse_m']:.4f}; "
            f"mean NEES {f['mean_nees']:.3f} in [{f['nees_interval'][0]:.3f}, {f['nees_interval'][1]:.3f}]; "
            f"chi2/dof {f['chi2_per_dof']:.4f} in [{f['chi2_interval'][0]:.4f}, {f['chi2_interval'][1]:.4f}]")


# --- error summaries ------------------------------------------------------------

SAMPLES = 1_000_000
# Binomial 99.999 % band for the fraction of samples inside a true 50 % region.
INSIDE_BAND = norm.ppf(1 - 0.5e-5) * np.sqrt(0.25 / SAMPLES)


def rotation_about_up(angle_rad):
    c, s = np.cos(angle_rad), np.sin(angle_rad)
    return np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])


COVARIANCES = {
    "round": np.diag([25.0, 25.0, 25.0]),
    "elongated-100-to-1": rotation_about_up(0.4) @ np.diag([100.0**2, 1.0, 50.0**2]) @ rotation_about_up(0.4).T,
    "correlated": np.array([[400.0, 300.0, 50.0], [300.0, 900.0, -100.0], [50.0, -100.0, 250.0]]),
}


@pytest.mark.parametrize("name", COVARIANCES)
def test_cep50_and_sep50_against_monte_carlo_medians(name):
    cov = COVARIANCES[name]
    summary = error_summary(cov)
    samples = np.random.default_rng(31).multivariate_normal(np.zeros(3), cov, SAMPLES)
    horizontal = np.linalg.norm(samples[:, :2], axis=1)
    spherical = np.linalg.norm(samples, axis=1)
    cep, sep = float(summary.cep50_m[0]), float(summary.sep50_m[0])
    # Distribution-free: the fraction inside the reported radius is 1/2 within binomial scatter.
    assert abs(np.mean(horizontal <= cep) - 0.5) < INSIDE_BAND
    assert abs(np.mean(spherical <= sep) - 0.5) < INSIDE_BAND
    # The sample median's relative standard error is <= 1.2/sqrt(n) = 0.12 % for these shapes.
    assert cep == pytest.approx(np.median(horizontal), rel=0.01)
    assert sep == pytest.approx(np.median(spherical), rel=0.01)


def test_cep50_and_sep50_closed_forms():
    sigma = 5.0
    summary = error_summary(np.diag([sigma**2] * 3))
    assert summary.cep50_m[0] == pytest.approx(sigma * np.sqrt(2 * np.log(2)), rel=1e-9)
    assert summary.sep50_m[0] == pytest.approx(sigma * np.sqrt(chi2.ppf(0.5, 3)), rel=1e-9)
    # A line: the 50 % radius of N(0, s^2) along one axis is the half-normal median.
    # 1e-3 relative is a millimetre per metre of CEP, far below any use of the figure.
    line = error_summary(np.diag([0.0, sigma**2, 0.0]))
    assert line.cep50_m[0] == pytest.approx(sigma * norm.ppf(0.75), rel=1e-3)
    assert line.sep50_m[0] == pytest.approx(sigma * norm.ppf(0.75), rel=1e-3)


def test_ellipse95_of_a_rotated_covariance():
    a, b, heading = 300.0, 40.0, d2r(30.0)  # major axis 30 deg clockwise from north
    major = np.array([np.sin(heading), np.cos(heading)])
    minor = np.array([np.cos(heading), -np.sin(heading)])
    cov = np.zeros((3, 3))
    cov[:2, :2] = a**2 * np.outer(major, major) + b**2 * np.outer(minor, minor)
    cov[2, 2] = 100.0
    summary = error_summary(cov)
    k = np.sqrt(chi2.ppf(0.95, 2))
    assert summary.ellipse_semi_major_m[0] == pytest.approx(k * a, rel=1e-12)
    assert summary.ellipse_semi_minor_m[0] == pytest.approx(k * b, rel=1e-12)
    assert summary.ellipse_orientation_rad[0] == pytest.approx(heading, abs=1e-12)
    assert summary.vertical_sigma_m[0] == pytest.approx(10.0, rel=1e-12)
    assert summary.gdop_m[0] == pytest.approx(np.sqrt(a**2 + b**2 + 100.0), rel=1e-12)
    # The ellipse as reported holds 95 % of samples.
    samples = np.random.default_rng(5).multivariate_normal(np.zeros(2), cov[:2, :2], 200_000)
    o = summary.ellipse_orientation_rad[0]
    along = samples @ [np.sin(o), np.cos(o)]
    across = samples @ [np.cos(o), -np.sin(o)]
    inside = (along / summary.ellipse_semi_major_m[0]) ** 2 + (across / summary.ellipse_semi_minor_m[0]) ** 2 <= 1
    assert abs(inside.mean() - 0.95) < 5 * np.sqrt(0.95 * 0.05 / 200_000)  # 5 binomial sigma


@pytest.mark.parametrize("cov_en, expected_deg", [
    ([[1.0, 0.9], [0.9, 1.0]], 45.0),  # along north-east
    ([[1.0, -0.9], [-0.9, 1.0]], 135.0),  # along north-west / south-east
    ([[1.0, 0.0], [0.0, 9.0]], 0.0),  # north
    ([[9.0, 0.0], [0.0, 1.0]], 90.0),  # east
])
def test_ellipse_orientation_is_clockwise_from_north(cov_en, expected_deg):
    cov = np.eye(3)
    cov[:2, :2] = cov_en
    got = np.rad2deg(error_summary(cov).ellipse_orientation_rad[0])
    assert 0.0 <= got < 180.0
    assert got == pytest.approx(expected_deg, abs=1e-9)


def test_error_summary_is_batched():
    covs = np.stack(list(COVARIANCES.values()))
    batch = error_summary(covs)
    assert batch.cep50_m.shape == (3,)
    for i, cov in enumerate(covs):
        assert batch.cep50_m[i] == pytest.approx(error_summary(cov).cep50_m[0], rel=1e-12)
        assert batch.sep50_m[i] == pytest.approx(error_summary(cov).sep50_m[0], rel=1e-12)


if __name__ == "__main__":
    print(format_figures(monte_carlo()))
