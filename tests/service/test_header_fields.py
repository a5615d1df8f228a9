"""Header fields: every field the service reads is parsed strictly in one place, repeated singletons are
refused, authentication and the rate limiter see one identity, and nothing of a body is read before the
caller is authenticated.

Requests are made straight against the ASGI app (inside the TestClient's lifespan) where a test needs bytes
a client library would not send: 0xB2, repeated fields, a Content-Length of its own.
"""

from __future__ import annotations

import hashlib

import anyio
import orjson
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from service.web import headers as fields
from tests.service.conftest import STATIONS_300KM, TARGET, bearing_request


def _digest(key: str) -> str:
    return hashlib.sha256(key.encode()).hexdigest()


class Raw:
    """One request straight to the app: status, headers, parsed body, and how often the body was read."""

    def __init__(self, client, method: str, path: str, header_list, body: bytes = b""):
        self.body_reads = 0

        async def call():
            messages, delivered = [], False

            async def receive():
                nonlocal delivered
                self.body_reads += 1
                if not delivered:
                    delivered = True
                    return {"type": "http.request", "body": body, "more_body": False}
                await anyio.sleep_forever()

            async def send(message):
                messages.append(message)

            scope = {"type": "http", "asgi": {"version": "3.0"}, "http_version": "1.1", "method": method,
                     "scheme": "http", "path": path, "raw_path": path.encode(), "query_string": b"",
                     "headers": [(n.lower(), v) for n, v in header_list], "client": ("192.0.2.1", 4000),
                     "server": ("testserver", 80), "root_path": "", "state": {}}
            await client.app(scope, receive, send)
            return messages

        messages = client.portal.call(call)
        start = messages[0]
        self.status = start["status"]
        self.headers = {name.decode(): value.decode("latin-1") for name, value in start["headers"]}
        raw = b"".join(m.get("body", b"") for m in messages[1:])
        self.json = orjson.loads(raw) if self.headers.get("content-type", "").endswith("json") and raw else None


def _fix_body() -> bytes:
    return orjson.dumps(bearing_request(STATIONS_300KM, TARGET))


JSON = (b"content-type", b"application/json")
#: Values no numeric field may take: too many digits for int(), a superscript (isdigit but not int), other
#: scripts' digits, signs, spaces inside, hex, exponent, empty, a control character.
BAD_NUMBERS = [b"9" * 4301, b"\xb2", "\u0661\u0662".encode(), "\uff11".encode(), b"-1", b"+5", b"1 2", b"0x10",
               b"1e3", b"", b"12\x0b", b"9" * 20]

#: field -> (method, path, extra headers, body, bad values): each request is otherwise acceptable up to the
#: point where the field is used.
CASES = {
    b"last-event-id": ("GET", "/v1/sessions/abc/events", [], b"", BAD_NUMBERS),
    b"content-length": ("POST", "/v1/fixes", [JSON], _fix_body(), BAD_NUMBERS),
    b"if-match": ("POST", "/v1/sessions/abc/measurements", [JSON], b'{"measurements": []}',
                  [b"\xb2", b"", b",", b'"7', b"7x", b'W/"7" junk', b"9" * 4301, "\"\u00e9\"".encode()]),
    b"x-request-id": ("GET", "/healthz", [], b"", [b"", b"a" * 129, b"trace\xb2", b"two words", "\u00e9".encode()]),
    b"accept": ("GET", "/healthz", [], b"", [b"text", b"image/png;q=2", b"image/png;q=0.1234", b"*/*;q=nan",
                                             b"image/png;q=\xb2", b"\xb2/png", b"a/b c"]),
    b"content-type": ("POST", "/v1/fixes", [], _fix_body(), [b"application/json\xb2", b"json", b"a/b;c",
                                                             b"application/json; charset"]),
}


@pytest.mark.parametrize("field", list(CASES), ids=lambda f: f.decode())
def test_a_malformed_value_of_any_field_read_is_a_400_naming_it(client, field):
    method, path, extra, body, bad_values = CASES[field]
    for value in bad_values:
        answer = Raw(client, method, path, [*extra, (field, value)], body)
        assert answer.status == 400, (value, answer.status, answer.json)
        assert answer.headers["content-type"] == "application/problem+json"
        assert answer.json["code"] == "invalid_header"
        assert fields._display(field) in answer.json["detail"], answer.json
        assert answer.body_reads == 0


