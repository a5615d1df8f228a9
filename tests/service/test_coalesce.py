"""Concurrent POST /v1/fixes share one batched solve and answer exactly as each would alone."""

from __future__ import annotations

import asyncio
import copy
import threading

import pytest

from core.parallel import Stopped
from service.fixes import pipeline
from service.fixes.coalesce import Coalescer
from service.web.responses import dumps
from service.fixes.pipeline import fix_results
from tests.service.conftest import STATIONS_300KM, TARGET, bearing_request
from tests.service.test_batch import _noisy, _subset, assert_close, mixed_batch


def _requests() -> list[dict]:
    """Every method, frame and mix of the batch tests, the malformed and unsolvable ones among them."""
    problems = mixed_batch()
    problems.append(bearing_request(_subset(["rx-1"]), TARGET, method="ml"))  # one station: unsolvable
    return problems


def _post_concurrently(client, bodies: list[dict]) -> list:
    barrier = threading.Barrier(len(bodies))
    out: list = [None] * len(bodies)

    def post(i):
        barrier.wait()
        out[i] = client.post("/v1/fixes", json=bodies[i])

    threads = [threading.Thread(target=post, args=(i,)) for i in range(len(bodies))]
    for t in threads:
        t.start()
    for t in threads:
        t.join()
    return out


def _without_request_id(body: dict) -> dict:
    return {k: v for k, v in body.items() if k not in ("request_id", "instance")}


def test_concurrent_fixes_equal_lone_fixes(make_client):
    bodies = _requests()
    shared = make_client()
    together = _post_concurrently(shared, bodies)
    lone_client = make_client()
    alone = [lone_client.post("/v1/fixes", json=b) for b in bodies]

    coalescer = shared.app.state.fix_coalescer
    assert coalescer.drains < coalescer.solved  # some requests did share a solve
    assert lone_client.app.state.fix_coalescer.drains == lone_client.app.state.fix_coalescer.solved
    statuses = [r.status_code for r in alone]
    assert statuses.count(200) >= len(bodies) // 2 and 422 in statuses
    for i, (got, expected) in enumerate(zip(together, alone)):
        assert got.status_code == expected.status_code, (i, got.text, expected.text)
        assert got.headers["content-type"] == expected.headers["content-type"]
        if expected.status_code == 200:
            assert_close(got.json(), expected.json(), f"request {i}")
        else:
            assert _without_request_id(got.json()) == _without_request_id(expected.json())


def _items():
    return [(body, f"rid-{i}") for i, body in enumerate(_requests())]


def test_one_drain_takes_everything_queued_and_matches_each_alone():
    items = _items()

    async def run():
        coalescer = Coalescer()
        results = await asyncio.gather(*(coalescer.solve(*item) for item in items), return_exceptions=True)
        return coalescer, results

    coalescer, results = asyncio.run(run())
    assert (coalescer.drains, coalescer.solved) == (1, len(items))
    failures = 0
    for (body, rid), result in zip(items, results):
        (alone,) = fix_results([body], rid)
        failures += not alone["ok"]
        assert dumps({**result, "index": 0}) == dumps(alone)
    assert failures >= 1


def test_an_idle_service_solves_a_lone_request_at_once():
    (item,) = _items()[:1]

    async def run():
        coalescer = Coalescer()
        first = await coalescer.solve(*item)
        second = await coalescer.solve(*item)
        return coalescer, first, second

    coalescer, first, second = asyncio.run(run())
    assert (coalescer.drains, coalescer.solved) == (2, 2)
    assert dumps(first) == dumps(second)


def _poisoned_core(monkeypatch, shared_too: bool = False) -> None:
    """A core that raises (a bug) on a problem whose max_iterations is 17, and on any batch if ``shared_too``."""
    real = pipeline.iter_solutions

    def buggy(batch, methods, options, should_stop=None, **kwargs):
        if shared_too and batch.size > 1:
            raise ZeroDivisionError("a bug in the shared call")
        if any(o.max_iterations == 17 for o in options):
            raise ZeroDivisionError("a bug in this problem")
        return real(batch, methods, options, should_stop, **kwargs)

    monkeypatch.setattr(pipeline, "iter_solutions", buggy)


def _good_and_poisoned() -> tuple[dict, dict]:
    good = _noisy(bearing_request(STATIONS_300KM, TARGET), 5)
    poisoned = copy.deepcopy(good)
    poisoned["options"] = {"max_iterations": 17}
    return good, poisoned


def test_a_bug_in_one_problem_fails_only_its_request(make_client, monkeypatch, tmp_path):
    from fastapi.testclient import TestClient

    from service.app import create_app
    from service.settings import Settings

    good, poisoned = _good_and_poisoned()
    _poisoned_core(monkeypatch)
    app = create_app(Settings(store=f"sqlite:///{tmp_path}/bug.db"))
    with TestClient(app, raise_server_exceptions=False) as client:
        responses = _post_concurrently(client, [good, poisoned, good, good])
    assert [r.status_code for r in responses] == [200, 500, 200, 200]
    assert responses[1].headers["content-type"].startswith("application/problem+json")
    assert responses[1].json()["code"] == "internal_error"
    expected = make_client().post("/v1/fixes", json=good).json()
    for k in (0, 2, 3):
        assert_close(responses[k].json(), expected)


