"""Network-session rows of ``python -m bench`` (row 10): reports over HTTP, each beside its yardstick.

- Single-report posts at 8 connections against ``GET /healthz`` at 8 connections (target >= 0.3x).
- Posts of 50 reports against single-report posts, in reports applied per second (target >= 8x).

Every post must be applied (a resent ``seq`` is a cheap duplicate), so unlike the fixed-body rows the load
comes from an asyncio client that gives each connection its own sessions and walks their reports in order;
the yardstick ``/healthz`` is measured by the same client in the same run, and by wrk when it is there
(:mod:`bench.load`), for reference. Reports are the DF network scene's (:mod:`core.simulation.network`):
one station's bearing each, posted in arrival order.
"""

from __future__ import annotations

import asyncio
import re
import time
from urllib.parse import urlsplit

import numpy as np
import orjson

from bench.load import LoadGenerator, run_python
from bench.rows import Row, _combined, _connection, _post
from bench.server import serve

CONNECTIONS = 8
BATCH = 50


def scene_sessions(count: int, seed: int = 0) -> tuple[list[bytes], list[list[dict]]]:
    """Create bodies and report lists of ``count`` DF-network runs (the HTTP API's JSON)."""
    from core.simulation.network import SCENES, simulate_network
    from service.sessions.scene_requests import api_report, create_body

    scene = SCENES["df_network"]()
    creates, reports = [], []
    for k in range(count):
        run = simulate_network(scene, np.random.default_rng(seed + k))
        creates.append(orjson.dumps(create_body(scene)))
        reports.append([api_report(p) for p in run.posted])
    return creates, reports


async def _feed(host: str, port: int, posts: list[tuple[str, bytes]], deadline: float, latencies: list,
                counts: dict) -> None:
    """One keep-alive connection posting ``posts`` in order until the deadline."""
    reader, writer = await asyncio.open_connection(host, port)
    try:
        for path, body in posts:
            if time.perf_counter() >= deadline:
                return
            started = time.perf_counter()
            writer.write((f"POST {path} HTTP/1.1\r\nHost: {host}:{port}\r\nContent-Type: application/json\r\n"
                          f"Content-Length: {len(body)}\r\n\r\n").encode() + body)
            head = await reader.readuntil(b"\r\n\r\n")
            status = int(head.split(b" ", 2)[1])
            length = re.search(rb"(?i)content-length:\s*(\d+)", head)
            data = await reader.readexactly(int(length.group(1)) if length else 0)
            latencies.append(time.perf_counter() - started)
            if status == 200:
                counts["reports"] += orjson.loads(data)["applied"]
            else:
                counts["failures"] += 1
                counts.setdefault("statuses", {}).setdefault(status, data[:200])
    finally:
        writer.close()


def report_load(url: str, per_post: int, duration_s: float, connections: int = CONNECTIONS) -> dict:
    """``connections`` clients each feed their own sessions, ``per_post`` reports a post, for ``duration_s``.

    The sessions are created (and their posts encoded) before the clock starts.
    """
    parts = urlsplit(url)
    creates, reports = scene_sessions(connections * 4)
    connection = _connection(url, timeout=60)
    plans: list[list[tuple[str, bytes]]] = [[] for _ in range(connections)]
    for k, (create, session_reports) in enumerate(zip(creates, reports)):
        status, data = _post(connection, "/v1/sessions", create)
        assert status == 201, data[:300]
        path = f"/v1/sessions/{orjson.loads(data)['id']}/reports"
        plans[k % connections].extend((path, orjson.dumps({"reports": session_reports[i:i + per_post]}))
                                      for i in range(0, len(session_reports), per_post))
    connection.close()
    latencies: list[float] = []
    counts = {"reports": 0, "failures": 0}

    async def run():
        deadline = time.perf_counter() + duration_s
        await asyncio.gather(*(_feed(parts.hostname, parts.port, plan, deadline, latencies, counts)
                               for plan in plans))

    started = time.perf_counter()
    asyncio.run(run())
    elapsed = time.perf_counter() - started
    ms = np.array(latencies) * 1e3
    return {"reports_per_s": counts["reports"] / elapsed, "posts_per_s": len(latencies) / elapsed,
            "p50_ms": float(np.percentile(ms, 50)), "p99_ms": float(np.percentile(ms, 99)),
            "failures": counts["failures"], "posts": len(latencies), "statuses": counts.get("statuses", {})}