def test_a_malformed_authorization_is_a_401_naming_it(make_client):
    secured = make_client(api_key_hashes=_digest("alice"))
    for value in (b"Bearer al\xb2ice", b"Bearer alice extra", b"Bearer\talice", b"", "Bearer \u00e9".encode(),
                  b"Bearer " + b"a" * 9000):
        answer = Raw(secured, "GET", "/v1/sessions", [(b"authorization", value)])
        assert answer.status == 401, (value, answer.json)
        assert "Authorization" in answer.json["detail"]
        assert 'error="invalid_request"' in answer.headers["www-authenticate"]


def test_well_formed_values_are_read_as_meant(client):
    assert Raw(client, "GET", "/healthz", [(b"x-request-id", b"c2-trace:42/a")]).headers["x-request-id"] == \
        "c2-trace:42/a"
    accepted = Raw(client, "GET", "/healthz", [(b"accept", b"image/png;q=0.5, application/json;q=1.000"),
                                               (b"accept", b"*/*;q=0")])
    assert accepted.status == 200
    parsed = fields.RequestHeaders.parse([(b"accept", b"image/png;q=0.5, , application/json;q=1.000"),
                                          (b"accept", b'text/plain;format="a;b";q=0'),
                                          (b"last-event-id", b" 0012 "), (b"if-match", b'"3", W/"4", 5'),
                                          (b"content-length", b"0"), (b"content-type", b"Application/JSON; a=b"),
                                          (b"authorization", b"bearer abc+/=="), (b"user-agent", b"\xb2" * 9000)])
    assert [(r.media, r.q) for r in parsed.accept] == [("image/png", 0.5), ("application/json", 1.0),
                                                       ("text/plain", 0.0)]
    assert parsed.last_event_id == 12 and parsed.content_length == 0
    assert parsed.if_match == ('"3"', 'W/"4"', '"5"')
    assert parsed.content_type == b"application/json"
    assert parsed.authorization == fields.Credentials("bearer", b"abc+/==")
    assert fields.RequestHeaders.parse([(b"if-match", b"*")]).if_match == ("*",)


SINGLETON_CASES = [(b"content-type", b"application/json"), (b"content-length", b"10"), (b"if-match", b'"1"'),
                   (b"last-event-id", b"1"), (b"x-request-id", b"a"), (b"host", b"testserver"),
                   (b"origin", b"https://c2.example")]


@pytest.mark.parametrize("field,value", SINGLETON_CASES, ids=lambda v: v.decode())
def test_a_singleton_field_sent_twice_is_a_400(client, field, value):
    for second in (value, value + b"0"):  # the same value again, or another: either way ambiguous
        answer = Raw(client, "POST", "/v1/sessions/abc/measurements",
                     [JSON, (field, value), (field, second)], b'{"measurements": []}')
        assert answer.status == 400, answer.json
        assert answer.json["code"] == "invalid_header" and "more than once" in answer.json["detail"]
        assert answer.body_reads == 0


def test_two_authorization_fields_are_a_401_whichever_comes_first(make_client):
    secured = make_client(api_key_hashes=_digest("alice"), rate_limit_per_s=0.001, rate_limit_burst=5)
    for pair in ([b"Bearer alice", b"Bearer junk"], [b"Bearer junk", b"Bearer alice"],
                 [b"Bearer alice", b"Bearer alice"]):
        answer = Raw(secured, "GET", "/v1/sessions", [(b"authorization", v) for v in pair])
        assert answer.status == 401, answer.json
        assert "more than once" in answer.json["detail"]
    assert len(secured.app.state.rate_limiter.buckets) == 0  # refused before any bucket was taken from


def test_a_key_whose_bucket_is_empty_gets_no_other_bucket(make_client):
    secured = make_client(api_key_hashes=f"{_digest('alice')},{_digest('bob')}", rate_limit_per_s=0.001,
                          rate_limit_burst=2)
    alice = [(b"authorization", b"Bearer alice")]
    assert [Raw(secured, "GET", "/v1/sessions", alice).status for _ in range(3)] == [200, 200, 429]
    for trick in ([(b"authorization", b"Bearer alice"), (b"authorization", b"Bearer bob")],
                  [(b"authorization", b"Bearer junk"), (b"authorization", b"Bearer alice")],
                  [(b"authorization", b"bearer  alice")]):
        assert Raw(secured, "GET", "/v1/sessions", trick).status in (401, 429)
    limiter = secured.app.state.rate_limiter
    assert set(limiter.buckets) == {b"key:" + _digest("alice").encode()}  # no fallback to the address's bucket


