"""Fixes stop at the request deadline and at shutdown: single fixes and batches answer 503
``deadline_exceeded`` with Retry-After, and a batch stops between its parts instead of solving them all."""

from __future__ import annotations

import asyncio
import threading
import time
from types import SimpleNamespace

import pytest

import core.estimators as estimators
from core.estimators.base import EstimatorSpec
from core.parallel import Stopped
from service.fixes.coalesce import Coalescer
from tests.service.conftest import STATIONS_300KM, TARGET, bearing_request
from tests.service.test_fixes_api import assert_problem


@pytest.fixture
def slow_parts(monkeypatch):
    """Once ``start(delay_s)`` is called (after the app's startup, whose kernel warm-up solves too), every
    part is ``state["delay_s"]`` slower and ``solved`` lists the parts solved."""
    parts = SimpleNamespace(solved=[], state={"delay_s": 0.0, "on": False})
    real = EstimatorSpec.solve_batch

    def slow(spec, batch, options, excluded=None):
        if parts.state["on"]:
            time.sleep(parts.state["delay_s"])  # a part that takes long (the deadline is what is tested)
            parts.solved.append(batch.size)
        return real(spec, batch, options, excluded)

    def start(delay_s):
        parts.state.update(delay_s=delay_s, on=True)

    parts.start = start
    monkeypatch.setattr(EstimatorSpec, "solve_batch", slow)
    monkeypatch.setattr(estimators, "PART_PROBLEMS", 1)
    monkeypatch.setattr(estimators, "MAX_WORKERS", 1)
    return parts


def _deadline_problem(response):
    problem = assert_problem(response, 503, code="deadline_exceeded")
    assert int(response.headers["retry-after"]) >= 1
    assert "request_deadline_s" in problem["detail"]
    return problem


def test_a_batch_over_its_deadline_is_503_and_stops_between_parts(make_client, slow_parts):
    client = make_client(request_deadline_s=0.3)
    slow_parts.start(0.2)
    problems = [bearing_request(STATIONS_300KM, TARGET)] * 20
    _deadline_problem(client.post("/v1/fixes/batch", json={"problems": problems}))
    assert len(slow_parts.solved) < 10, slow_parts.solved  # 20 parts of 0.2 s would take 4 s


def test_a_single_fix_over_its_deadline_is_503_and_the_next_one_is_solved(make_client, slow_parts):
    client = make_client(request_deadline_s=0.2, inline_fix_cost=0)  # on the worker, where deadlines are watched
    slow_parts.start(1.5)  # longer than the deadline and the grace after it
    _deadline_problem(client.post("/v1/fixes", json=bearing_request(STATIONS_300KM, TARGET)))
    slow_parts.state["delay_s"] = 0.0
    time.sleep(0.5)  # the abandoned solve finishes
    response = client.post("/v1/fixes", json=bearing_request(STATIONS_300KM, TARGET))
    assert response.status_code == 200, response.text


def test_a_batch_within_its_deadline_is_solved_whole(make_client, slow_parts):
    client = make_client(request_deadline_s=30)
    slow_parts.start(0.0)
    response = client.post("/v1/fixes/batch", json={"problems": [bearing_request(STATIONS_300KM, TARGET)] * 3})
    assert response.status_code == 200 and all(r["ok"] for r in response.json()["results"])
    assert slow_parts.solved == [1, 1, 1]


def test_a_stopping_server_stops_the_coalesced_solve():
    stopping = threading.Event()
    stopping.set()
    with pytest.raises(Stopped):
        asyncio.run(Coalescer(stopping).solve(bearing_request(STATIONS_300KM, TARGET)))


def test_a_closed_coalescer_answers_stopped_rather_than_hang():
    coalescer = Coalescer()
    coalescer.close()
    with pytest.raises(Stopped):
        asyncio.run(asyncio.wait_for(coalescer.solve(bearing_request(STATIONS_300KM, TARGET)), 10))


def test_a_drain_stops_only_when_every_request_of_it_says_stop():
    body = bearing_request(STATIONS_300KM, TARGET)

    async def both(first_stops: bool, second_stops: bool):
        coalescer = Coalescer()
        return await asyncio.gather(coalescer.solve(body, "a", lambda: first_stops),
                                    coalescer.solve(body, "b", lambda: second_stops), return_exceptions=True)

    assert all(r["ok"] for r in asyncio.run(both(True, False)))
    assert all(isinstance(r, Stopped) for r in asyncio.run(both(True, True)))
