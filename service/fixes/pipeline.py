"""The fix road, top to bottom: decode, read into one core batch, solve, summarise, write.

:func:`fix_results` is its one entry point, called by ``POST /v1/fixes`` (through
:class:`service.fixes.coalesce.Coalescer`) and ``POST /v1/fixes/batch``:

1. decode: the routes decode bodies into typed structs (:mod:`service.fixes.decode`);
2. read: :func:`service.fixes.read.read_fix_requests` reads them into one core batch under the
   request's rules (:mod:`service.fixes.rules`);
3. solve: :func:`core.estimators.iter_solutions` solves it part by part;
4. summarise and write: :func:`service.fixes.write.fix_bodies` has the core summarise each part's fixes
   (:func:`core.fix_summary.summary_kernel`: in the axes at each fix, on the earth, with their error figures)
   and writes every fix body, and its renderings, from those arrays.

Responses are plain dicts and JSON texts (serialised by orjson) rather than
re-validated models: the schema documents them and the tests check that
every response validates against it.
"""

from __future__ import annotations

import logging

import numpy as np

from core import kernels as core_kernels
from core.errors import LocalizationError
from core.estimators import PART_PROBLEMS, iter_solutions, resolve_methods
from core.parallel import Stopped
from core.problem.batch import size_groups
from service.fixes import decode
from service.fixes.read import read_fix_requests
from service.fixes.write import fix_bodies
from service.web.problems import for_request, localization_problem, problem_body

logger = logging.getLogger("passive_locator")


#: Fix bodies that reach every kernel of this module: geodetic and local frames, every measurement kind, an
#: azimuth without a sigma, a known altitude, renderings, and a body the lean reader hands to the schema.
_WARM_BODIES = [
    {"frame": "wgs84", "formats": ["geojson", "cot"],
     "stations": [{"id": "a", "position": {"lat_deg": 34.0, "lon_deg": 108.0, "alt_m": 400.0}},
                  {"id": "b", "position": {"lat_deg": 34.1, "lon_deg": 108.2, "alt_m": 450.0}},
                  {"id": "c", "position": {"lat_deg": 34.2, "lon_deg": 108.0}}],
     "measurements": [{"type": "bearing", "station_id": "a", "azimuth_deg": 45.0, "elevation_deg": 1.0,
                       "sigma_azimuth_deg": 0.5, "sigma_elevation_deg": 0.5},
                      {"type": "bearing", "station_id": "b", "azimuth_deg": 330.0, "sigma_azimuth_deg": 0.5},
                      {"type": "range", "station_id": "c", "range_m": 20000.0, "sigma_m": 50.0},
                      {"type": "toa", "station_id": "a", "toa_s": 1e-4, "sigma_s": 1e-7},
                      {"type": "toa", "station_id": "b", "toa_s": 1.2e-4, "sigma_s": 1e-7}]},
    {"frame": "local", "method": "taylor_wls", "constraints": {"altitude_m": 1000.0},
     "stations": [{"id": "a", "position": {"east_m": 0.0, "north_m": 0.0}},
                  {"id": "b", "position": {"east_m": 10000.0, "north_m": 0.0}},
                  {"id": "c", "position": {"east_m": 0.0, "north_m": 10000.0, "up_m": 50.0}}],
     "measurements": [{"type": "bearing", "station_id": s, "azimuth_deg": a} for s, a in
                      (("a", 40.0), ("b", 300.0), ("c", 150.0))]},
    {"stations": [], "measurements": []},
]


def compile_kernels() -> None:
    """Compile (or load from numba's on-disk cache) every kernel a request can reach: the core's
    (:func:`core.kernels.compile_kernels`) and this module's, by reading, solving and writing
    :data:`_WARM_BODIES`. Run at install and image build time (which fill the cache) and in the lifespan."""
    core_kernels.compile_kernels()
    fix_results(_WARM_BODIES)


