"""Simulated measurements for a known target, and Monte Carlo evaluation of estimators."""

from __future__ import annotations

from dataclasses import dataclass, replace

import numpy as np

from core.batch import ProblemBatch
from core.errors import LocalizationError, UnobservableGeometry
from core.measurements import predict
from core.problem import Problem

NOISE_KINDS = ("gaussian", "uniform")


def true_values(problem: Problem, target_enu_m) -> np.ndarray:
    """Noise-free values ``(M,)`` in problem units for a target (TOA emitted at the reference time).

    Parameters
    ----------
    problem : Problem
        Supplies stations, kinds and the frame; its values are ignored.
    target_enu_m : ndarray, shape (3,)
    """
    s = problem.station_index
    predicted, _ = predict(np.asarray(target_enu_m, dtype=float)[None], np.zeros(1),
                           problem.stations_enu_m[s][None], problem.station_rotations[s][None], problem.kinds[None])
    return predicted[0] / problem.unit_scale()


def trial_batch(problem: Problem, values) -> ProblemBatch:
    """One geometry under T sets of measured values, as a batch of T problems (a Monte Carlo in one call).

    Parameters
    ----------
    problem : Problem
        Supplies everything but the values.
    values : ndarray, shape (T, M) or (M,)
        Problem units (rad, m, s after the TOA reference).
    """
    values = np.atleast_2d(np.asarray(values, dtype=float))
    one = ProblemBatch.from_problems([problem])
    return replace(one.take(np.zeros(values.shape[0], dtype=np.intp)), values=values)


def measure(problem: Problem, target_enu_m, rng: np.random.Generator | None = None,
            noise: str = "gaussian") -> Problem:
    """The problem with values measured from a target, noisy when ``rng`` is given.

    Parameters
    ----------
    problem : Problem
    target_enu_m : ndarray, shape (3,)
    rng : numpy.random.Generator, optional
        None gives noise-free values.
    noise : {"gaussian", "uniform"}
        Uniform noise is zero-mean with the stated sigma (half-width sigma sqrt(3)).
    """
    values = true_values(problem, target_enu_m)
    if rng is not None:
        values = values + draw_noise(rng, problem.sigmas, noise)
    return problem.with_values(values)


def draw_noise(rng: np.random.Generator, sigmas, noise: str = "gaussian", size=None) -> np.ndarray:
    """Zero-mean noise with standard deviations ``sigmas`` (shape ``size + sigmas.shape``)."""
    sigmas = np.asarray(sigmas, dtype=float)
    shape = sigmas.shape if size is None else tuple(np.atleast_1d(size)) + sigmas.shape
    if noise == "gaussian":
        return rng.standard_normal(shape) * sigmas
    if noise == "uniform":
        return rng.uniform(-1.0, 1.0, shape) * np.sqrt(3.0) * sigmas
    raise ValueError(f"unknown noise {noise!r}")


@dataclass(frozen=True)
class MethodAccuracy:
    """Monte Carlo accuracy of one method against the bound.

    Attributes
    ----------
    rmse_m : float
        sqrt(mean |error|^2) over successful trials.
    rmse_enu_m, bias_enu_m : ndarray, shape (3,)
    crlb_rmse_m : float
        sqrt(trace(CRLB)) at the true target.
    efficiency : float
        ``rmse^2 / trace(CRLB)`` (1 is efficient).
    nees_mean : float
        Mean of ``e^T C^-1 e`` with the method's own covariance (3 if honest).
    failures : int
        Trials where the method gave no fix.
    errors_enu_m : ndarray, shape (T, 3)
        Per-trial errors of successful trials.
    """

    rmse_m: float
    rmse_enu_m: np.ndarray
    bias_enu_m: np.ndarray
    crlb_rmse_m: float
    efficiency: float
    nees_mean: float
    failures: int
    errors_enu_m: np.ndarray


def evaluate(problem: Problem, target_enu_m, methods, trials: int, rng: np.random.Generator,
             noise: str = "gaussian", options=None) -> dict[str, MethodAccuracy]:
    """Monte Carlo RMSE, bias, efficiency and NEES of methods on one scenario.

    Every method sees the same noisy draws. ML-family methods run batched.

    Parameters
    ----------
    problem : Problem
        The scenario (values ignored).
    target_enu_m : ndarray, shape (3,)
    methods : sequence of str
    trials : int
    rng : numpy.random.Generator
    noise : {"gaussian", "uniform"}
    options : SolveOptions, optional
    """
    from core.crlb import information_at
    from core.estimators import SolveOptions, solve_batch

    options = options or SolveOptions()
    target = np.asarray(target_enu_m, dtype=float)
    clean = true_values(problem, target)
    draws = clean + draw_noise(rng, problem.sigmas, noise, size=trials)
    noisy = [problem.with_values(v) for v in draws]
    information = information_at(problem, target)
    if not information.observable[0]:
        raise UnobservableGeometry("the scenario's sensors do not determine the target (singular information)")
    bound = information.covariance_enu_m2[0]
    out = {}
    for method in methods:
        results = solve_batch(noisy, method, options)
        fixes = [r for r in results if not isinstance(r, LocalizationError)]
        errors = np.array([f.position_enu_m - target for f in fixes]).reshape(-1, 3)
        nees = [_nees(e, f.covariance_enu_m2) for e, f in zip(errors, fixes)]
        out[method] = MethodAccuracy(
            rmse_m=float(np.sqrt(np.mean(np.sum(errors**2, axis=1)))) if len(fixes) else float("nan"),
            rmse_enu_m=np.sqrt(np.mean(errors**2, axis=0)) if len(fixes) else np.full(3, np.nan),
            bias_enu_m=errors.mean(axis=0) if len(fixes) else np.full(3, np.nan),
            crlb_rmse_m=float(np.sqrt(np.trace(bound))),
            efficiency=float(np.mean(np.sum(errors**2, axis=1)) / np.trace(bound)) if len(fixes) else float("nan"),
            nees_mean=float(np.mean(nees)) if nees else float("nan"),
            failures=trials - len(fixes),
            errors_enu_m=errors,
        )
    return out


def _nees(error_enu_m, covariance_enu_m2) -> float:
    """``e^T C^+ e`` (pseudo-inverse: a constrained fix has a rank-2 covariance)."""
    return float(error_enu_m @ np.linalg.pinv(covariance_enu_m2, rcond=1e-12, hermitian=True) @ error_enu_m)
