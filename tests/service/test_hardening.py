"""HTTP hygiene, auth, the rate limiter, the store guard and the logs, in process."""

from __future__ import annotations

import asyncio
import hashlib
import io
import logging
import sqlite3
import tracemalloc

import orjson
import pytest

from service import cli
from service.ops import logs
from service.fixes import pipeline
from service.web.auth import identify
from service.web.headers import parse_authorization
from service.web.middleware import ServiceMiddleware, TokenBucket
from service.web.problems import store_headers
from service.stores.base import StoreBusy, StoreUnavailable
from service.stores.guard import GuardedStore
from tests.service.conftest import STATIONS_300KM, TARGET, bearing_request
from tests.service.test_fixes_api import assert_problem


@pytest.mark.parametrize("route", ["/v1/fixes", "/v1/fixes/batch", "/v1/crlb", "/v1/evaluations", "/v1/sessions"])
@pytest.mark.parametrize("content_type", ["text/plain", "application/x-www-form-urlencoded", None])
def test_a_body_that_is_not_json_is_415(client, route, content_type):
    headers = {} if content_type is None else {"content-type": content_type}
    assert_problem(client.post(route, content=b'{"problems": []}', headers=headers), 415,
                   code="unsupported_media_type")


def test_json_with_a_charset_or_a_json_suffix_is_accepted(client):
    body = orjson.dumps(bearing_request(STATIONS_300KM, TARGET))
    for content_type in ("application/json; charset=utf-8", "application/merge+json"):
        assert client.post("/v1/fixes", content=body, headers={"content-type": content_type}).status_code == 200


def test_a_chunked_body_over_the_limit_is_413(make_client):
    small = make_client(max_body_bytes=4096)

    def chunks():
        for _ in range(10):
            yield b" " * 1024

    for route in ("/v1/fixes", "/v1/fixes/batch"):
        response = small.post(route, content=chunks(), headers={"content-type": "application/json"})
        assert "content-length" not in response.request.headers
        assert_problem(response, 413, code="body_too_large")


def test_405_lists_every_method_of_the_path(client):
    for method, path, allowed in (("PUT", "/v1/sessions", "GET, POST"), ("POST", "/v1/sessions/0123", "DELETE, GET"),
                                  ("GET", "/v1/fixes", "POST"), ("PUT", "/v1/sessions/0123/measurements", "POST")):
        response = client.request(method, path)
        assert_problem(response, 405, code="method_not_allowed")
        assert response.headers["allow"] == allowed


def test_route_answers_agree_with_the_router_when_kept_and_stay_bounded(client):
    """The middleware keeps its route-match answers by method and path: a kept answer is the router's, and
    unknown or long paths cannot grow what it keeps."""
    middleware = ServiceMiddleware(None, max_body_bytes=1, metrics=None, routes=client.app.routes)

    def matches(method: str, path: str) -> bool:
        return middleware._route_matches({"type": "http", "method": method, "path": path, "root_path": ""})

    for _ in range(2):  # the second round answers from what the first kept
        assert matches("POST", "/v1/sessions/0123/reports") and matches("GET", "/healthz")
        assert not matches("PUT", "/v1/sessions") and not matches("GET", "/v1/nowhere")
    for i in range(5000):
        assert not matches("GET", f"/v1/nowhere/{i}")
    assert not matches("GET", "/v1/" + "x" * 5000)
    kept = middleware._route_answers
    assert len(kept) <= 4096 and all(len(path) <= 256 for _, _, path in kept)


def _digest(key: str) -> str:
    return hashlib.sha256(key.encode()).hexdigest()


def test_missing_and_wrong_keys_are_401_with_a_bearer_challenge(make_client):
    secured = make_client(api_key_hashes=_digest("alice"))
    for headers in ({}, {"authorization": "Bearer bob"}, {"authorization": "Basic YWxpY2U6"},
                    {"authorization": "Bearer"}):
        response = secured.get("/v1/sessions", headers=headers)
        assert_problem(response, 401, code="unauthorized")
        assert response.headers["www-authenticate"].startswith("Bearer")
    assert secured.get("/v1/sessions", headers={"authorization": "Bearer alice"}).status_code == 200