def fix_results(bodies: list, request_ids=None, should_stop=None, methods_run: list | None = None,
                max_fix_cost: int | None = None) -> list[dict]:
    """Results of FixRequest bodies (see :func:`read_fix_requests`): read, solved and written as one batch.

    A failure that is no problem's own error (a bug) fails only the bodies
    that meet it: the shared call's exception is logged, each body is then
    solved alone, and a body that fails alone too gets a 500
    ``internal_error`` in its slot (logged with its request id).

    Parameters
    ----------
    bodies : list
        Parsed JSON of each request.
    request_ids : str or sequence of str, optional
        Written into each error body (one for all, or one per body).
    should_stop : callable returning bool, optional
        Asked before each part is solved (:func:`core.estimators.iter_solutions`: deadline, disconnect,
        shutdown).
    methods_run : list, optional
        Replaced by the method of each body, in order, whatever its outcome: the estimator that ran (``auto``
        resolved), or the requested method of a body refused before solving (what metrics count a fix under).
    max_fix_cost : int, optional
        The app's ``max_fix_cost``: a body over it fails its slot (422); None: no limit.

    Returns
    -------
    list of dict
        ``{"index", "ok": True, "fix"}`` or ``{"index", "ok": False, "error"}`` per body, in order.

    Raises
    ------
    core.parallel.Stopped
        When ``should_stop`` said so.
    """
    if request_ids is None or isinstance(request_ids, str):
        request_ids = [request_ids] * len(bodies)
    ran: list = [None] * len(bodies)
    results = None
    if len(bodies) > 1:
        try:
            results = _shared_results(bodies, request_ids, should_stop, ran, max_fix_cost)
        except Stopped:
            raise
        except Exception:
            logger.exception("shared solve of %d fixes failed; solving each alone", len(bodies))
    if results is None:
        results = [{**_alone(body, request_id, should_stop, ran, slot, max_fix_cost), "index": slot}
                   for slot, (body, request_id) in enumerate(zip(bodies, request_ids))]
    if methods_run is not None:
        methods_run[:] = ran
    return results


def _alone(body, request_id: str | None, should_stop, ran: list, slot: int, max_fix_cost: int | None) -> dict:
    """One body's result, solved alone (its method set in ``ran[slot]``); a bug is its slot's 500 ``internal_error``."""
    one = [None]
    try:
        return _shared_results([body], [request_id], should_stop, one, max_fix_cost)[0]
    except Stopped:
        raise
    except Exception:
        logger.exception("fix failed", extra={"request_id": request_id})
        return {"ok": False, "error": problem_body(500, "internal_error",
                                                   f"internal error; quote request id {request_id}",
                                                   request_id=request_id)}
    finally:
        ran[slot] = one[0] if one[0] is not None else decode.requested_method(body)


def _shared_results(bodies: list, request_ids: list, should_stop, ran: list, max_fix_cost: int | None) -> list[dict]:
    """:func:`fix_results` as one shared read, solve and write (chunk by chunk), which any exception fails whole.

    ``ran[slot]`` is set to the method each body ran with (the requested one when it was refused before solving).
    """
    results: list[dict | None] = [None] * len(bodies)

    def put(slot: int, result: dict, method) -> None:
        if not result["ok"]:
            for_request(result["error"], request_ids[slot])
        results[slot] = {"index": slot, **result}
        ran[slot] = method

    # Read in chunks of a solve part, each set solving on the solver threads while the next one is read
    # (reading holds the GIL, the compiled solves do not), then write every chunk's fixes in turn.
    chunks = [group[start:start + PART_PROBLEMS] for group in _size_classes(bodies)
              for start in range(0, len(group), PART_PROBLEMS)]
    started = []
    try:
        for chunk in chunks:
            read = read_fix_requests([bodies[slot] for slot in chunk], max_fix_cost)
            for j, error in read.errors.items():
                put(chunk[j], {"ok": False, "error": error}, decode.requested_method(bodies[chunk[j]]))
            if read.batch is not None:
                started.append((chunk, read, iter_solutions(read.batch, read.methods, read.options, should_stop,
                                                            background=len(chunks) > 1)))
        for chunk, read, solutions in started:
            for rows, fixes in solutions:
                if isinstance(fixes, LocalizationError):
                    resolved = resolve_methods(read.batch, read.methods)
                    for r in rows.tolist():
                        put(chunk[read.slots[r]], {"ok": False, "error": localization_problem(fixes)}, resolved[r])
                    continue
                for r, result in zip(rows.tolist(), fix_bodies(fixes, [read.formats[r] for r in rows])):
                    put(chunk[read.slots[r]], result, fixes.method)
    finally:
        for *_, solutions in started:
            solutions.close()
    return results


def _size_classes(bodies: list) -> list[list[int]]:
    """The slots of ``bodies`` in groups of like size, each to be read as one batch.

    A batch pads every problem to its largest, so reading all at once made
    memory grow with the number of problems times the largest one: 9,000
    four-bearing problems and one of 1,024 bearings took 750 MB more than
    the 9,000 alone, and twice the time. Grouped by
    :func:`core.problem.batch.size_groups` on each body's station and
    measurement counts (a bearing is one or two rows), a problem is padded
    to at most four times its own rows. Anything but a problem counts as size 1.
    """
    stations = np.ones(len(bodies), dtype=np.intp)
    measurements = np.ones(len(bodies), dtype=np.intp)
    for slot, body in enumerate(bodies):
        if type(body) is decode.FixBody:
            stations[slot], measurements[slot] = len(body.stations), len(body.measurements)
        elif type(body) is dict:
            listed = body.get("stations"), body.get("measurements")
            if type(listed[0]) is list:
                stations[slot] = len(listed[0])
            if type(listed[1]) is list:
                measurements[slot] = len(listed[1])
    return [group.tolist() for group in size_groups(measurements, stations)]