def test_the_owner_a_route_sees_is_the_identity_the_limiter_charged(make_client):
    secured = make_client(api_key_hashes=f"{_digest('alice')},{_digest('bob')}")
    from tests.service.sessions.helpers import create_body

    made = secured.post("/v1/sessions", json=create_body(), headers={"authorization": "Bearer alice"})
    assert made.status_code == 201
    assert secured.get(f"/v1/sessions/{made.json()['id']}", headers={"authorization": "Bearer bob"}).status_code \
        == 404
    assert secured.get(f"/v1/sessions/{made.json()['id']}", headers={"authorization": "Bearer alice"}) \
        .status_code == 200


@pytest.mark.parametrize("path", ["/v1/fixes", "/v1/fixes/batch", "/v1/evaluations", "/v1/crlb", "/v1/crlb/grid",
                                  "/v1/sessions", "/v1/sessions/abc/measurements"])
def test_no_body_is_read_before_the_caller_is_authenticated(make_client, path):
    secured = make_client(api_key_hashes=_digest("alice"), max_body_bytes=1000)
    for body, declared in ((b"{" * 5000, b"5000"), (_fix_body(), str(len(_fix_body())).encode()),
                           (b"not json", b"8")):
        for authorization in ([], [(b"authorization", b"Bearer junk")]):
            answer = Raw(secured, "POST", path, [JSON, (b"content-length", declared), *authorization], body)
            assert answer.status == 401, (path, answer.json)
            assert answer.body_reads == 0
    good = Raw(secured, "POST", path, [JSON, (b"authorization", b"Bearer alice")], b"not json")
    assert good.status == 400 and good.body_reads >= 1  # the same body is read and refused once let in


def test_the_probes_and_the_docs_stay_open_with_keys(make_client):
    secured = make_client(api_key_hashes=_digest("alice"))
    for path in ("/healthz", "/readyz", "/metrics", "/openapi.json"):
        assert secured.get(path).status_code == 200, path


_FIELDS = st.sampled_from([b"last-event-id", b"if-match", b"content-length", b"x-request-id", b"accept",
                           b"content-type", b"authorization", b"origin", b"host"])
_VALUES = st.binary(max_size=40).filter(lambda v: not any(c in v for c in b"\r\n\0")) | st.sampled_from(
    [b"9" * 4301, b"\xb2", b"1" * 19, b"1" * 20, b"*", b'"1"', b"image/png;q=0.5"])


@settings(max_examples=300, deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture])
@given(field=_FIELDS, value=_VALUES, twice=st.booleans(),
       route=st.sampled_from([("GET", "/v1/sessions/abc/events", b""),
                              ("POST", "/v1/sessions/abc/measurements", b'{"measurements": []}'),
                              ("GET", "/healthz", b""), ("POST", "/v1/crlb", b"{}")]))
def test_no_header_value_is_a_500(client, field, value, twice, route):
    method, path, body = route
    header_list = [(field, value)] * (2 if twice else 1)
    if field != b"content-type":
        header_list.append(JSON)
    answer = Raw(client, method, path, header_list, body)
    assert answer.status < 500, (field, value, answer.json)
    assert answer.headers["content-type"].startswith("application/")


def test_a_live_sessions_event_stream_refuses_a_malformed_last_event_id(client):
    from tests.service.sessions.helpers import create_body

    session = client.post("/v1/sessions", json=create_body()).json()["id"]
    for value in BAD_NUMBERS:
        answer = Raw(client, "GET", f"/v1/sessions/{session}/events", [(b"last-event-id", value)])
        assert answer.status == 400, (value, answer.json)
        assert "Last-Event-ID" in answer.json["detail"]


def test_a_request_no_route_serves_is_the_routers_404_or_405_whatever_its_fields(client):
    bad = [(b"last-event-id", b"\xb2"), (b"if-match", b"")]
    assert Raw(client, "TRACE", "/v1/sessions/abc/events", bad).status == 405
    assert Raw(client, "GET", "/v1/nowhere", bad).status == 404


@pytest.mark.parametrize("value", [b"a/b" + b";  " * 40 + b"\x01", b"a/b" + b" , " * 40 + b"\x01",
                                   b"a/b" + b"\t;\t" * 40 + b"x", b",  " * 40 + b"a/b;\x01"])
def test_a_value_failing_after_many_empty_elements_is_refused_without_backtracking(value):
    """A grammar with two blank runs side by side in a repeated group has 2^40 readings of these values; the
    parse must be linear (done in microseconds; the bound below only stops a regression from hanging)."""
    import threading

    outcomes = []

    def parse():
        for parser in (fields.parse_media_type, fields.parse_accept):
            try:
                parser(value)
                outcomes.append("accepted")
            except fields.HeaderError:
                outcomes.append("refused")

    worker = threading.Thread(target=parse, daemon=True)
    worker.start()
    worker.join(timeout=60)
    assert outcomes == ["refused", "refused"]