def test_serve_refuses_an_open_non_loopback_host(monkeypatch):
    ran = []
    monkeypatch.setattr("uvicorn.run", lambda *args, **kwargs: ran.append(kwargs))
    for name in ("PASSIVE_LOCATOR_API_KEY_HASHES", "PASSIVE_LOCATOR_API_KEY_HASHES_FILE",
                 "PASSIVE_LOCATOR_ALLOW_ANONYMOUS"):
        monkeypatch.delenv(name, raising=False)
    with pytest.raises(SystemExit) as refused:
        cli.main(["serve", "--host", "0.0.0.0"])
    assert "PASSIVE_LOCATOR_ALLOW_ANONYMOUS" in str(refused.value)
    assert ran == []
    cli.main(["serve", "--host", "127.0.0.1"])
    monkeypatch.setenv("PASSIVE_LOCATOR_ALLOW_ANONYMOUS", "true")
    cli.main(["serve", "--host", "0.0.0.0"])
    monkeypatch.delenv("PASSIVE_LOCATOR_ALLOW_ANONYMOUS")
    monkeypatch.setenv("PASSIVE_LOCATOR_API_KEY_HASHES", _digest("k"))
    cli.main(["serve", "--host", "::"])
    assert [r["host"] for r in ran] == ["127.0.0.1", "0.0.0.0", "::"]
    assert all(r["timeout_graceful_shutdown"] > 0 for r in ran)


JUNK_HEADERS = ("authorization", "x-forwarded-for", "x-real-ip", "forwarded", "x-request-id", "user-agent")


def test_the_limiter_cannot_be_dodged_by_varying_headers(make_client):
    limited = make_client(rate_limit_per_s=0.001, rate_limit_burst=3)
    statuses = [limited.get("/v1/sessions", headers={name: f"junk-{i}" for name in JUNK_HEADERS}).status_code
                for i in range(8)]
    assert statuses == [200] * 3 + [429] * 5
    assert len(limited.app.state.rate_limiter.buckets) == 1


def test_the_limiter_keys_on_the_authenticated_key(make_client):
    limited = make_client(rate_limit_per_s=0.001, rate_limit_burst=2,
                          api_key_hashes=f"{_digest('alice')},{_digest('bob')}")
    alice, bob = {"authorization": "Bearer alice"}, {"authorization": "Bearer bob"}
    assert [limited.get("/v1/sessions", headers=alice).status_code for _ in range(3)] == [200, 200, 429]
    assert limited.get("/v1/sessions", headers=bob).status_code == 200  # a key of its own
    junk = [limited.get("/v1/sessions", headers={"authorization": f"Bearer junk-{i}"}).status_code for i in range(4)]
    assert junk == [401, 401, 429, 429]  # wrong keys share the address's bucket
    assert len(limited.app.state.rate_limiter.buckets) == 3


def test_ten_thousand_junk_keys_do_not_grow_the_limiter(make_client):
    limited = make_client(rate_limit_per_s=1000.0, rate_limit_burst=10, api_key_hashes=_digest("alice"))
    limiter, digests = limited.app.state.rate_limiter, limited.app.state.key_digests

    def bucket(authorization: str) -> bytes:
        return identify(parse_authorization(authorization.encode()), digests, "203.0.113.7").limiter_key

    tracemalloc.start()
    try:
        for i in range(1000):  # warm up: the table's one entry and the allocator's pools
            limiter.take(bucket(f"Bearer junk-{i}"))
        before = tracemalloc.take_snapshot()
        for i in range(10_000):
            limiter.take(bucket(f"Bearer junk-{i}-{i}"))
        grown = sum(stat.size_diff for stat in tracemalloc.take_snapshot().compare_to(before, "filename"))
    finally:
        tracemalloc.stop()
    assert len(limiter.buckets) == 1
    assert grown < 64 * 1024, grown


def test_the_limiter_table_is_bounded_by_clients_too():
    limiter = TokenBucket(1.0, 5, max_clients=100)
    for i in range(10_000):
        limiter.take(f"addr:{i}".encode())
    assert len(limiter.buckets) == 100
    assert b"addr:9999" in limiter.buckets and b"addr:0" not in limiter.buckets


def test_probes_are_never_rate_limited(make_client):
    limited = make_client(rate_limit_per_s=0.001, rate_limit_burst=1)
    assert limited.get("/v1/sessions").status_code == 200
    assert limited.get("/v1/sessions").status_code == 429
    assert {limited.get(probe).status_code for probe in ("/healthz", "/readyz", "/metrics") * 5} == {200}


class _Broken:
    kind = "sqlite"

    def __init__(self):
        self.calls = 0

    def get(self):
        self.calls += 1
        raise sqlite3.OperationalError("database or disk is full")

    def close(self):
        pass


def test_the_store_guard_answers_503_opens_its_breaker_and_closes_it_on_success():
    backend = _Broken()
    guard = GuardedStore(lambda clock: backend, "sqlite", workers=2, call_timeout_s=1.0, failure_threshold=2,
                         cooldown_s=0.2)

    async def scenario():
        for _ in range(2):
            with pytest.raises(StoreUnavailable) as failed:
                await guard.run(lambda store: store.get())
            assert int(store_headers(failed.value)["Retry-After"]) >= 1
        with pytest.raises(StoreUnavailable):
            await guard.run(lambda store: store.get())
        assert backend.calls == 2  # open: the store is not touched
        await asyncio.sleep(0.25)  # past the cooldown
        assert await guard.run(lambda store: "fine") == "fine"
        assert not guard.breaker.is_open

    try:
        asyncio.run(scenario())
    finally:
        guard.close()


