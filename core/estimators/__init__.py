"""Estimators behind one interface: ``solve(problem, method, options) -> Fix``.

Importing this package registers every estimator module in
:data:`core.estimators.base.REGISTRY`, which the API's ``method`` looks up.
"""

from __future__ import annotations

import importlib
import pkgutil

import numpy as np

from core.errors import InvalidInput, LocalizationError
from core.estimators import ml as _ml
from core.estimators.base import REGISTRY, Fix, FixWarning, SolveOptions, get_estimator
from core.measurements import Kind
from core.problem import Problem

AUTO = "auto"

for _module in pkgutil.iter_modules(__path__):
    importlib.import_module(f"{__name__}.{_module.name}")


def resolve_method(problem: Problem, method: str) -> str:
    """The estimator ``auto`` stands for, given the measurement mix.

    ML (started from the best closed form for the mix) whenever sigmas are
    known; ``taylor_wls``, which estimates them, when azimuth-only bearings
    come without sigmas.
    """
    if method != AUTO:
        return get_estimator(method).name
    unknown_sigma = np.isnan(problem.sigmas) & (problem.kinds == Kind.AZIMUTH)
    azimuth_only = problem.count(Kind.AZIMUTH) == problem.n_measurements
    if np.any(unknown_sigma) and azimuth_only and "taylor_wls" in REGISTRY:
        return "taylor_wls"
    return "ml"


def solve(problem: Problem, method: str = AUTO, options: SolveOptions | None = None) -> Fix:
    """Run one estimator on one problem.

    Raises
    ------
    LocalizationError
        When the method cannot give a fix for this problem.
    """
    options = options or SolveOptions()
    spec = get_estimator(resolve_method(problem, method))
    _require_sigmas(problem, spec.name, spec.needs_sigmas)
    return spec.solve(problem, options)


def solve_many(problems: list[Problem], methods: list[str], options: list[SolveOptions]) -> list[Fix | LocalizationError]:
    """Solve independent problems; ML problems share one batched iteration.

    Returns
    -------
    list of Fix or LocalizationError, in input order.
    """
    results: list[Fix | LocalizationError | None] = [None] * len(problems)
    batched: dict[tuple, list[int]] = {}
    for i, (problem, method, opts) in enumerate(zip(problems, methods, options)):
        try:
            name = resolve_method(problem, method)
            _require_sigmas(problem, name, get_estimator(name).needs_sigmas)
        except LocalizationError as error:
            results[i] = error
            continue
        if name == "ml":
            batched.setdefault((opts.max_iterations, opts.tolerance_m), []).append(i)
            continue
        try:
            results[i] = get_estimator(name).solve(problem, opts)
        except LocalizationError as error:
            results[i] = error
    for key, indices in batched.items():
        solved = _ml.solve_ml_batch([problems[i] for i in indices], SolveOptions(*key))
        for i, result in zip(indices, solved):
            results[i] = result
    return results


def _require_sigmas(problem: Problem, name: str, needs_sigmas: bool) -> None:
    missing = np.flatnonzero(np.isnan(problem.sigmas))
    if needs_sigmas and missing.size:
        i = int(problem.source_index[missing[0]])
        raise InvalidInput(f"method {name} needs sigma_azimuth_deg on every bearing",
                           ("measurements", i, "sigma_azimuth_deg"))


__all__ = ["AUTO", "REGISTRY", "Fix", "FixWarning", "SolveOptions", "resolve_method", "solve", "solve_many"]