def test_results_go_to_cancelled_waiters_without_harm():
    items = _items()[:3]

    async def run():
        coalescer = Coalescer()
        tasks = [asyncio.ensure_future(coalescer.solve(*item)) for item in items]
        await asyncio.sleep(0)
        tasks[1].cancel()
        done = await asyncio.gather(*tasks, return_exceptions=True)
        again = await coalescer.solve(*items[0])
        return done, again

    done, again = asyncio.run(run())
    assert isinstance(done[1], asyncio.CancelledError)
    assert dumps(done[0]) == dumps(again)


def test_a_bug_in_the_shared_solve_falls_back_to_each_alone(monkeypatch, caplog):
    good, poisoned = _good_and_poisoned()
    expected = fix_results([good], "rid-0")[0]
    _poisoned_core(monkeypatch, shared_too=True)
    results = fix_results([good, poisoned, good], ["rid-0", "rid-1", "rid-2"])
    assert "shared solve of 3 fixes failed" in caplog.text and "a bug in this problem" in caplog.text
    assert [r["index"] for r in results] == [0, 1, 2]
    error = results[1]["error"]
    assert not results[1]["ok"] and (error["status"], error["code"], error["request_id"]) == (500, "internal_error",
                                                                                             "rid-1")
    for k in (0, 2):
        assert dumps({**results[k], "index": 0}) == dumps(expected)


def _threads_that_solve(monkeypatch) -> list:
    """The thread of each ``fix_results`` call the coalescer makes, and how many bodies it took."""
    import service.fixes.coalesce as coalesce

    calls = []
    real = coalesce.fix_results

    def recorded(bodies, *args, **kwargs):
        calls.append((threading.get_ident(), len(bodies)))
        return real(bodies, *args, **kwargs)

    monkeypatch.setattr(coalesce, "fix_results", recorded)
    return calls


def test_the_cost_estimate_alone_sends_a_fix_to_the_loop_or_the_worker(monkeypatch):
    # A four-station, four-bearing fix costs 16 (stations x measurements): on the loop at a threshold of 16, on
    # the worker at 15; with outlier exclusion (16 x its 10 solves at most) on the worker at 16 too.
    from service.limits import body_fix_cost

    body = bearing_request(STATIONS_300KM, TARGET)
    excluding = {**body, "options": {"outliers": "exclude"}}
    assert (body_fix_cost(body), body_fix_cost(excluding)) == (16, 160)
    calls = _threads_that_solve(monkeypatch)

    async def run(threshold, bodies):
        coalescer = Coalescer(inline_fix_cost=threshold)
        results = [await coalescer.solve(b) for b in bodies]
        coalescer.close()
        return threading.get_ident(), coalescer, results

    loop_thread, coalescer, results = asyncio.run(run(16, [body, excluding]))
    assert all(r["ok"] for r in results)
    assert [thread == loop_thread for thread, _ in calls] == [True, False]
    assert (coalescer.drains, coalescer.inline_drains) == (2, 1)
    calls.clear()
    loop_thread, coalescer, _ = asyncio.run(run(15, [body]))
    assert [thread == loop_thread for thread, _ in calls] == [False] and coalescer.inline_drains == 0
    calls.clear()
    loop_thread, coalescer, _ = asyncio.run(run(None, [body]))
    assert [thread == loop_thread for thread, _ in calls] == [False] and coalescer.inline_drains == 0


def test_small_fixes_queued_together_share_one_solve_on_the_loop(monkeypatch):
    calls = _threads_that_solve(monkeypatch)
    items = [(bearing_request(STATIONS_300KM, TARGET), f"rid-{i}") for i in range(3)]
    large = (bearing_request(STATIONS_300KM, TARGET) | {"options": {"outliers": "exclude"}}, "rid-large")

    async def run():
        coalescer = Coalescer(inline_fix_cost=16)
        results = await asyncio.gather(*(coalescer.solve(*item) for item in [*items, large]))
        coalescer.close()
        return threading.get_ident(), results

    loop_thread, results = asyncio.run(run())
    assert sorted((thread == loop_thread, size) for thread, size in calls) == [(False, 1), (True, 3)]
    for (body, rid), result in zip([*items, large], results):
        assert dumps({**result, "index": 0}) == dumps(fix_results([body], rid)[0])


def test_a_fix_on_the_loop_answers_as_on_the_worker_and_is_counted(make_client):
    body = bearing_request(STATIONS_300KM, TARGET)
    on_loop, on_worker = make_client(), make_client(inline_fix_cost=0)
    first, second = on_loop.post("/v1/fixes", json=body), on_worker.post("/v1/fixes", json=body)
    assert first.status_code == second.status_code == 200
    assert_close(first.json(), second.json())
    assert on_loop.app.state.fix_coalescer.inline_drains == 1
    assert on_worker.app.state.fix_coalescer.inline_drains == 0
    counted = [line for line in on_loop.get("/metrics").text.splitlines()
               if "fix_seconds_count" in line and 'method="ml"' in line]
    assert counted and counted[0].endswith(" 1.0"), counted


def test_a_stopping_server_answers_a_fix_on_the_loop_503():
    stopping = threading.Event()
    stopping.set()
    with pytest.raises(Stopped):
        asyncio.run(Coalescer(stopping, inline_fix_cost=16).solve(bearing_request(STATIONS_300KM, TARGET)))