def network_session_rows(duration_s: float, rounds: int = 3, store: str | None = None) -> list[Row]:
    """Row 10: single-report posts vs healthz at c=8, and 50-report posts vs single-report posts.

    ``rounds`` interleaved runs of each subject (the machine is shared: only same-run ratios count).
    """
    load = LoadGenerator(install=False)
    single, batched, healthz, healthz_wrk = [], [], [], []
    with serve(store) as url:
        report_load(url, 1, min(1.0, duration_s))  # warm up: compile the kernels, open the store
        for _ in range(rounds):
            healthz.append(run_python(f"{url}/healthz", duration_s, CONNECTIONS))
            single.append(report_load(url, 1, duration_s))
            batched.append(report_load(url, BATCH, duration_s))
            if load.wrk:
                healthz_wrk.append(load.run(f"{url}/healthz", duration_s, CONNECTIONS))
    healthz_rps, healthz_p50, healthz_p99, _ = _combined(healthz)
    single_rps = float(np.sum([m["posts"] for m in single]) / np.sum([m["posts"] / m["posts_per_s"] for m in single]))
    single_reports = float(np.median([m["reports_per_s"] for m in single]))
    batched_reports = float(np.median([m["reports_per_s"] for m in batched]))
    ratio_healthz = single_rps / healthz_rps
    ratio_batch = batched_reports / single_reports
    store_name = "SQLite" if store is None or store.startswith("sqlite") else "Redis"
    notes = [f"{store_name} store, 1 uvicorn worker; DF-network reports (one station's bearing each), each "
             f"connection feeding its own sessions in arrival order; {rounds} interleaved rounds of "
             f"{duration_s:g} s; failed posts: single {sum(m['failures'] for m in single)}, batched "
             f"{sum(m['failures'] for m in batched)} "
             f"({sorted({code for m in single + batched for code in m['statuses']}) or 'none'})",
             "per round, single posts/s / healthz req/s: " + ", ".join(
                 f"{s['posts_per_s'] / h.requests_per_s:.2f}" for s, h in zip(single, healthz)),
             "per round, 50-report reports/s / single-report reports/s: " + ", ".join(
                 f"{b['reports_per_s'] / s['reports_per_s']:.1f}" for s, b in zip(single, batched))]
    if healthz_wrk:
        wrk_rps = _combined(healthz_wrk)[0]
        notes.append(f"healthz by wrk at c=8 in the same rounds: {wrk_rps:,.0f} req/s (single posts / that: "
                     f"{single_rps / wrk_rps:.2f}x); the ratio above uses the asyncio client for both")
    rows = [
        Row(10, f"network session: single-report posts over HTTP, c={CONNECTIONS}",
            f"{single_rps:,.0f} posts/s (p50 {np.median([m['p50_ms'] for m in single]):.1f} ms, "
            f"p99 {max(m['p99_ms'] for m in single):.1f} ms)",
            f"healthz {healthz_rps:,.0f} req/s (p50 {healthz_p50:.1f}, p99 {healthz_p99:.1f} ms), same client",
            f"{ratio_healthz:.2f}x healthz", ">= 0.3x healthz",
            "met" if ratio_healthz >= 0.3 else f"missed: {ratio_healthz:.2f}x is {0.3 / ratio_healthz:.1f}x short",
            notes),
        Row(10, f"network session: posts of {BATCH} reports over HTTP, c={CONNECTIONS}",
            f"{batched_reports:,.0f} reports/s ({np.median([m['posts_per_s'] for m in batched]):,.0f} posts/s, p99 "
            f"{max(m['p99_ms'] for m in batched):.1f} ms)",
            f"single-report posts {single_reports:,.0f} reports/s", f"{ratio_batch:.1f}x", ">= 8x",
            "met" if ratio_batch >= 8.0 else f"missed: {ratio_batch:.1f}x is {8.0 / ratio_batch:.1f}x short"),
    ]
    return rows


def main(argv=None) -> int:
    """``python -m bench.network_sessions [--duration S] [--rounds N]``: print the rows."""
    import argparse

    parser = argparse.ArgumentParser(prog="python -m bench.network_sessions", description=__doc__.splitlines()[0])
    parser.add_argument("--duration", type=float, default=10.0)
    parser.add_argument("--rounds", type=int, default=3)
    parser.add_argument("--store", default=None, help="session store URL (default: a fresh SQLite file)")
    args = parser.parse_args(argv)
    for row in network_session_rows(args.duration, args.rounds, args.store):
        print(f"| {row.number} | {row.what} | {row.measured} | {row.reference} | {row.ratio} | {row.target} | "
              f"{row.verdict} |")
        for note in row.notes:
            print(f"  - {note}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
