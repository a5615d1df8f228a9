"""The rows of ``python -m bench``: each measures a thing and its yardstick side by side in one run."""

from __future__ import annotations

import gc
import http.client
import importlib
import math
import os
import subprocess
import time
from dataclasses import dataclass, field
from pathlib import Path
from urllib.parse import urlsplit

import numpy as np
import orjson

from bench.load import LoadGenerator
from bench.scenarios import four_station_requests
from bench.server import serve

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


def _combined(runs) -> tuple[float, float, float, int]:
    """Requests/s over all runs, median p50, worst p99, failures."""
    seconds = sum(r.requests / r.requests_per_s for r in runs)
    return (sum(r.requests for r in runs) / seconds, float(np.median([r.p50_ms for r in runs])),
            max(r.p99_ms for r in runs), sum(r.failures for r in runs))


def _single_phase_times(count: int = 300) -> dict[str, float]:
    """Where one fix's server time goes (us), phase by phase, in this process: the route's own steps."""
    from core.error_summary import error_summary
    from core.estimators import solve_many
    from service.fixes.decode import decode_fix
    from service.fixes.read import read_fix_requests
    from service.fixes.write import fix_bodies
    from service.web.deps import parse_json
    from service.web.responses import JsonResponse

    bodies = [orjson.dumps(b) for b in four_station_requests(count, np.random.default_rng(12))]
    error_summary(np.eye(3))  # its interpolation tables are built once per process, on first use: not per fix
    totals = dict.fromkeys(("decode (msgspec)", "read (reader, geodesy)", "solve (start + LM + finish)",
                            "bodies (summaries, dicts)", "serialise (orjson)"), 0.0)
    for body in bodies[:30]:  # warm up as row 7 does (first calls after import resolve types and fill caches)
        read = read_fix_requests([decode_fix(body) or parse_json(body)])
        fix_bodies(solve_many(read.batch, read.methods, read.options)[0][1], read.formats)
    for body in bodies:
        t0 = time.perf_counter()
        parsed = decode_fix(body) or parse_json(body)
        t1 = time.perf_counter()
        read = read_fix_requests([parsed])
        t2 = time.perf_counter()
        ((_, fixes),) = solve_many(read.batch, read.methods, read.options)
        t3 = time.perf_counter()
        out = fix_bodies(fixes, read.formats)
        t4 = time.perf_counter()
        JsonResponse(out[0]["fix"])
        t5 = time.perf_counter()
        for key, dt in zip(totals, (t1 - t0, t2 - t1, t3 - t2, t4 - t3, t5 - t4)):
            totals[key] += dt
    return {k: v / count * 1e6 for k, v in totals.items()}


#: A pause before each call in :func:`_thread_hop_times`, as a server idles between the requests of one client.
IDLE_BETWEEN_S = 200e-6


def _thread_hop_times(count: int = 300, rounds: int = 3) -> dict[str, float]:
    """What the hop to a worker thread costs one fix, in this process (us): ``fix_results`` of one body run on the
    caller's thread (back to back, and after a short sleep each), then awaited from an event loop through a
    one-thread executor (as the route does), and a call that does nothing sent the same way. Medians of
    per-request figures; thread CPU from ``thread_time``."""
    import asyncio
    from concurrent.futures import ThreadPoolExecutor

    from service.fixes.pipeline import fix_results

    bodies = four_station_requests(count, np.random.default_rng(14))
    cpu: list[float] = []

    def solve(body):
        t = time.thread_time()
        fix_results([body])
        cpu.append(time.thread_time() - t)

    for body in bodies[:30]:
        solve(body)
    cpu.clear()
    wall = []
    for body in bodies * rounds:
        t = time.perf_counter()
        solve(body)
        wall.append(time.perf_counter() - t)
    inline_wall, inline_cpu = float(np.median(wall)), float(np.median(cpu))
    cpu.clear()
    for body in bodies * rounds:
        time.sleep(IDLE_BETWEEN_S)
        solve(body)
    idle_cpu = float(np.median(cpu))

    async def hopped():
        loop = asyncio.get_running_loop()
        with ThreadPoolExecutor(1) as pool:
            for body in bodies[:30]:
                await loop.run_in_executor(pool, solve, body)
            cpu.clear()
            walls, empty = [], []
            for body in bodies * rounds:
                t = time.perf_counter()
                await loop.run_in_executor(pool, solve, body)
                walls.append(time.perf_counter() - t)
            for _ in range(count * rounds):
                t = time.perf_counter()
                await loop.run_in_executor(pool, int)
                empty.append(time.perf_counter() - t)
        return float(np.median(walls)), float(np.median(cpu)), float(np.median(empty))

    try:
        import uvloop  # what uvicorn runs when it is installed
        run = uvloop.run
    except ImportError:
        run = asyncio.run
    hop_wall, hop_cpu, empty = run(hopped())
    return {"on the caller's thread: wall": inline_wall * 1e6, "thread CPU": inline_cpu * 1e6,
            f"thread CPU when the thread sleeps {IDLE_BETWEEN_S * 1e6:.0f} us before each": idle_cpu * 1e6,
            "through the executor: wall": hop_wall * 1e6, "worker thread CPU": hop_cpu * 1e6,
            "an empty call through the executor: wall": empty * 1e6}


