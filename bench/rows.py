"""The rows of ``python -m bench``: each measures a thing and its yardstick side by side in one run."""

from __future__ import annotations

import gc
import http.client
import subprocess
import time
from dataclasses import dataclass, field
from pathlib import Path
from urllib.parse import urlsplit

import numpy as np
import orjson

from bench.load import LoadGenerator
from bench.scenarios import four_station_requests

ROOT = Path(__file__).resolve().parents[1]


@dataclass
class Row:
    """One line of the table, and the notes that explain it in ``results.md``."""

    number: int
    what: str
    measured: str
    reference: str
    ratio: str
    target: str
    verdict: str
    notes: list[str] = field(default_factory=list)


def unavailable(number: int, what: str, target: str, reason: str) -> Row:
    return Row(number, what, "not available yet", "-", "-", target, "not measured", [reason])


def committed(*paths: str) -> bool:
    """Whether every path is tracked by git (has landed), not merely present in the work tree."""
    try:
        out = subprocess.run(["git", "ls-files", "--error-unmatch", *paths], cwd=ROOT, capture_output=True,
                             check=False)
    except OSError:
        return False
    return out.returncode == 0


def _post(connection: http.client.HTTPConnection, path: str, body: bytes) -> tuple[int, bytes]:
    connection.request("POST", path, body, {"Content-Type": "application/json"})
    response = connection.getresponse()
    return response.status, response.read()


def _connection(url: str, timeout: float = 300.0) -> http.client.HTTPConnection:
    parts = urlsplit(url)
    return http.client.HTTPConnection(parts.hostname, parts.port, timeout=timeout)


def single_fix_row(url: str, load: LoadGenerator, duration_s: float, connections: int = 16) -> Row:
    """Row 1: /v1/fixes against /bench/echo (same body) and /healthz, back to back on one server."""
    body = orjson.dumps(four_station_requests(1, np.random.default_rng(11))[0])
    connection = _connection(url)
    for path in ("/v1/fixes", "/bench/echo"):
        for _ in range(100):
            status, _ = _post(connection, path, body)
            if status != 200:
                raise RuntimeError(f"warm-up {path} answered {status}")
    connection.close()
    echo = load.run(f"{url}/bench/echo", duration_s, connections, body)
    fix = load.run(f"{url}/v1/fixes", duration_s, connections, body)
    health = load.run(f"{url}/healthz", duration_s, connections)
    ratio = fix.requests_per_s / echo.requests_per_s
    met_ratio, met_p99 = ratio >= 0.60, fix.p99_ms <= 10.0
    verdict = "met" if met_ratio and met_p99 else "missed: " + "; ".join(
        part for part, ok in ((f"{ratio:.2f}x of echo is {0.60 / ratio:.1f}x short of 0.60x", met_ratio),
                              (f"p99 {fix.p99_ms:.1f} ms is {fix.p99_ms / 10.0:.1f}x the 10 ms", met_p99)) if not ok)
    failures = fix.failures + echo.failures + health.failures
    return Row(
        1, f"single ML fix over HTTP (4 stations, 1 worker, c={connections}, {duration_s:g} s each)",
        f"{fix.requests_per_s:,.0f} req/s, p50 {fix.p50_ms:.1f} ms, p99 {fix.p99_ms:.1f} ms",
        f"echo {echo.requests_per_s:,.0f} req/s (p50 {echo.p50_ms:.1f}, p99 {echo.p99_ms:.1f} ms); "
        f"healthz {health.requests_per_s:,.0f} req/s (p50 {health.p50_ms:.1f}, p99 {health.p99_ms:.1f} ms)",
        f"{ratio:.2f}x echo", ">= 0.60x echo, p99 <= 10 ms", verdict,
        [f"body {len(body)} bytes; load generator {fix.generator}; non-2xx or socket errors: {failures}"])


