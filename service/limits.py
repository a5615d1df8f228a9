"""The cost model: what one request may ask of the machine (422 ``over_limit`` naming the limit above it).

Costs are in units of about one batched ML measurement row. Every method is
solved batched, within 4x of ML's cost per problem (10,000 four-station
problems in core, estimate and finish on one thread, us per fix:
ml 9.7, weighted_eove 10.4, eove 8.6, ove 29.9, los_intersection 15.7, ple3d
10.4, ws3d 15.2, angle_range 38.5 with its range, tls 38.1 and ctls 31.8 with
the altitude, taylor_wls 27.3; ``python -m bench.closed_form_core -r 5 10000
<methods>``), so every method weighs 1:

- evaluation: ``trials x sum over methods of weight x measurement rows``
  (``max_evaluation_cost``);
- batch: ``sum over problems of weight x measurements`` (``max_batch_cost``);
- coverage map: ``cells x measurement rows`` (``max_grid_cost``); the bound took 3.7 us per cell and
  row (1,002,001 cells of two azimuths in 7.4 s, in chunks of 1,024) and the GeoJSON is about 280 bytes
  per cell (40,401 cells: 11.2 MB, built in 0.3 s), so the default 200,000 is 100,000 cells of two
  azimuths (about 28 MB of GeoJSON) or 25,000 of eight rows;
- fix: ``stations x measurements`` (``max_fix_cost``), for a single fix and
  for each problem of a batch (the largest fix the schema allows,
  256 x 1024, is within 3 s and 300 MB with every method:
  ``python -m bench.largest_fix`` and ``tests/service/test_faults.py``).

los_intersection intersects every pair of lines of sight: a problem of M measurements costs it about
0.4 us x M^2 in core (414 ms for 2 stations x 1,024 bearings, 33 ms for 256; ml: 1.8 ms), so a fix, a
batch problem or an evaluation trial costs it at least M^2 / 4 (:func:`problem_units`; rows for a trial).

Each of them is multiplied, for a problem solved with ``options.outliers "exclude"``, by the solves
exclusion may take (:func:`exclusion_solves`): its refits run the method again, up to 65 times. Unpriced,
256 x 1,024 with los_intersection and exclusion took 28 s, and 2 x 1,008 took 25 s.
"""

from __future__ import annotations

from service.web.problems import ApiError
from service.fixes.decode import measurement_count, requested_method, requests_exclusion, station_count

#: The key of pydantic's validation context (``model_validate(..., context=...)``) that carries the app's
#: ``max_fix_cost`` to :class:`service.schemas.FixRequest`'s cost check (:func:`fix_cost_context`).
FIX_COST_LIMIT_KEY = "max_fix_cost"


def fix_cost_context(limit: int | None) -> dict:
    """The validation context that makes :class:`service.schemas.FixRequest` check ``limit``
    (None: no limit)."""
    return {FIX_COST_LIMIT_KEY: limit}


def method_weight(method) -> int:
    """Cost of one measurement row of ``method`` (see the module docstring: all methods weigh alike)."""
    return 1