def test_a_store_error_is_answered_503_problem_json_with_its_code_and_retry_after():
    from fastapi import FastAPI
    from fastapi.testclient import TestClient

    from service.web import problems

    app = FastAPI()
    problems.install(app)

    @app.get("/busy")
    def busy():
        raise StoreBusy("the session store is busy; retry")

    @app.get("/down")
    def down():
        raise StoreUnavailable("session store sqlite unavailable (OSError); retry", 2.5)

    client = TestClient(app)
    for path, code, retry_after in (("/busy", "store_busy", "1"), ("/down", "store_unavailable", "3")):
        response = client.get(path)
        assert response.status_code == 503
        assert response.headers["content-type"] == "application/problem+json"
        assert response.headers["retry-after"] == retry_after
        body = response.json()
        assert (body["status"], body["code"]) == (503, code)
        assert body["type"].endswith(code) and body["detail"].endswith("retry")


def test_a_hung_store_call_is_503_at_the_call_timeout():
    """The store call never returns by itself (it waits until the test releases it): only the guard's call
    timeout can answer, so the 503 that names it is the guard's path, whatever the machine's load. The hung
    call still holds its worker until released, and then ends."""
    import threading

    release, ended = threading.Event(), threading.Event()
    guard = GuardedStore(lambda clock: _Broken(), "redis", workers=1, call_timeout_s=0.3)

    def hung(store):
        release.wait()
        ended.set()

    async def scenario():
        with pytest.raises(StoreUnavailable, match="did not answer within 0.3 s") as refused:
            await guard.run(hung)
        assert not release.is_set() and not ended.is_set()  # answered while the store call was still hung
        return refused.value

    try:
        refused = asyncio.run(scenario())
        assert refused.retry_after_s == guard.breaker.cooldown_s  # the client is told when to retry
    finally:
        release.set()
    assert ended.wait(30)  # released, the worker finishes the call (a bound on a hang, not a speed)
    guard.close()


@pytest.fixture
def captured_logs():
    stream = io.StringIO()
    handler = logging.StreamHandler(stream)
    handler.setFormatter(logs.JsonFormatter())
    logger = logging.getLogger("passive_locator")
    logger.addHandler(handler)
    level = logger.level
    logger.setLevel(logging.INFO)
    yield lambda: [orjson.loads(line) for line in stream.getvalue().splitlines()]
    logger.removeHandler(handler)
    logger.setLevel(level)


def test_log_lines_are_json_with_time_level_and_request_id_and_no_measurements(client, captured_logs):
    body = bearing_request(STATIONS_300KM, TARGET)
    client.post("/v1/fixes", json=body, headers={"x-request-id": "trace-7"})
    lines = [line for line in captured_logs() if line.get("request_id") == "trace-7"]
    assert lines and lines[-1]["message"] == "request" and lines[-1]["status"] == 200
    assert {"timestamp", "level", "logger", "message", "request_id"} <= lines[-1].keys()
    assert lines[-1]["timestamp"].endswith("Z") and lines[-1]["level"] == "info"
    azimuth = f"{body['measurements'][0]['azimuth_deg']}"
    assert not any(azimuth in orjson.dumps(line).decode() for line in captured_logs())


def test_the_shared_solve_logs_the_exception_its_fallback_absorbs(monkeypatch, captured_logs):
    real = pipeline.iter_solutions

    def broken_when_shared(batch, methods, options, should_stop=None, **kwargs):
        if batch.size > 1:
            raise RuntimeError("the batched path broke")
        return real(batch, methods, options, should_stop, **kwargs)

    monkeypatch.setattr(pipeline, "iter_solutions", broken_when_shared)
    body = bearing_request(STATIONS_300KM, TARGET)
    solved = pipeline.fix_results([body, body], ["a", "b"])
    assert all(result["ok"] for result in solved)
    errors = [line for line in captured_logs() if line["level"] == "error"]
    assert errors and "the batched path broke" in errors[0]["exception"]


def test_the_old_plain_key_setting_stops_the_service_rather_than_opening_it(monkeypatch):
    from service.settings import Settings

    monkeypatch.setenv("PASSIVE_LOCATOR_API_KEYS", '["k1"]')
    with pytest.raises(ValueError, match="API_KEY_HASHES"):
        Settings()