def _phase_times(problems: list) -> dict[str, float]:
    """Where a batch's server time goes, phase by phase, measured in this process (GC paused as the route does)."""
    from core.batch import size_groups
    from core.estimators import SolveOptions
    from core.estimators.ml import solve_ml_problem_batch
    from service.responses import JsonResponse
    from service.translate import fix_batch_to_dicts, to_problem_batch

    raw = orjson.dumps({"problems": problems})
    times: dict[str, float] = {}
    gc.collect()
    gc.disable()
    try:
        t = time.perf_counter()
        parsed = orjson.loads(raw)["problems"]
        times["parse JSON (orjson)"] = time.perf_counter() - t
        t = time.perf_counter()
        slots, options, formats, batch, rest = to_problem_batch(parsed)
        times["read + build batch (lean reader, geodesy)"] = time.perf_counter() - t
        t = time.perf_counter()
        solved = [(group, solve_ml_problem_batch(batch.take(group), SolveOptions()))
                  for group in size_groups(batch.n_measurements, batch.n_stations)]
        times["core: start + LM + finish"] = time.perf_counter() - t
        t = time.perf_counter()
        bodies = [fix_batch_to_dicts(fixes, [formats[i] for i in group]) for group, fixes in solved]
        times["response dicts (summaries, geodetic, dicts)"] = time.perf_counter() - t
        t = time.perf_counter()
        results = [{"index": i, "ok": True, "fix": b} for part in bodies for i, b in enumerate(part)]
        JsonResponse({"results": results})
        times["serialise (orjson)"] = time.perf_counter() - t
    finally:
        gc.enable()
    if rest:
        raise RuntimeError(f"{len(rest)} benchmark problems left the lean path")
    return times


def batch_row(url: str, size: int, repeats: int = 5) -> tuple[Row, float, list]:
    """Row 2: one POST of ``size`` four-station problems, end to end; and the core's own time per fix."""
    from core.estimators import SolveOptions
    from core.estimators.ml import solve_ml_problem_batch
    from service.translate import to_problem_batch

    problems = four_station_requests(size, np.random.default_rng(22))
    body = orjson.dumps({"problems": problems})
    connection = _connection(url)
    status, data = _post(connection, "/v1/fixes/batch", body)
    if status != 200:
        raise RuntimeError(f"batch answered {status}: {data[:300]!r}")
    results = orjson.loads(data)["results"]
    ok = sum(r["ok"] for r in results)
    elapsed = []
    for _ in range(repeats):
        t = time.perf_counter()
        status, data = _post(connection, "/v1/fixes/batch", body)
        elapsed.append(time.perf_counter() - t)
    connection.close()
    http_s = float(np.median(elapsed))

    _, _, _, batch, _ = to_problem_batch(problems)
    core_runs = []
    for _ in range(repeats):
        gc.collect()
        t = time.perf_counter()
        solve_ml_problem_batch(batch, SolveOptions())
        core_runs.append(time.perf_counter() - t)
    core_s = float(np.median(core_runs))
    phases = _phase_times(problems)
    rate = size / http_s
    verdict = "met" if rate >= 20_000 else f"missed: {rate:,.0f}/s is {20_000 / rate:.1f}x short of 20,000/s"
    notes = [f"request {len(body) / 1e6:.1f} MB, response {len(data) / 1e6:.1f} MB; {ok}/{size} ok; "
             f"HTTP times (s) of {repeats} posts: " + ", ".join(f"{e:.3f}" for e in elapsed),
             "server-side phases of the same batch in this process (s): "
             + "; ".join(f"{k} {v:.3f}" for k, v in phases.items())]
    row = Row(2, f"batch of {size:,} four-station ML fixes over HTTP (one POST)",
              f"{rate:,.0f} fixes/s end to end ({http_s:.3f} s per POST)",
              f"core only: {core_s / size * 1e6:.1f} us per fix ({size / core_s:,.0f} fixes/s)",
              f"core is {core_s / http_s:.0%} of HTTP", ">= 20,000 fixes/s", verdict, notes)
    return row, core_s, problems