def problem_units(method, base: int, measurements: int) -> int:
    """A problem's cost for ``method`` on one solve: ``base`` (its measurements, or stations x measurements
    for a fix), and for los_intersection, which intersects every pair of lines of sight, at least
    ``measurements^2 / 4``."""
    return max(base, measurements * measurements // 4) if method == "los_intersection" else base


def over_limit(name: str, cost: int, limit: int, loc: list, what: str) -> ApiError:
    detail = f"{what} costs {cost:,} units, over the limit {name} = {limit:,}; ask for less"
    return ApiError(422, "over_limit", detail, [{"loc": loc, "msg": detail, "type": "over_limit"}])


def exclusion_solves(exclude: bool, sources: int) -> int:
    """How many times a problem of ``sources`` request measurements may be solved: once, and with outlier
    exclusion (``exclude``) the budget exclusion keeps to (:func:`core.estimators.exclusion_solves`)."""
    from core.estimators import exclusion_solves as budget

    return budget(sources) if exclude else 1


def evaluation_cost(trials: int, methods, rows: int, exclude: bool = False, sources: int = 1) -> int:
    """``trials x rows x method weights`` (:func:`problem_units`), times the solves a trial may take
    (:func:`exclusion_solves`)."""
    per_trial = sum(problem_units(m, rows * method_weight(m), rows) for m in methods)
    return trials * per_trial * exclusion_solves(exclude, sources)


def check_evaluation(trials: int, methods, rows: int, limit: int, exclude: bool = False, sources: int = 1) -> None:
    cost = evaluation_cost(trials, methods, rows, exclude, sources)
    if cost > limit:
        raise over_limit("max_evaluation_cost", cost, limit, ["trials"],
                         f"{trials} trials x {len(methods)} methods x {rows} measurement rows"
                         + (" (los_intersection: rows^2 / 4, its pairs of lines of sight)"
                            if "los_intersection" in methods else "")
                         + (" x (1 + the refits each trial's exclusions may take)" if exclude else ""))


def check_grid(cells: int, rows: int, limit: int) -> None:
    cost = cells * rows
    if cost > limit:
        raise over_limit("max_grid_cost", cost, limit, ["grid", "step_m"],
                         f"a grid of {cells:,} cells x {rows} measurement rows")


def batch_cost(problems: list) -> int:
    """``sum of weight x measurements x solves`` (:func:`exclusion_solves`) over parsed or decoded problems
    (anything malformed costs 1)."""
    total = 0
    for body in problems:
        count = measurement_count(body)
        method = requested_method(body)
        total += 1 if count is None else (problem_units(method, count * method_weight(method), count)
                                          * exclusion_solves(requests_exclusion(body), count))
    return total


def check_batch(problems: list, limit: int) -> None:
    cost = batch_cost(problems)
    if cost > limit:
        raise over_limit("max_batch_cost", cost, limit, ["problems"], f"a batch of {len(problems)} problems")


def fix_cost(stations: int, measurements: int, method: str = "auto", exclude: bool = False) -> int:
    """``stations x measurements`` (:func:`problem_units`) ``x solves`` (:func:`exclusion_solves`)."""
    return problem_units(method, stations * measurements, measurements) * exclusion_solves(exclude, measurements)


def body_fix_cost(body) -> int:
    """:func:`fix_cost` of a parsed or decoded FixRequest body, as it asks (1 for a body without lists of
    stations and measurements: it is refused before any solve)."""
    stations, measurements = station_count(body), measurement_count(body)
    if stations is None or measurements is None:
        return 1
    method = requested_method(body)
    return fix_cost(stations, measurements, method if type(method) is str else "auto", requests_exclusion(body))


def check_fix(stations: int, measurements: int, method: str, exclude: bool, limit: int | None) -> None:
    """Raise ``ValueError`` (a validation error of the request) when a fix is over ``limit`` (the app's
    ``max_fix_cost``; None: no limit)."""
    cost = fix_cost(stations, measurements, method, exclude)
    if limit is not None and cost > limit:
        units = problem_units(method, stations * measurements, measurements)
        solves = exclusion_solves(exclude, measurements)
        raise ValueError(
            (f"{stations} stations x {measurements} measurements" if units == stations * measurements else
             f"{method} on {measurements} measurements (their pairs: {measurements}^2 / 4)")
            + (f" x {solves} solves (outlier exclusion's refits at most)" if solves > 1 else "")
            + f" = {cost:,}, over the limit max_fix_cost = {limit:,}")


def fix_within_limit(stations: int, measurements: int, method: str, exclude: bool, limit: int | None) -> bool:
    """Whether a fix is within ``limit`` (the app's ``max_fix_cost``; None: no limit)."""
    return limit is None or fix_cost(stations, measurements, method, exclude) <= limit
