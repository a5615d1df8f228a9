"""Simulated measurements for a known target, and Monte Carlo evaluation of estimators."""

from __future__ import annotations

from dataclasses import dataclass, field, replace
from typing import Any, Callable

import numpy as np

from core.errors import LocalizationError, UnobservableGeometry
from core.measurements import predict
from core.parallel import chunk_seeds, chunk_slices, run_chunks
from core.problem.batch import ProblemBatch
from core.problem.frame import Problem

NOISE_KINDS = ("gaussian", "uniform", "outlier")
#: ``"outlier"`` noise, a contaminated gaussian: each measurement's error is N(0, sigma^2), except with this
#: probability, independently per measurement, a gross error N(0, (OUTLIER_SCALE sigma)^2).
OUTLIER_PROBABILITY = 0.05
OUTLIER_SCALE = 10.0
#: Trials drawn from one child seed: the draws of a seeded evaluation depend on the seed and the trial count
#: only, not on how the trials are chunked for running (or on how many workers run them).
DRAW_BLOCK_TRIALS = 64


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
    noise : {"gaussian", "uniform", "outlier"}
        See :func:`draw_noise`.
    """
    values = true_values(problem, target_enu_m)
    if rng is not None:
        values = values + draw_noise(rng, problem.sigmas, noise)
    return problem.with_values(values)


def draw_noise(rng: np.random.Generator, sigmas, noise: str = "gaussian", size=None) -> np.ndarray:
    """Zero-mean noise scaled by ``sigmas`` (shape ``size + sigmas.shape``).

    ``"gaussian"``: N(0, sigma^2). ``"uniform"``: zero-mean with the same sigma (half-width sigma sqrt(3)).
    ``"outlier"``: a contaminated gaussian, N(0, sigma^2) except with probability
    :data:`OUTLIER_PROBABILITY` per measurement N(0, (:data:`OUTLIER_SCALE` sigma)^2): gross errors that
    outlier exclusion (``SolveOptions(outliers="exclude")``) should find.
    """
    sigmas = np.asarray(sigmas, dtype=float)
    shape = sigmas.shape if size is None else tuple(np.atleast_1d(size)) + sigmas.shape
    if noise == "gaussian":
        return rng.standard_normal(shape) * sigmas
    if noise == "uniform":
        return rng.uniform(-1.0, 1.0, shape) * np.sqrt(3.0) * sigmas
    if noise == "outlier":
        gross = rng.random(shape) < OUTLIER_PROBABILITY
        return rng.standard_normal(shape) * sigmas * np.where(gross, OUTLIER_SCALE, 1.0)
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
    excluded_trials : int
        Successful trials in which outlier exclusion dropped at least one measurement.
    failure_reasons : dict of str to (int, str)
        Per error code of the failed trials (:attr:`core.errors.LocalizationError.code`): how many, and the
        first one's message.
    """

    rmse_m: float
    rmse_enu_m: np.ndarray
    bias_enu_m: np.ndarray
    crlb_rmse_m: float
    efficiency: float
    nees_mean: float
    failures: int
    errors_enu_m: np.ndarray
    excluded_trials: int = 0
    failure_reasons: dict = field(default_factory=dict)


