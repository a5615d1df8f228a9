"""Estimators behind one interface, batch first.

Every estimator is registered in :data:`core.estimators.base.REGISTRY` under
its API name and consumes a :class:`~core.problem.batch.ProblemBatch`
(``spec.solve_batch(batch, options) -> FixBatch``). :func:`solve_many` runs
many problems, each with its own method and options, grouped so that each
group is one batched call; :func:`solve` is a batch of one, squeezed.
Importing this package registers every estimator module.
"""

from __future__ import annotations

import dataclasses
import importlib
import math
import os
import pkgutil
import threading
from concurrent.futures import ThreadPoolExecutor

import numpy as np

from core.errors import AmbiguousGeometry, InvalidInput, LocalizationError, UnobservableGeometry
from core.estimators.base import REGISTRY, SolveOptions, get_estimator
from core.estimators.finish import not_isolable_warning, outlier_warning
from core.estimators.loss import LOSSES
from core.estimators.result import Fix, FixBatch, FixWarning
from core.measurements import AZIMUTH
from core.parallel import Stopped
from core.problem.batch import ProblemBatch, size_groups
from core.problem.frame import Problem

AUTO = "auto"

for _module in pkgutil.walk_packages(__path__, prefix=f"{__name__}."):
    importlib.import_module(_module.name)


def resolve_methods(batch: ProblemBatch, methods: list[str]) -> list[str]:
    """The estimator each problem's method stands for (``auto`` depends on the measurement mix).

    ``auto`` is ML (started from the best closed form for the mix) whenever
    sigmas are known; ``taylor_wls``, which estimates them, when azimuth-only
    bearings come without sigmas.
    """
    if AUTO not in methods:
        return list(methods)
    valid = batch.valid
    unknown_sigma = np.any(valid & np.isnan(batch.sigmas) & (batch.kinds == AZIMUTH), axis=-1)
    azimuth_only = np.all(~valid | (batch.kinds == AZIMUTH), axis=-1)
    estimates_sigmas = (unknown_sigma & azimuth_only).tolist()
    return [("taylor_wls" if estimates_sigmas[b] else "ml") if m == AUTO else m for b, m in enumerate(methods)]


#: Problems per call of an estimator's ``solve_batch``: a larger group is solved in parts of this many.
PART_PROBLEMS = 2048
#: ... and of at most about this many measurement pairs (each problem's rows squared, summed; one problem at
#: the least): the pairwise methods' time and memory grow with them (ws3d held about 90 MB per problem of
#: 1,024 bearings at once), and a part is what a deadline or a gone client waits for before the solve stops.
PART_PAIRS = PART_PROBLEMS * 16**2
#: Threads that solve the parts of one call at once (the kernels release the GIL).
MAX_WORKERS = min(2, os.cpu_count() or 1)
_pool: ThreadPoolExecutor | None = None
_pool_lock = threading.Lock()


def _workers() -> ThreadPoolExecutor:
    global _pool
    with _pool_lock:
        if _pool is None:
            _pool = ThreadPoolExecutor(MAX_WORKERS, thread_name_prefix="solve")
        return _pool


def _groups(names: list[str], options: list) -> dict[tuple, np.ndarray]:
    """The rows of each distinct (method name, options) pair, in order of first appearance.

    Rows are told apart by their name and the identity of their options object, in C-level passes over the
    batch; one row of each distinct pair of objects is then hashed by value, so equal options sent as
    separate objects (one per request) still share a group.
    """
    if len(dict.fromkeys(names)) <= 1 and len(dict.fromkeys(map(id, options))) <= 1:
        return {(names[0], options[0]): np.arange(len(names))} if names else {}
    pairs = list(zip(names, map(id, options)))
    pair_codes = dict.fromkeys(pairs)
    for code, pair in enumerate(pair_codes):
        pair_codes[pair] = code
    by_pair = np.fromiter(map(pair_codes.__getitem__, pairs), dtype=np.intp, count=len(pairs))
    first_rows = np.unique(by_pair, return_index=True)[1].tolist()  # the first row of each pair, by its code
    value_codes: dict[tuple, int] = {}
    pair_values = np.array([value_codes.setdefault((names[r], options[r]), len(value_codes)) for r in first_rows])
    by_value = pair_values[by_pair]
    order = np.argsort(by_value, kind="stable")
    keys = list(value_codes)
    return {keys[int(by_value[rows[0]])]: rows
            for rows in np.split(order, np.flatnonzero(np.diff(by_value[order])) + 1)}