def scipy_row(problems: list, core_s: float) -> Row:
    """Row 3: the same problems one by one with ``scipy.optimize.least_squares`` (what a user would write)."""
    from scipy.optimize import least_squares

    from core.estimators.start import initial_positions
    from core.measurements import Kind
    from service.translate import to_problem_batch

    _, _, _, batch, _ = to_problem_batch(problems)
    starts, _, _ = initial_positions(batch)
    stations, rotations = batch.measurement_stations()
    is_azimuth = batch.kinds == Kind.AZIMUTH
    size = batch.size

    def residual(p, stations, rotations, azimuth, values, sigmas):
        d = np.einsum("mij,mj->mi", rotations, p - stations)
        predicted = np.where(azimuth, np.arctan2(d[:, 0], d[:, 1]), np.arctan2(d[:, 2], np.hypot(d[:, 0], d[:, 1])))
        return (np.mod(values - predicted + np.pi, 2 * np.pi) - np.pi) / sigmas

    positions = np.empty((size, 3))
    t = time.perf_counter()
    for b in range(size):
        m = int(batch.n_measurements[b])
        args = (stations[b, :m], rotations[b, :m], is_azimuth[b, :m], batch.values[b, :m], batch.sigmas[b, :m])
        positions[b] = least_squares(residual, starts[b], args=args, method="lm").x
    scipy_s = time.perf_counter() - t

    from core.estimators import SolveOptions
    from core.estimators.ml import solve_ml_problem_batch

    ours = solve_ml_problem_batch(batch, SolveOptions()).position_enu_m
    gap = np.linalg.norm(positions - ours, axis=-1)
    ratio = scipy_s / core_s
    verdict = "met" if ratio >= 100 else f"missed: {ratio:.0f}x is {100 / ratio:.1f}x short of 100x"
    return Row(3, f"the same {size:,} problems one by one with scipy.optimize.least_squares (method lm)",
               f"{scipy_s / size * 1e6:,.0f} us per fix ({scipy_s:.1f} s)",
               f"batched core {core_s / size * 1e6:.1f} us per fix (row 2)", f"{ratio:,.0f}x faster",
               ">= 100x", verdict,
               ["scipy gets the position only (no covariance, CRLB, residual report or warnings), finite-"
                "difference Jacobians, and starts from our weighted-EOVE start (not timed): the most generous "
                f"baseline. Median |scipy - ours| = {np.median(gap) * 1e3:.2f} mm (max {gap.max():.3f} m)."])


def paper_002_row() -> Row:
    """Row 6: paper 002's grid, 441 points x 1000 trials of ``los_intersection``."""
    what = "paper 002 grid: 441 points x 1000 trials of los_intersection"
    target = "<= 10 s"
    if not committed("core/estimators/line_of_sight_intersection.py"):
        return unavailable(6, what, target, "core/estimators/line_of_sight_intersection.py has not landed")
    from core.crlb import information_at
    from core.estimators.line_of_sight_intersection import intersect_lines_of_sight
    from core.problem import Bearing, LocalPoint, build_problem
    from core.simulation.measurements import draw_noise, true_values

    stations = [("s1", LocalPoint(0.0, 0.0, 0.0)), ("s2", LocalPoint(10_000.0, 0.0, 0.0)),
                ("s3", LocalPoint(5_000.0, 10_000.0, 0.0))]
    problem = build_problem(stations, [Bearing(sid, 0.0, 0.0, 0.010, 0.010) for sid, _ in stations])
    rng = np.random.default_rng(2002)
    grid = np.arange(0.0, 10_000.0 + 1.0, 500.0)
    ratios = []
    t = time.perf_counter()
    for east in grid:
        for north in grid:
            target_enu = np.array([east, north, 500.0])
            result = intersect_lines_of_sight(problem, true_values(problem, target_enu)
                                              + draw_noise(rng, problem.sigmas, size=1000))
            squared = np.sum((result.position_enu_m - target_enu) ** 2, axis=1)
            ratios.append(np.nanmean(squared) / np.trace(information_at(problem, target_enu).covariance_enu_m2[0]))
    elapsed = time.perf_counter() - t
    verdict = "met" if elapsed <= 10.0 else f"missed: {elapsed:.1f} s is {elapsed / 10:.1f}x the 10 s"
    return Row(6, what, f"{elapsed:.2f} s ({elapsed / (grid.size ** 2) * 1e3:.1f} ms per point)",
               "-", "-", target, verdict,
               [f"{grid.size ** 2} points (0.5 km grid over [0, 10]^2 km, height 0.5 km), 1000 noise draws each, "
                f"intersection + CRLB per point; median MSE/trace(CRLB) {np.median(ratios):.3f}"])


def session_rows(load: LoadGenerator, duration_s: float) -> list[Row]:
    """Row 4: session epochs/s over HTTP (SQLite with 1 and 10 epochs per request, Redis)."""
    what = "session epochs/s over HTTP (SQLite: 1 and 10 epochs/request; Redis)"
    if not committed("service/routes/sessions.py", "core/tracking/session.py"):
        return [unavailable(4, what, "-", "the sessions routes (service/routes/sessions.py) and the filters "
                                          "(core/tracking) have not landed in git yet")]
    return [unavailable(4, what, "-", "sessions landed after this benchmark was written")]


def filter_step_row() -> Row:
    """Row 5: one filter step of the session model in core next to filterpy's UKF doing the same step."""
    what = "one session filter step in core vs filterpy UnscentedKalmanFilter"
    if not committed("core/tracking/session.py"):
        return unavailable(5, what, "<= 1/5 of filterpy", "core/tracking (the session filters) has not landed "
                                                          "in git yet")
    return unavailable(5, what, "<= 1/5 of filterpy", "core/tracking landed after this benchmark was written")