def evaluate(problem: Problem, target_enu_m, methods, trials: int, seed: int | np.random.SeedSequence = 0,
             noise: str = "gaussian", options=None, should_stop: Callable[[], bool] | None = None,
             chunk_trials: int = 256, scheduler: Any = None,
             progress: Callable[[int, int], None] | None = None) -> dict[str, MethodAccuracy]:
    """Monte Carlo RMSE, bias, efficiency and NEES of methods on one scenario.

    Every method sees the same noisy draws, and each method solves a chunk of
    trials as one batch (:func:`core.estimators.solve_many`). The trials are
    drawn in blocks of :data:`DRAW_BLOCK_TRIALS`, block ``b`` from child
    ``b`` of the seed (:func:`core.parallel.chunk_seeds`); the trials are
    cut into chunks of ``chunk_trials`` (each drawing the blocks it overlaps
    and keeping its rows of them) that run here or on a Dask cluster
    (:func:`core.parallel.run_chunks`). The result for a seed is
    therefore the same for any chunk size and any number of workers.
    ``should_stop`` is asked between chunks.

    Parameters
    ----------
    problem : Problem
        The scenario (values ignored).
    target_enu_m : ndarray, shape (3,)
    methods : sequence of str
    trials : int
    seed : int or numpy.random.SeedSequence
    noise : {"gaussian", "uniform", "outlier"}
        See :func:`draw_noise`.
    options : SolveOptions, optional
        ``outliers="exclude"`` shows exclusion against ``noise="outlier"``.
    should_stop : callable returning bool, optional
        True = stop now (raises :class:`core.parallel.Stopped`).
    chunk_trials : int
        Trials per chunk.
    scheduler : str or distributed.Client, optional
        Run the chunks on this Dask cluster; None runs them in this process.
    progress : callable(done, total), optional
        Called after each chunk.

    Raises
    ------
    UnobservableGeometry
        When the sensors do not determine the target.
    core.parallel.Stopped
        When ``should_stop`` returned True.
    """
    from core.crlb import information_at
    from core.estimators import SolveOptions

    if noise not in NOISE_KINDS:
        raise ValueError(f"unknown noise {noise!r}")
    options = options or SolveOptions()
    methods = list(methods)
    target = np.asarray(target_enu_m, dtype=float)
    information = information_at(problem, target)
    if not information.observable[0]:
        raise UnobservableGeometry("the scenario's sensors do not determine the target (singular information)")
    bound = information.covariance_enu_m2[0]
    blocks = chunk_slices(trials, DRAW_BLOCK_TRIALS)
    seeds = chunk_seeds(seed, len(blocks))
    chunks = []
    for part in chunk_slices(trials, chunk_trials):
        pieces = []
        for b in range(part.start // DRAW_BLOCK_TRIALS, (part.stop - 1) // DRAW_BLOCK_TRIALS + 1):
            block = blocks[b]
            pieces.append((seeds[b], block.stop - block.start, max(part.start, block.start) - block.start,
                           min(part.stop, block.stop) - block.start))
        chunks.append((problem, target, methods, pieces, noise, options))
    parts = run_chunks(evaluate_chunk, chunks, scheduler=scheduler, should_stop=should_stop, progress=progress)
    out = {}
    for method in methods:
        errors = np.concatenate([part[method][0] for part in parts]) if parts else np.zeros((0, 3))
        nees = np.concatenate([part[method][1] for part in parts]) if parts else np.zeros(0)
        excluded = sum(int(part[method][2]) for part in parts)
        reasons: dict[str, tuple[int, str]] = {}
        for part in parts:
            for code, (count, message) in part[method][3].items():
                earlier, first = reasons.get(code, (0, message))
                reasons[code] = (earlier + count, first)
        found = len(errors)
        out[method] = MethodAccuracy(
            rmse_m=float(np.sqrt(np.mean(np.sum(errors**2, axis=1)))) if found else float("nan"),
            rmse_enu_m=np.sqrt(np.mean(errors**2, axis=0)) if found else np.full(3, np.nan),
            bias_enu_m=errors.mean(axis=0) if found else np.full(3, np.nan),
            crlb_rmse_m=float(np.sqrt(np.trace(bound))),
            efficiency=float(np.mean(np.sum(errors**2, axis=1)) / np.trace(bound)) if found else float("nan"),
            nees_mean=float(np.mean(nees)) if found else float("nan"),
            failures=trials - found,
            errors_enu_m=errors,
            excluded_trials=excluded,
            failure_reasons=reasons,
        )
    return out


def evaluate_chunk(problem: Problem, target_enu_m, methods, blocks, noise: str, options):
    """One chunk of :func:`evaluate`: its draw blocks, every method solved over them as one batch.

    Parameters
    ----------
    problem : Problem
    target_enu_m : ndarray, shape (3,)
    methods : list of str
    blocks : list of (numpy.random.SeedSequence, int, int, int)
        The draw blocks the chunk overlaps: each block's seed and trial count, and the rows of it the chunk
        takes (``start``, ``stop``).
    noise : str
    options : SolveOptions

    Returns
    -------
    dict of str to (ndarray (F, 3), ndarray (F,), int, dict)
        Per method: the errors and NEES of the F trials that gave a fix, how many of them excluded
        a measurement, and the failed trials' count and first message per error code.
    """
    from core.estimators import solve_many

    clean = true_values(problem, target_enu_m)
    draws = np.concatenate([clean + draw_noise(np.random.default_rng(block_seed), problem.sigmas, noise,
                                               size=size)[start:stop] for block_seed, size, start, stop in blocks])
    batch = trial_batch(problem, draws)
    out = {}
    for method in methods:
        errors, nees, excluded, reasons = [], [], 0, {}
        for rows, fixes in solve_many(batch, method, options):
            failed = [(fixes, rows.size, int(rows.min()))] if isinstance(fixes, LocalizationError) else \
                [(error, 1, int(rows[b])) for b, error in fixes.errors.items()]
            for error, count, row in failed:  # the message kept is the earliest trial's, whatever the grouping
                earlier, first_row, first = reasons.get(error.code, (0, row, error.message))
                reasons[error.code] = (earlier + count, *min((first_row, first), (row, error.message)))
            if isinstance(fixes, LocalizationError):
                continue
            ok = fixes.ok
            if not ok.any():
                continue
            e = fixes.position_enu_m[ok] - target_enu_m
            errors.append(np.column_stack([rows[ok], e]))
            nees.append(_nees(e, fixes.covariance_enu_m2[ok]))
            excluded += int(np.count_nonzero(fixes.excluded[ok].any(axis=1)))
        reasons = {code: (count, message) for code, (count, _, message) in reasons.items()}
        if errors:
            joined = np.concatenate(errors)
            order = np.argsort(joined[:, 0], kind="stable")
            out[method] = (joined[order, 1:], np.concatenate(nees)[order], excluded, reasons)
        else:
            out[method] = (np.zeros((0, 3)), np.zeros(0), 0, reasons)
    return out


def _nees(errors_enu_m, covariances_enu_m2) -> np.ndarray:
    """``e^T C^+ e`` per row ``(F,)`` (pseudo-inverse: a constrained fix has a rank-2 covariance)."""
    inverse = np.linalg.pinv(covariances_enu_m2, rcond=1e-12, hermitian=True)
    return np.einsum("fi,fij,fj->f", errors_enu_m, inverse, errors_enu_m)