def solve_many(batch: ProblemBatch, methods, options,
               should_stop=None) -> list[tuple[np.ndarray, FixBatch | LocalizationError]]:
    """Fixes of every problem of a batch, each with its own method and options: :func:`iter_solutions` as a list."""
    return list(iter_solutions(batch, methods, options, should_stop))


def iter_solutions(batch: ProblemBatch, methods, options, should_stop=None, *, background: bool = False):
    """Fixes of every problem of a batch, each with its own method and options, part by part.

    Problems with the same method and options are solved together, one
    batched call per size class (padding stays under 2x) and per part of at
    most :data:`PART_PROBLEMS` problems or :data:`PART_PAIRS` measurement
    pairs (a class of several parts is cut into parts of equal size, as
    many for each thread). With more than one part (or ``background``), up to
    :data:`MAX_WORKERS` threads solve them, started by this call, and each
    part is yielded, in order, as soon as it and those before it are done
    (a caller can write the first parts, or read its next batch, while the
    next ones are solved). A single part is otherwise solved as it is asked
    for, on the caller's thread.

    Parameters
    ----------
    batch : ProblemBatch
    methods : str or sequence of str, length B
        API method names (``auto`` allowed).
    options : SolveOptions or sequence of SolveOptions, length B, optional
    should_stop : callable returning bool, optional
        Asked before each part is solved, and before each round of outlier exclusion; True raises
        :class:`core.parallel.Stopped`.
    background : bool
        Start solving on the threads now, even a single part.

    Returns
    -------
    iterator of (rows, FixBatch or LocalizationError)
        ``rows`` indexes ``batch``; a LocalizationError stands for every
        problem of its rows (an unknown method or variant, a missing sigma).
        Closing it cancels the parts not started.
    """
    size = batch.size
    methods = [methods] * size if isinstance(methods, str) else list(methods)
    if options is None or isinstance(options, SolveOptions):
        options = [options or SolveOptions()] * size
    missing = batch.lacks_sigma
    any_missing = np.count_nonzero(missing) > 0
    work: list = []
    for (name, opts), rows in _groups(resolve_methods(batch, methods), options).items():
        try:
            spec = get_estimator(name)
            _check_variant(spec, opts)
            _check_loss(spec, opts)
        except LocalizationError as error:
            work.append((rows, error))
            continue
        if spec.needs_sigmas and any_missing:
            lacking = missing[rows]
            for b in rows[lacking].tolist():
                m = int(np.flatnonzero(batch.valid[b] & np.isnan(batch.sigmas[b]))[0])
                work.append((np.array([b]), InvalidInput(
                    f"method {name} needs the azimuth sigma of every bearing",
                    ("measurements", int(batch.source_index[b, m]), "sigma_azimuth_rad"))))
            rows = rows[~lacking]
        for group in size_groups(batch.n_measurements[rows], batch.n_stations[rows]):
            width = max(int(batch.n_measurements[rows[group]].max()), 1)
            step = max(1, min(PART_PROBLEMS, PART_PAIRS // width**2))
            parts = -(-group.size // step)
            if parts > 1:  # as many parts for each thread, of equal size: no thread waits on another's last part
                step = -(-group.size // (-(-parts // MAX_WORKERS) * MAX_WORKERS))
            for start in range(0, group.size, step):
                work.append((rows[group[start:start + step]], spec, opts))

    def solve_part(chosen, spec, opts):
        if should_stop is not None and should_stop():
            raise Stopped()
        part = batch if chosen.size == size else batch.take(chosen)
        fixes = spec.solve_batch(part, opts)
        if opts.outliers == "exclude":
            fixes = exclude_outliers(spec, part, opts, fixes, should_stop)
        elif opts.loss == "linear":  # a robust loss's verdict is its weights (measurement_downweighted)
            fixes = confirm_outliers(spec, part, opts, fixes)
        return fixes if opts.absolute_sigma else fixes.scaled_by_fit()

    parts = sum(len(item) == 3 for item in work)
    if MAX_WORKERS == 1 or (parts <= 1 and not background):
        return ((item if len(item) == 2 else (item[0], solve_part(*item))) for item in work)
    pool = _workers()
    return _in_order(work, [None if len(item) == 2 else pool.submit(solve_part, *item) for item in work])


def _in_order(work: list, futures: list):
    """Each work item's result as :func:`iter_solutions` yields it, waiting on its future; the futures not
    started are cancelled when the iteration ends or is closed."""
    try:
        for item, future in zip(work, futures):
            yield item if future is None else (item[0], future.result())
    finally:
        for future in futures:
            if future is not None:
                future.cancel()


#: Chi-square p-value below which a fit fails the consistency test and its worst measurement is excluded.
EXCLUSION_P = 0.01
#: At most this many measurements are excluded from one problem.
MAX_EXCLUSIONS = 8
#: Each exclusion tries leaving out at most this many request measurements (the most suspect): a refit each.
EXCLUSION_CANDIDATES = 8
#: ... and, where no single one explains the fault, each pair of at most this many (the most suspect).
PAIR_CANDIDATES = 5
#: Report mode confirms ``outlier_suspected`` by refits (:func:`confirm_outliers`) in problems of at most this
#: many request measurements.
CONFIRM_MAX_SOURCES = 16


def exclusion_solves(sources: int) -> int:
    """How many times exclusion may solve a problem of ``sources`` request measurements at most (its first
    solve included): the budget :func:`exclude_outliers` keeps to, whatever the rounds cost."""
    return 1 + sum(min(EXCLUSION_CANDIDATES, sources - done) for done in range(min(MAX_EXCLUSIONS, sources - 1)))


def exclude_outliers(spec, batch: ProblemBatch, options: SolveOptions, fixes: FixBatch, should_stop=None) -> FixBatch:
    """Fault detection and exclusion (RAIM FDE) over a batch.

    While a fix fails the chi-square test (``p < EXCLUSION_P``), or ran off
    to where the geometry is unobservable (as one bearing 20 deg off can
    make it on nearly parallel lines of sight), each of its
    :data:`EXCLUSION_CANDIDATES` most suspect request measurements (largest
    studentized residual first; a bearing's azimuth and elevation together)
    is left out in turn and the problem solved again, all at once as one
    batch (:func:`_isolations`). A measurement is excluded only where that
    isolates it: its refit is the only one that passes the test (were
    another measurement the fault, that one's refit would pass but for
    ``EXCLUSION_P`` of the draws); where none passes (several faults), the
    only pair of the most suspect whose exclusion passes is excluded. The
    test then runs again on the refit, so that further faults are excluded
    while the dof allow. The refits are the nonlinear form of the
    largest-studentized-residual rule (for a linear model, leaving a
    measurement out lowers chi-square by its studentized residual squared)
    and also unmask a gross error that a nonlinear or robust fit absorbed.

    RAIM's rule: a fault is detected with one degree of freedom but
    isolated only with two or more; a fault detected and not isolable (one
    dof, or several exclusions that explain it alike) names no one, keeps
    its fix, and says so (``fault_detected_not_isolable``). The covariance
    and CRLB are those of the measurements used; every excluded one is named
    in a warning. ``should_stop`` is asked before each round (True raises
    :class:`core.parallel.Stopped`).
    """
    used = batch.valid.copy()
    excluded = np.zeros_like(used)
    settled = np.zeros(batch.size, dtype=bool)
    blameless = np.zeros(batch.size, dtype=bool)  # detected, not isolable
    sizes, inverse = np.unique(batch.source_index.max(axis=-1, initial=0) + 1, return_inverse=True)
    budget = np.array([exclusion_solves(int(n)) for n in sizes])[inverse] - 1  # refits left, per problem
    for _ in range(MAX_EXCLUSIONS):
        # A round's single exclusions and the refit of its choice must fit in the budget (pairs: see below).
        marked = np.concatenate([np.full((batch.size, 1), -1), np.where(used, batch.source_index, -1)], axis=-1)
        left = np.count_nonzero(np.diff(np.sort(marked, axis=-1), axis=-1), axis=-1)  # request measurements used
        broke = ~settled & (budget < np.minimum(EXCLUSION_CANDIDATES, left) + 1)
        blameless |= broke & fixes.ok & (np.nan_to_num(fixes.p_value, nan=1.0) < EXCLUSION_P)
        settled |= broke
        testing = ~settled & fixes.ok & (np.nan_to_num(fixes.p_value, nan=1.0) < EXCLUSION_P)
        few = testing & (fixes.dof < 2)  # every exclusion fits exactly: nothing to tell them apart
        blameless |= few
        settled |= few
        testing &= ~few
        for b, error in fixes.errors.items():
            testing[b] = not settled[b] and isinstance(error, UnobservableGeometry)
        rows = np.flatnonzero(testing)
        if rows.size == 0:
            break
        if should_stop is not None and should_stop():
            raise Stopped()
        isolated, vague, drops, spent = _isolations(spec, batch, options, fixes, used, excluded, rows,
                                                    budget=budget[rows] - 1)
        budget[rows] -= spent + isolated
        blameless[rows[vague]] = True
        settled[rows[~isolated]] = True
        keep = rows[isolated]
        used[keep] &= ~drops[isolated]
        excluded[keep] |= drops[isolated]
        fixes = fixes.replace_rows(keep, _refits(spec, batch, options, keep, used[keep], excluded[keep])[1])
    return _blameless(fixes, blameless)


def confirm_outliers(spec, batch: ProblemBatch, options: SolveOptions, fixes: FixBatch) -> FixBatch:
    """Report mode's isolation, by refits, of a fault its residuals detected (``outlier_suspected`` or
    ``fault_detected_not_isolable``) where the fit fails the chi-square test, in problems of at most
    :data:`CONFIRM_MAX_SOURCES` request measurements: the single exclusions of :func:`_isolations` name the
    measurement (``outlier_suspected``) where exactly one of their refits passes and it is the one with the
    largest studentized residual, else no one (``fault_detected_not_isolable``). With few degrees of freedom
    the residuals' linear isolation misleads both ways (a fault that pulls the fix far along a poorly determined
    direction leaves its largest residual elsewhere, or leaves another as large); with many it holds, and report
    mode's price stays one solve."""
    if not any(fixes.warnings):  # clean fixes, the usual case: nothing to confirm
        return fixes
    flagged = np.array([any(w.code in ("outlier_suspected", "fault_detected_not_isolable") for w in warnings)
                        for warnings in fixes.warnings])
    small = batch.source_index.max(axis=-1, initial=0) < CONFIRM_MAX_SOURCES
    rows = np.flatnonzero(flagged & small & fixes.ok & (np.nan_to_num(fixes.p_value, nan=1.0) < EXCLUSION_P))
    if rows.size == 0:
        return fixes
    isolated, _, drops, _ = _isolations(spec, batch, options, fixes, batch.valid, np.zeros_like(batch.valid), rows,
                                        budget=np.zeros(rows.size, dtype=int))
    studentized = fixes.studentized_residuals[rows]
    worst = np.argmax(np.where(batch.valid[rows], np.abs(studentized), -1.0), axis=-1)
    agrees = isolated & drops[np.arange(rows.size), worst] & (fixes.dof[rows] >= 2)
    warnings = list(fixes.warnings)
    for j, b in enumerate(rows.tolist()):
        kept = tuple(w for w in warnings[b] if w.code not in ("outlier_suspected", "fault_detected_not_isolable"))
        if agrees[j]:
            warnings[b] = kept + (outlier_warning(batch, b, int(worst[j]), float(studentized[j, worst[j]])),)
        else:
            warnings[b] = kept + (not_isolable_warning(float(fixes.chi2[b]), int(fixes.dof[b]),
                                                       float(np.abs(studentized[j, worst[j]]))),)
    return dataclasses.replace(fixes, warnings=warnings)


def _blameless(fixes: FixBatch, rows) -> FixBatch:
    """The fixes with ``fault_detected_not_isolable`` added where ``rows`` ``(B,)`` (and no one named as an
    outlier)."""
    rows = rows & fixes.ok
    if not np.count_nonzero(rows):
        return fixes
    warnings = list(fixes.warnings)
    for b in np.flatnonzero(rows).tolist():
        kept = tuple(w for w in warnings[b] if w.code != "outlier_suspected")
        if not any(w.code == "fault_detected_not_isolable" for w in kept):
            kept += (not_isolable_warning(float(fixes.chi2[b]), int(fixes.dof[b]),
                                          float(np.max(np.abs(fixes.studentized_residuals[b])))),)
        warnings[b] = kept
    return dataclasses.replace(fixes, warnings=warnings)


def _refits(spec, batch: ProblemBatch, options: SolveOptions, owners, used, excluded) -> tuple:
    """Problems ``owners`` ``(C,)`` (rows of ``batch``) solved with the measurements ``used`` ``(C, M)``
    (``excluded`` ``(C, M)``: those exclusion set aside); returns the subsets and their fixes."""
    trials = batch.take(owners)
    width = trials.kinds.shape[1]
    trials = trials.with_used(used[:, :width])
    return trials, spec.solve_batch(trials, options, excluded=excluded[:, :width])


def _scores(trials: ProblemBatch, refits: FixBatch) -> np.ndarray:
    """``(C,)``: each refit's p-value where it converged with a degree of freedom left (else -inf); a subset with
    a degree of freedom that two points fit alike (``AmbiguousGeometry``) is consistent too, and scores 1."""
    score = np.where(refits.ok & refits.converged & (trials.dof > 0), np.nan_to_num(refits.p_value, nan=-1.0),
                     -np.inf)
    for j, error in refits.errors.items():
        if isinstance(error, AmbiguousGeometry) and trials.dof[j] > 0:
            score[j] = 1.0
    return score


def _isolations(spec, batch: ProblemBatch, options: SolveOptions, fixes: FixBatch, used, excluded, rows, budget):
    """Which measurements, if any, each problem of ``rows`` isolates as its fault (see :func:`exclude_outliers`).

    Its :data:`EXCLUSION_CANDIDATES` most suspect request measurements (by ``|studentized|``, NaN first) are
    left out in turn, all solved as one batch. The fault is isolated where exactly one of those refits passes
    the test. Where none does the data hold two faults or more: the pairs of the :data:`PAIR_CANDIDATES` most
    suspect are left out (with three dof or more), and exactly one passing pair is isolated. Where several
    pass, the fault is detected and not isolable. A problem without a fix (it ran off) takes its best single
    exclusion.

    Returns
    -------
    isolated : ndarray of bool, shape (R,)
    vague : ndarray of bool, shape (R,)
        Detected, not isolable (a problem with a fix and no isolation: several exclusions explain the fault
        alike, or none does).
    drops : ndarray of bool, shape (R, M)
        The measurements to exclude where ``isolated``.
    spent : ndarray of int, shape (R,)
        The refits each problem took (its pairs only where its ``budget`` ``(R,)`` of refits covered them).
    """
    suspicion = np.abs(fixes.studentized_residuals)
    owners, drops = batch.leave_one_out(rows, used, suspicion, EXCLUSION_CANDIDATES)  # rows ascending
    trials, refits = _refits(spec, batch, options, owners, used[owners] & ~drops, excluded[owners] | drops)
    score = _scores(trials, refits)
    problem = np.searchsorted(rows, owners)  # rows ascending: each candidate's index in rows
    passing = np.bincount(problem[score >= EXCLUSION_P], minlength=rows.size)
    order = np.lexsort((-score, problem))  # per problem, the best score first (the most suspect on a tie)
    firsts = order[np.flatnonzero(np.diff(problem[order], prepend=-1))]
    best = np.full(rows.size, -1, dtype=np.intp)  # each problem's best candidate (-1: it had none)
    best[problem[firsts]] = firsts
    possible = best >= 0
    possible[possible] = score[best[possible]] > -np.inf
    has_fix = fixes.ok[rows]
    isolated = possible & ((passing == 1) | (passing == 0) & ~has_fix)
    out = np.zeros((rows.size,) + used.shape[1:], dtype=bool)
    out[isolated] = drops[best[isolated]]
    spent = np.bincount(problem, minlength=rows.size)
    count = np.minimum(np.bincount(problem, minlength=rows.size), PAIR_CANDIDATES)
    affordable = budget - spent >= count * (count - 1) // 2
    several = np.flatnonzero(has_fix & (passing == 0) & (fixes.dof[rows] >= 3) & affordable)
    spent[several] += count[several] * (count[several] - 1) // 2
    if several.size:
        # The pairs among each problem's first PAIR_CANDIDATES candidates (they come most suspect first).
        rank = np.arange(owners.size) - np.searchsorted(problem, problem)
        mine = np.isin(problem, several) & (rank < PAIR_CANDIDATES)
        first, second = [], []
        for k in several.tolist():
            members = np.flatnonzero(mine & (problem == k))
            for i in range(members.size):
                for j in range(i + 1, members.size):
                    first.append(members[i])
                    second.append(members[j])
        first, second = np.array(first, dtype=np.intp), np.array(second, dtype=np.intp)
        if first.size:
            pair_drops = drops[first] | drops[second]
            pair_owners = owners[first]
            trials, pair_refits = _refits(spec, batch, options, pair_owners, used[pair_owners] & ~pair_drops,
                                          excluded[pair_owners] | pair_drops)
            pair_score = _scores(trials, pair_refits)
            pair_problem = problem[first]
            pair_passing = np.bincount(pair_problem[pair_score >= EXCLUSION_P], minlength=rows.size)
            found = several[pair_passing[several] == 1]
            isolated[found] = True
            winners = np.flatnonzero((pair_score >= EXCLUSION_P) & np.isin(pair_problem, found))
            out[pair_problem[winners]] = pair_drops[winners]
    return isolated, has_fix & ~isolated, out, spent


def solve_batch(problems, method=AUTO, options=None) -> list[Fix | LocalizationError]:
    """Every problem's fix (or the error that stopped it), in order.

    Parameters
    ----------
    problems : ProblemBatch or sequence of Problem
    method : str or sequence of str
        One method for all, or one per problem.
    options : SolveOptions or sequence of SolveOptions, optional
    """
    batch = problems if isinstance(problems, ProblemBatch) else ProblemBatch.from_problems(list(problems))
    results: list[Fix | LocalizationError | None] = [None] * batch.size
    for rows, fixes in solve_many(batch, method, options):
        for j, b in enumerate(rows.tolist()):
            results[b] = fixes if isinstance(fixes, LocalizationError) else fixes.fix(j)
    return results


def solve(problem: Problem, method: str = AUTO, options: SolveOptions | None = None) -> Fix:
    """Run one estimator on one problem (a batch of one).

    Raises
    ------
    LocalizationError
        When the method cannot give a fix for this problem.
    """
    (result,) = solve_batch([problem], method, options)
    if isinstance(result, LocalizationError):
        raise result
    return result


def _check_variant(spec, options: SolveOptions) -> None:
    variant = options.variant
    if variant is None or variant in spec.variants:
        return
    if spec.variants:
        raise InvalidInput(f"{spec.name} variant must be one of {', '.join(spec.variants)}; got {variant!r}",
                           ("variant",))
    raise InvalidInput(f"{spec.name} has no variants; got {variant!r}", ("variant",))


def _check_loss(spec, options: SolveOptions) -> None:
    if options.loss not in LOSSES:
        raise InvalidInput(f"loss must be one of {', '.join(LOSSES)}; got {options.loss!r}", ("loss",))
    if not (math.isfinite(options.loss_scale) and options.loss_scale > 0):
        raise InvalidInput(f"loss_scale must be a positive number of sigmas; got {options.loss_scale!r}",
                           ("loss_scale",))
    if options.loss != "linear" and not spec.robust:
        robust = ", ".join(sorted(name for name, s in REGISTRY.items() if s.robust))
        raise InvalidInput(f"{spec.name} minimises plain least squares; loss {options.loss!r} needs {robust}",
                           ("loss",))


__all__ = ["AUTO", "REGISTRY", "Fix", "FixBatch", "FixWarning", "SolveOptions", "confirm_outliers", "exclude_outliers",
           "exclusion_solves", "resolve_methods", "solve", "iter_solutions", "solve_batch", "solve_many"]
