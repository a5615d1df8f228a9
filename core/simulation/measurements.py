"""Simulated measurements for a known target, and Monte Carlo evaluation of estimators."""

from __future__ import annotations

from dataclasses import dataclass, replace
from typing import Callable

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


class EvaluationStopped(Exception):
    """An evaluation stopped between chunks because its ``should_stop`` said so (deadline, cancellation)."""


def evaluate(problem: Problem, target_enu_m, methods, trials: int, rng: np.random.Generator,
             noise: str = "gaussian", options=None, should_stop: Callable[[], bool] | None = None,
             chunk_trials: int = 256) -> dict[str, MethodAccuracy]:
    """Monte Carlo RMSE, bias, efficiency and NEES of methods on one scenario.

    Every method sees the same noisy draws. ML-family methods run batched.
    Trials run in chunks; between chunks (and between methods within one)
    ``should_stop`` is asked, so a long evaluation can be abandoned within
    one chunk of one method. The draws are those of one ``trials``-row draw
    whatever the chunking (numpy's generators fill rows in order).

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
    should_stop : callable returning bool, optional
        True = stop now (raises :class:`EvaluationStopped`).
    chunk_trials : int
        Trials per chunk.

    Raises
    ------
    UnobservableGeometry
        When the sensors do not determine the target.
    EvaluationStopped
        When ``should_stop`` returned True.
    """
    from core.crlb import information_at
    from core.estimators import SolveOptions, solve_batch

    options = options or SolveOptions()
    target = np.asarray(target_enu_m, dtype=float)
    information = information_at(problem, target)
    if not information.observable[0]:
        raise UnobservableGeometry("the scenario's sensors do not determine the target (singular information)")
    bound = information.covariance_enu_m2[0]
    clean = true_values(problem, target)
    errors_by_method: dict[str, list[np.ndarray]] = {method: [] for method in methods}
    nees_by_method: dict[str, list[float]] = {method: [] for method in methods}

    def check() -> None:
        if should_stop is not None and should_stop():
            raise EvaluationStopped("the evaluation was stopped")

    for start in range(0, trials, max(1, chunk_trials)):
        size = min(max(1, chunk_trials), trials - start)
        check()
        draws = clean + draw_noise(rng, problem.sigmas, noise, size=size)
        noisy = [problem.with_values(v) for v in draws]
        for method in methods:
            check()
            results = solve_batch(noisy, method, options)
            fixes = [r for r in results if not isinstance(r, LocalizationError)]
            errors = np.array([f.position_enu_m - target for f in fixes]).reshape(-1, 3)
            errors_by_method[method].append(errors)
            nees_by_method[method].extend(_nees(e, f.covariance_enu_m2) for e, f in zip(errors, fixes))
    out = {}
    for method in methods:
        errors = np.concatenate(errors_by_method[method]) if errors_by_method[method] else np.zeros((0, 3))
        nees = nees_by_method[method]
        found = len(errors)
        out[method] = MethodAccuracy(
            rmse_m=float(np.sqrt(np.mean(np.sum(errors**2, axis=1)))) if found else float("nan"),
            rmse_enu_m=np.sqrt(np.mean(errors**2, axis=0)) if found else np.full(3, np.nan),
            bias_enu_m=errors.mean(axis=0) if found else np.full(3, np.nan),
            crlb_rmse_m=float(np.sqrt(np.trace(bound))),
            efficiency=float(np.mean(np.sum(errors**2, axis=1)) / np.trace(bound)) if found else float("nan"),
            nees_mean=float(np.mean(nees)) if nees else float("nan"),
            failures=trials - found,
            errors_enu_m=errors,
        )
    return out


def _nees(error_enu_m, covariance_enu_m2) -> float:
    """``e^T C^+ e`` (pseudo-inverse: a constrained fix has a rank-2 covariance)."""
    return float(error_enu_m @ np.linalg.pinv(covariance_enu_m2, rcond=1e-12, hermitian=True) @ error_enu_m)