def single_fix_row(url: str, load: LoadGenerator, duration_s: float, connections: int, rounds: int = 5) -> Row:
    """Row 1: /v1/fixes against ``GET /healthz`` (and /bench/echo and /bench/echo_inline, same body:
    ``bench.app``), interleaved in rounds on one server.

    Each route gets ``duration_s`` in all, as ``rounds`` runs taken in turn (healthz, fix, echo, echo_inline,
    healthz, ...), so a burst of load from elsewhere on the machine hits all four alike.
    """
    target = 0.5 if connections == 1 else 0.6
    body = orjson.dumps(four_station_requests(1, np.random.default_rng(11))[0])
    connection = _connection(url)
    for path in ("/v1/fixes", "/bench/echo", "/bench/echo_inline"):
        for _ in range(100):
            status, _ = _post(connection, path, body)
            if status != 200:
                raise RuntimeError(f"warm-up {path} answered {status}")
    connection.close()
    rounds = max(1, min(rounds, int(duration_s)))
    each = max(1, int(duration_s // rounds))
    runs = {"echo": [], "inline": [], "fix": [], "healthz": []}
    for _ in range(rounds):
        runs["healthz"].append(load.run(f"{url}/healthz", each, connections))
        runs["fix"].append(load.run(f"{url}/v1/fixes", each, connections, body))
        runs["echo"].append(load.run(f"{url}/bench/echo", each, connections, body))
        runs["inline"].append(load.run(f"{url}/bench/echo_inline", each, connections, body))
    (fix_rps, fix_p50, fix_p99, fix_fail), (echo_rps, echo_p50, echo_p99, echo_fail), \
        (inline_rps, _, _, inline_fail), (health_rps, health_p50, health_p99, health_fail) = (
            _combined(runs[k]) for k in ("fix", "echo", "inline", "healthz"))
    ratio = fix_rps / health_rps
    per_round = [f.requests_per_s / h.requests_per_s for f, h in zip(runs["fix"], runs["healthz"])]
    verdict = "met" if ratio >= target else f"missed: {ratio:.2f}x of healthz is {target / ratio:.1f}x short of {target}x"
    if ratio < target and echo_rps / health_rps < target:
        verdict += (f"; out of reach on this route's shape: with a solve that costs nothing (/bench/echo) it reaches "
                    f"{echo_rps / health_rps:.2f}x")
    return Row(
        1, f"single ML fix over HTTP (4 stations, 1 worker, c={connections}, {duration_s:g} s per route "
           f"in {rounds} interleaved rounds)",
        f"{fix_rps:,.0f} req/s, p50 {fix_p50:.1f} ms, p99 {fix_p99:.1f} ms",
        f"healthz {health_rps:,.0f} req/s (p50 {health_p50:.1f}, p99 {health_p99:.1f} ms)",
        f"{ratio:.2f}x healthz", f">= {target}x healthz", verdict,
        [f"c={connections}: body {len(body)} bytes; load generator {runs['fix'][0].generator}; non-2xx or socket "
         f"errors: {fix_fail + echo_fail + inline_fail + health_fail}; fix/healthz per round: "
         + ", ".join(f"{r:.2f}" for r in per_round)
         + f"; the same body to /bench/echo (the fix route's shape with a solve that costs nothing: parse, a hop to "
         f"a worker thread and back per request, answer): {echo_rps:,.0f} req/s = {echo_rps / health_rps:.2f}x "
         f"healthz (fix/echo {fix_rps / echo_rps:.2f}x; the fix route's coalescer shares one hop among the requests "
         "queued together); /bench/echo_inline (echo without the hop, the solve's place on the loop): "
         f"{inline_rps:,.0f} req/s = {inline_rps / health_rps:.2f}x healthz, so the hop costs "
         f"{1e6 / echo_rps - 1e6 / inline_rps:.0f} us a request"]
        + ([] if connections != 1 else [
            "one fix's server-side work in this process (us): "
            + "; ".join(f"{k} {v:.0f}" for k, v in _single_phase_times().items()),
            "one fix_results of one body in this process, median per request (us): "
            + "; ".join(f"{k} {v:.0f}" for k, v in _thread_hop_times().items())]))


def core_single_row(count: int = 300, rounds: int = 5) -> Row:
    """Row 7: one four-station ML fix in core, one call per problem, reading the request included.

    Each call reads the request's stations and bearings into the common frame (exact geodesy) and solves
    it as a batch of one (start, LM, finish with CRLB, residuals and warnings): what ``POST /v1/fixes`` costs
    apart from HTTP and JSON.
    """
    from core.error_summary import error_summary
    from core.estimators import solve_many
    from service.fixes.read import read_fix_requests

    requests = four_station_requests(count, np.random.default_rng(13))
    error_summary(np.eye(3))

    def one(request):
        read = read_fix_requests([request])
        return solve_many(read.batch, read.methods, read.options)

    for request in requests[:20]:
        one(request)
    per_fix, build = [], []
    for _ in range(rounds):
        t = time.perf_counter()
        for request in requests:
            one(request)
        per_fix.append((time.perf_counter() - t) / count * 1e6)
        t = time.perf_counter()
        for request in requests:
            read_fix_requests([request])
        build.append((time.perf_counter() - t) / count * 1e6)
    us = float(np.median(per_fix))
    verdict = "met" if us <= 100 else f"missed: {us:,.0f} us is {us / 100:.1f}x the 100 us"
    return Row(7, "one 4-station ML fix in core, one call per problem (reading the request into the frame included)",
               f"{us:,.0f} us per fix (median of {rounds} rounds of {count})",
               f"of which reading/building {float(np.median(build)):,.0f} us", "-", "<= 100 us", verdict,
               ["rounds (us per fix): " + ", ".join(f"{x:,.0f}" for x in per_fix)])


def _phase_times(problems: list) -> dict[str, float]:
    """Where a batch's server time goes, phase by phase, measured in this process (GC paused as the route does)."""
    from core.estimators import solve_many
    from service.fixes.decode import decode_batch
    from service.fixes.read import read_fix_requests
    from service.fixes.write import fix_bodies
    from service.web.responses import JsonResponse

    raw = orjson.dumps({"problems": problems})
    times: dict[str, float] = {}
    gc.collect()
    gc.disable()
    try:
        t = time.perf_counter()
        parsed = decode_batch(raw)
        times["decode JSON (msgspec structs)"] = time.perf_counter() - t
        t = time.perf_counter()
        read = read_fix_requests(parsed)
        times["read + build batch (reader, geodesy)"] = time.perf_counter() - t
        t = time.perf_counter()
        solved = solve_many(read.batch, read.methods, read.options)
        times["core: start + LM + finish"] = time.perf_counter() - t
        t = time.perf_counter()
        bodies = [fix_bodies(fixes, [read.formats[i] for i in rows]) for rows, fixes in solved]
        times["response dicts (summaries, geodetic, dicts)"] = time.perf_counter() - t
        t = time.perf_counter()
        results = [{"index": i, **b} for part in bodies for i, b in enumerate(part)]
        JsonResponse({"results": results})
        times["serialise (orjson)"] = time.perf_counter() - t
    finally:
        gc.enable()
    if len(read.slots) != len(problems) or read.errors:
        raise RuntimeError(f"{len(problems) - len(read.slots)} benchmark problems were not read")
    return times


#: The closed forms of the batch row (its target covers ML and every closed form), each measured like ML.
CLOSED_FORMS = ("weighted_eove", "eove", "los_intersection", "ple3d", "ws3d", "angle_range", "tls", "ctls",
                "taylor_wls")


def batch_row(url: str, size: int, method: str = "ml", repeats: int = 3) -> tuple[Row, float, list]:
    """Row 2: one POST of ``size`` four-station problems for ``method``, to the last byte of the answer."""
    from core.estimators import MAX_WORKERS, SolveOptions, solve_many
    from service.fixes.read import read_fix_requests

    target = 25_000 if method == "ml" else 20_000
    problems = four_station_requests(size, np.random.default_rng(22), method=method)
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

    batch = read_fix_requests(problems).batch
    core_runs = []
    gc.collect()
    gc.freeze()
    for _ in range(repeats):
        t = time.perf_counter()
        solve_many(batch, method, SolveOptions())
        core_runs.append(time.perf_counter() - t)
    gc.unfreeze()
    core_s = float(np.median(core_runs))
    rate = size / http_s
    if ok < size:
        verdict = f"not measured: only {ok:,} of {size:,} problems gave a fix"
    else:
        verdict = "met" if rate >= target else f"missed: {rate:,.0f}/s is {1 - rate / target:.0%} short of {target:,}/s"
    notes = [f"{method}: request {len(body) / 1e6:.1f} MB, response {len(data) / 1e6:.1f} MB; {ok}/{size} ok; "
             f"HTTP times (s) of {repeats} posts: " + ", ".join(f"{e:.3f}" for e in elapsed)]
    if method == "ml":
        notes.append("server-side phases of the same batch in this process, on one thread (the route overlaps "
                     "the core and the summaries of later parts with the bodies of earlier ones on two threads) (s): "
                     + "; ".join(f"{k} {v:.3f}" for k, v in _phase_times(problems).items()))
    row = Row(2, f"batch of {size:,} four-station `{method}` fixes over HTTP (one POST)",
              f"{rate:,.0f} fixes/s end to end ({http_s:.3f} s per POST)",
              f"core only (solve_many: estimate + finish, parts on {MAX_WORKERS} threads): {core_s / size * 1e6:.1f} us "
              f"per fix ({size / core_s:,.0f} fixes/s)",
              f"core is {core_s / http_s:.0%} of HTTP", f">= {target:,} fixes/s", verdict, notes)
    return row, core_s, problems


def scipy_row(problems: list, rounds: int = 10) -> Row:
    """Row 3: the same problems one by one with ``scipy.optimize.least_squares`` (what a user would write).

    The problems are split into ``rounds`` slices; each round times the batched core on all of them and
    then scipy on one slice, so every ratio compares two timings taken moments apart.
    """
    from scipy.optimize import least_squares

    from core.estimators import MAX_WORKERS, SolveOptions, solve_many
    from core.estimators.starting_points import initial_positions
    from core.measurements import Kind
    from service.fixes.read import read_fix_requests

    batch = read_fix_requests(problems).batch
    starts, _, _ = initial_positions(batch)
    stations, rotations = batch.measurement_stations()
    is_azimuth = batch.kinds == Kind.AZIMUTH
    size = batch.size

    def residual(p, stations, rotations, azimuth, values, sigmas):
        d = np.einsum("mij,mj->mi", rotations, p - stations)
        predicted = np.where(azimuth, np.arctan2(d[:, 0], d[:, 1]), np.arctan2(d[:, 2], np.hypot(d[:, 0], d[:, 1])))
        return (np.mod(values - predicted + np.pi, 2 * np.pi) - np.pi) / sigmas

    positions = np.empty((size, 3))
    ratios, scipy_total, core_total, ours = [], 0.0, 0.0, None
    gc.collect()
    gc.freeze()  # the request dicts of row 2 would otherwise be rescanned by every full collection
    for part in np.array_split(np.arange(size), rounds):
        t = time.perf_counter()
        solved = solve_many(batch, "ml", SolveOptions())
        core_s = time.perf_counter() - t
        ours = np.empty((size, 3))
        for rows, fixes in solved:
            ours[rows] = fixes.position_enu_m
        t = time.perf_counter()
        for b in part:
            m = int(batch.n_measurements[b])
            args = (stations[b, :m], rotations[b, :m], is_azimuth[b, :m], batch.values[b, :m], batch.sigmas[b, :m])
            positions[b] = least_squares(residual, starts[b], args=args, method="lm").x
        scipy_s = time.perf_counter() - t
        ratios.append((scipy_s / part.size) / (core_s / size))
        scipy_total += scipy_s
        core_total += core_s
    gc.unfreeze()
    gap = np.linalg.norm(positions - ours, axis=-1)
    ratio = float(np.median(ratios))
    verdict = "met" if ratio >= 100 else f"missed: {ratio:.0f}x is {100 / ratio:.1f}x short of 100x"
    return Row(3, f"the same {size:,} problems one by one with scipy.optimize.least_squares (method lm)",
               f"{scipy_total / size * 1e6:,.0f} us per fix ({scipy_total:.1f} s)",
               f"batched core (solve_many, parts on {MAX_WORKERS} threads) {core_total / rounds / size * 1e6:.1f} us "
               f"per fix (all {size:,}, once per round)",
               f"{ratio:,.0f}x faster (median of {rounds} rounds)", ">= 100x", verdict,
               ["scipy gets the position only (no covariance, CRLB, residual report or warnings), finite-"
                "difference Jacobians, and starts from our weighted-EOVE start (not timed): the most generous "
                f"baseline. Per-round ratios: {', '.join(f'{r:.0f}' for r in ratios)}. "
                f"Median |scipy - ours| = {np.median(gap) * 1e3:.2f} mm (max {gap.max():.3f} m)."])


def paper_002_row() -> Row:
    """Row 6: paper 002's grid, 441 points x 1000 trials of ``los_intersection``."""
    what = "paper 002 grid: 441 points x 1000 trials of los_intersection"
    target = "<= 10 s"
    if not committed("core/estimators/methods/line_of_sight_intersection.py"):
        return unavailable(6, what, target, "core/estimators/methods/line_of_sight_intersection.py has not landed")
    from core.crlb import information_at
    from core.estimators.methods.line_of_sight_intersection import intersect_lines_of_sight
    from core.problem.build import Bearing, build_problem
    from core.problem.frame import LocalPoint
    from core.simulation.measurements import draw_noise, trial_batch, true_values

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
            result = intersect_lines_of_sight(trial_batch(problem, true_values(problem, target_enu)
                                                          + draw_noise(rng, problem.sigmas, size=1000)))
            squared = np.sum((result.position_enu_m - target_enu) ** 2, axis=1)
            ratios.append(np.nanmean(squared) / np.trace(information_at(problem, target_enu).covariance_enu_m2[0]))
    elapsed = time.perf_counter() - t
    verdict = "met" if elapsed <= 10.0 else f"missed: {elapsed:.1f} s is {elapsed / 10:.1f}x the 10 s"
    return Row(6, what, f"{elapsed:.2f} s ({elapsed / (grid.size ** 2) * 1e3:.1f} ms per point)",
               "-", "-", target, verdict,
               [f"{grid.size ** 2} points (0.5 km grid over [0, 10]^2 km, height 0.5 km), 1000 noise draws each, "
                f"intersection + CRLB per point; median MSE/trace(CRLB) {np.median(ratios):.3f}"])


def _session_bodies(epochs_per_post: int):
    """The create body and the measurement posts of one paper-001 run (seq from 1, degrees)."""
    from core.simulation.emitter import paper_001_scenario, simulate_emitter

    scenario = paper_001_scenario()
    track = simulate_emitter(scenario, np.random.default_rng(4))
    create = orjson.dumps({
        "frame": "local", "observer": {"position": {"east_m": 0.0, "north_m": 0.0, "up_m": 0.0}},
        "model": "velocity_kinematic",
        "pulse": {"period_s": scenario.period_s, "period_known": False,
                  "pulses_per_observation": scenario.pulses_per_observation},
        "noise": {"sigma_azimuth_deg": math.degrees(scenario.sigma_azimuth_rad),
                  "sigma_elevation_deg": math.degrees(scenario.sigma_elevation_rad),
                  "sigma_azimuth_rate_deg_s": math.degrees(scenario.sigma_azimuth_rate_rad_s),
                  "sigma_toa_s": scenario.sigma_toa_s},
        "ttl_s": 600.0})
    epochs = [{"seq": k + 1, "time_s": e.time_s, "azimuth_deg": math.degrees(e.azimuth_rad),
               "elevation_deg": math.degrees(e.elevation_rad),
               "azimuth_rate_deg_s": math.degrees(e.azimuth_rate_rad_s),
               "toa_s": e.toa_s} for k, e in enumerate(track.epochs)]
    posts = [orjson.dumps({"measurements": epochs[i:i + epochs_per_post]})
             for i in range(0, len(epochs), epochs_per_post)]
    return create, posts


def _session_load(url: str, epochs_per_post: int, duration_s: float, clients: int = 8) -> dict:
    """Clients each feed one session after another, post by post, for ``duration_s``."""
    import threading

    create, posts = _session_bodies(epochs_per_post)
    latencies: list[float] = []
    counts = {"epochs": 0, "failures": 0}
    lock = threading.Lock()
    deadline = time.perf_counter() + duration_s

    def client():
        connection = _connection(url, timeout=60)
        mine, applied, failed = [], 0, 0
        while time.perf_counter() < deadline:
            status, data = _post(connection, "/v1/sessions", create)
            if status != 201:
                failed += 1
                continue
            session = orjson.loads(data)["id"]
            for body in posts:
                if time.perf_counter() >= deadline:
                    break
                t = time.perf_counter()
                status, data = _post(connection, f"/v1/sessions/{session}/measurements", body)
                mine.append(time.perf_counter() - t)
                if status == 200:
                    applied += orjson.loads(data)["applied"]
                else:
                    failed += 1
        connection.close()
        with lock:
            latencies.extend(mine)
            counts["epochs"] += applied
            counts["failures"] += failed

    threads = [threading.Thread(target=client) for _ in range(clients)]
    started = time.perf_counter()
    for thread in threads:
        thread.start()
    for thread in threads:
        thread.join()
    elapsed = time.perf_counter() - started
    ms = np.array(latencies) * 1e3
    return {"epochs_per_s": counts["epochs"] / elapsed, "posts_per_s": len(latencies) / elapsed,
            "p50_ms": float(np.percentile(ms, 50)), "p99_ms": float(np.percentile(ms, 99)),
            "failures": counts["failures"]}


def session_rows(load: LoadGenerator, duration_s: float, redis_url: str = "redis://127.0.0.1:6379/14") -> list[Row]:
    """Row 4: session epochs/s over HTTP: SQLite with 1 and 10 epochs per post, and Redis."""
    what = "session epochs/s over HTTP"
    if not committed("service/routes/sessions.py", "core/tracking/session.py", "core/simulation/emitter.py"):
        return [unavailable(4, what + " (SQLite: 1 and 10 epochs/post; Redis)", "-",
                            "the sessions routes (service/routes/sessions.py) have not landed in git yet")]
    measured = {}
    with serve() as url:
        for per_post in (1, 10):
            measured[("SQLite", per_post)] = _session_load(url, per_post, duration_s)
    try:
        import redis

        redis.Redis.from_url(redis_url, socket_timeout=2).ping()
        with serve(store=redis_url) as url:
            for per_post in (1, 10):
                measured[("Redis", per_post)] = _session_load(url, per_post, duration_s)
    except Exception as error:  # no Redis here: the row says so instead of failing the table
        measured[("Redis", 0)] = {"unavailable": f"{type(error).__name__}: {error}"}
    base = measured[("SQLite", 1)]["epochs_per_s"]
    rows = []
    for (store, per_post), m in measured.items():
        if "unavailable" in m:
            rows.append(unavailable(4, f"{what}, {store}", "-", f"Redis at {redis_url}: {m['unavailable']}"))
            continue
        rows.append(Row(4, f"{what}, {store} store, {per_post} epoch(s) per post (8 clients, {duration_s:g} s)",
                        f"{m['epochs_per_s']:,.0f} epochs/s ({m['posts_per_s']:,.0f} posts/s, p50 {m['p50_ms']:.1f} ms,"
                        f" p99 {m['p99_ms']:.1f} ms)", "SQLite, 1 epoch per post (first line)",
                        f"{m['epochs_per_s'] / base:.2f}x", "-", "measured",
                        [f"{store}, {per_post}/post: failed posts {m['failures']}; paper-001 epochs, velocity_kinematic,"
                         " each client feeds one session after another"]))
    return rows


def _filterpy_joint_ukf(config, track, start: int):
    """filterpy's UnscentedKalmanFilter set up as the joint UKF of paper 001 (the same step, the same numbers).

    State ``[x, y, z, vx, vy, vz, c * period_error]``, constant velocity; measurement
    ``(B, E, c (dTOA - N Tr), Bdot)`` with the previous range taken from the state, as in
    ``core.tracking.joint_ukf``; Merwe sigma points (alpha 1e-3, beta 2, kappa 0).
    """
    from filterpy.kalman import MerweScaledSigmaPoints, UnscentedKalmanFilter

    c = 299_792_458.0
    n_pulses = config.pulses_per_observation
    interval = n_pulses * config.period_s

    def fx(x, dt):
        out = x.copy()
        out[:3] += dt * x[3:6]
        return out

    def hx(x):
        p, v = x[:3], x[3:6]
        rho2 = p[0] ** 2 + p[1] ** 2
        previous = np.linalg.norm(p - v * interval)
        return np.array([np.arctan2(p[0], p[1]), np.arctan2(p[2], np.sqrt(rho2)),
                         np.linalg.norm(p) - previous + n_pulses * x[6], (p[1] * v[0] - p[0] * v[1]) / rho2])

    def residual(a, b):
        d = a - b
        d[0] = (d[0] + np.pi) % (2 * np.pi) - np.pi
        return d

    points = MerweScaledSigmaPoints(7, alpha=1e-3, beta=2.0, kappa=0.0)
    ukf = UnscentedKalmanFilter(dim_x=7, dim_z=4, dt=interval, hx=hx, fx=fx, points=points, residual_z=residual)
    truth = track.states_enu[start]
    ukf.x = np.r_[truth, 0.0]
    ukf.P = np.diag([1e6, 1e6, 1e6, 1e2, 1e2, 1e2, 1e-2])
    q = config.accel_sigma_mps2**2
    block = np.array([[interval**3 / 3, interval**2 / 2], [interval**2 / 2, interval]]) * q
    ukf.Q = np.zeros((7, 7))
    for i in range(3):
        ukf.Q[np.ix_([i, i + 3], [i, i + 3])] = block
    ukf.R = np.diag([config.sigma_azimuth_rad**2, config.sigma_elevation_rad**2, 2 * (c * config.sigma_toa_s) ** 2,
                     config.sigma_azimuth_rate_rad_s**2])
    measurements = []
    for k in range(start + 1, len(track.epochs)):
        e, previous = track.epochs[k], track.epochs[k - 1]
        dtoa = c * (e.toa_s - previous.toa_s - n_pulses * config.period_s)
        measurements.append(np.array([e.azimuth_rad, e.elevation_rad, dtoa, e.azimuth_rate_rad_s]))
    return ukf, measurements


def filter_step_row(repeats: int = 9) -> Row:
    """Row 5: one steady-state filter step of the session models in core next to filterpy's UKF doing the same
    step; the verdict is the default model's (joint_ukf)."""
    what = "one session filter step in core vs filterpy UnscentedKalmanFilter"
    target = "<= 1/5 of filterpy"
    if not committed("core/tracking/session.py", "core/simulation/emitter.py"):
        return unavailable(5, what, target, "core/tracking (the session filters) has not landed in git yet")
    from core.simulation.emitter import paper_001_scenario, simulate_emitter
    from core.tracking import TrackerConfig, new_state, step

    scenario = paper_001_scenario()
    track = simulate_emitter(scenario, np.random.default_rng(1))
    models = ("joint_ukf", "velocity_kinematic")
    runs = {}
    for model in models:
        config = TrackerConfig(model=model, period_s=scenario.period_s, period_known=False,
                               pulses_per_observation=scenario.pulses_per_observation,
                               sigma_azimuth_rad=scenario.sigma_azimuth_rad,
                               sigma_elevation_rad=scenario.sigma_elevation_rad,
                               sigma_azimuth_rate_rad_s=scenario.sigma_azimuth_rate_rad_s,
                               sigma_toa_s=scenario.sigma_toa_s)
        history = [new_state(config)]
        for epoch in track.epochs:
            history.append(step(history[-1], epoch, config))
        runs[model] = (history, config)
    # Steady state: from the first epoch after which both models stay in "tracking" (joint_ukf's range
    # mixture has collapsed to one UKF).
    start = max(next((i for i in range(len(history)) if all(s.stage == "tracking" for s in history[i:])),
                     len(history)) for history, _ in runs.values())
    if start >= len(track.epochs) - 5:
        return Row(5, what, "not measured", "-", "-", target, "not measured",
                   [f"a model is not in its steady stage (\"tracking\") by epoch {len(track.epochs) - 5}"])
    rest = track.epochs[start:]
    passes = max(1, 200 // len(rest))
    mixture = [i for i, s in enumerate(runs["joint_ukf"][0][:start]) if s.stage == "mixture"]
    ukf, measurements = _filterpy_joint_ukf(runs["joint_ukf"][1], track, start - 1)
    x0, p0 = ukf.x.copy(), ukf.P.copy()

    def core_steps(model):
        history, config = runs[model]
        t = time.perf_counter()
        for _ in range(passes):
            s = history[start]
            for epoch in rest:
                s = step(s, epoch, config)
        return (time.perf_counter() - t) / (passes * len(rest))

    def mixture_steps():
        if not mixture:
            return math.nan
        history, config = runs["joint_ukf"]
        t = time.perf_counter()
        for i in mixture:
            step(history[i], track.epochs[i], config)
        return (time.perf_counter() - t) / len(mixture)

    def filterpy_steps():
        t = time.perf_counter()
        for _ in range(passes):
            ukf.x, ukf.P = x0.copy(), p0.copy()
            for z in measurements:
                ukf.predict()
                ukf.update(z)
        return (time.perf_counter() - t) / (passes * len(measurements))

    rounds = {"joint_ukf": [], "velocity_kinematic": [], "filterpy": [], "mixture": []}
    for _ in range(repeats):
        for model in models:
            rounds[model].append(core_steps(model))
        rounds["filterpy"].append(filterpy_steps())
        rounds["mixture"].append(mixture_steps())
    ratios = {model: [c / f for c, f in zip(rounds[model], rounds["filterpy"])] for model in models + ("mixture",)}
    median = {k: float(np.median(v)) for k, v in rounds.items()}
    ratio = {k: float(np.median(v)) for k, v in ratios.items()}
    verdict = "met" if ratio["joint_ukf"] <= 0.2 else (
        f"missed: {ratio['joint_ukf']:.2f}x is {ratio['joint_ukf'] / 0.2:.1f}x the 1/5 allowed")
    return Row(5, what + " (paper-001 scenario, steady state, default model joint_ukf)",
               f"joint_ukf {median['joint_ukf'] * 1e6:,.0f} us per step; "
               f"velocity_kinematic {median['velocity_kinematic'] * 1e6:,.0f} us",
               f"filterpy UKF predict+update {median['filterpy'] * 1e6:,.0f} us per step",
               f"{ratio['joint_ukf']:.2f}x filterpy (velocity_kinematic {ratio['velocity_kinematic']:.2f}x), "
               f"median of {repeats} rounds", target, verdict,
               [f"core.tracking.step on epochs {start}-{len(track.epochs) - 1} ({len(rest)} epochs, {passes} passes "
                f"per round), from the states the models reached there; both models are in their steady stage "
                f"(\"tracking\") from epoch {start} on; the three filters in turn in each of {repeats} rounds "
                "(medians shown); per-round joint_ukf ratios " + ", ".join(f"{r:.2f}" for r in ratios["joint_ukf"])
                + ("; filterpy: 7-state joint UKF (position, velocity, period error) with the raw (B, E, dTOA, "
                   "Bdot), Merwe points, the same epochs; the step includes core's input validation and immutable "
                   "state."),
                (f"Before that, joint_ukf runs its range mixture (epochs {mixture[0]}-{mixture[-1]} here): "
                 f"{median['mixture'] * 1e6:,.0f} us per step, {ratio['mixture']:.2f}x filterpy's step (not judged)."
                 if mixture else "joint_ukf's range mixture collapsed before the first epoch timed.")])


def evaluation_throughput_row(trials: int = 20_000, chunk_trials: int = 1_000) -> Row:
    """Row 8: Monte Carlo evaluation throughput (trials/s of ``ml``) in this process and on a local two-worker
    Dask cluster, the same chunks and seed (the results are compared bit for bit)."""
    what = f"evaluation: {trials:,} ml trials, 3 stations, in-process vs LocalCluster(2 workers)"
    target = "same result; report both"
    try:
        import distributed
    except ImportError:
        return unavailable(7, what, target, "distributed is not installed (pip install 'passive-locator[distributed]')")
    from core.problem.build import Bearing, build_problem
    from core.problem.frame import LocalPoint
    from core.simulation.measurements import evaluate

    stations = [("a", LocalPoint(0.0, 0.0, 0.0)), ("b", LocalPoint(20_000.0, 0.0, 100.0)),
                ("c", LocalPoint(10_000.0, 18_000.0, 300.0))]
    sigma = np.deg2rad(0.5)
    problem = build_problem(stations, [Bearing(i, 0.0, 0.0, sigma, sigma) for i, _ in stations])
    target_enu = np.array([9_000.0, 7_000.0, 3_000.0])
    evaluate(problem, target_enu, ["ml"], 200, 1)  # imports and caches warm
    t = time.perf_counter()
    here = evaluate(problem, target_enu, ["ml"], trials, 7, chunk_trials=chunk_trials)["ml"]
    here_s = time.perf_counter() - t
    with distributed.LocalCluster(n_workers=2, threads_per_worker=1, processes=True,
                                  dashboard_address=None) as cluster, distributed.Client(cluster) as client:
        # every worker imports core and solves once before the clock starts (its first task would pay for both)
        client.run(importlib.import_module, "core.simulation.measurements")
        evaluate(problem, target_enu, ["ml"], 1_000, 1, chunk_trials=64, scheduler=client)
        t = time.perf_counter()
        there = evaluate(problem, target_enu, ["ml"], trials, 7, chunk_trials=chunk_trials, scheduler=client)["ml"]
        there_s = time.perf_counter() - t
    same = bool(np.array_equal(here.errors_enu_m, there.errors_enu_m))
    return Row(8, what, f"{trials / there_s:,.0f} trials/s on 2 workers ({there_s:.2f} s)",
               f"{trials / here_s:,.0f} trials/s in-process ({here_s:.2f} s)", f"{here_s / there_s:.2f}x", target,
               ("met" if same else "missed") + f": results {'identical' if same else 'DIFFER'}",
               [f"{trials // chunk_trials} chunks of {chunk_trials} trials, seed 7; {os.cpu_count()} CPUs shared with "
                "the cluster's two worker processes and the client, so the ratio is bounded by the free cores"])
