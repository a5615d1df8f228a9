"""The README's curl examples work as written (run through the app, not a shell)."""

from __future__ import annotations

import pathlib
import re

ROOT = pathlib.Path(__file__).resolve().parents[2]
BASE = "http://127.0.0.1:8080"


def readme_requests() -> list[tuple[str, str, str | None]]:
    """``(method, path, body)`` of every curl in the README's sh blocks, in order (streams left out)."""
    text = (ROOT / "README.md").read_text()
    found = []
    for block in re.findall(r"```sh\n(.*?)```", text, re.S):
        for segment in re.split(r"(?=\bcurl )", block)[1:]:
            url = re.search(r'"?(http://[^\s"]+)', segment)[1]
            body = re.search(r"-d '(.*?)'", segment, re.S)
            if " -N " in segment or "/events" in url:
                continue
            found.append(("POST" if body else "GET", url[len(BASE):], body[1] if body else None))
    return found


def test_the_readme_examples_answer(client):
    requests = readme_requests()
    assert [(m, p.split("?")[0]) for m, p, _ in requests] == [
        ("POST", "/v1/fixes"), ("POST", "/v1/fixes/batch"), ("POST", "/v1/crlb"), ("POST", "/v1/crlb/grid"),
        ("POST", "/v1/evaluations"),
        ("POST", "/v1/sessions"), ("POST", "/v1/sessions/$ID/measurements"), ("GET", "/v1/sessions/$ID"),
        ("POST", "/v1/sessions"), ("POST", "/v1/sessions/$NID/reports"), ("GET", "/v1/sessions/$NID")]
    ids = {}
    for method, path, body in requests:
        for name, session_id in ids.items():
            path = path.replace(f"${name}", session_id)
        response = client.request(method, path, content=body, headers={"content-type": "application/json"})
        assert response.status_code in (200, 201), (path, response.text)
        answer = response.json()
        if path == "/v1/sessions":
            ids["NID" if "stations" in answer else "ID"] = answer["id"]
        if path.endswith("/reports"):
            assert (answer["applied"], answer["duplicates"], answer["late"]) == (6, 0, 0)
        if "formats=cot" in path and "tracks" in answer:
            (track,) = answer["tracks"]
            assert track["cot"].startswith("<event") and 'uid="vehicle-1"' in track["cot"]
            assert answer["geojson"]["type"] == "FeatureCollection" and answer["geojson"]["features"]
        if path == "/v1/fixes":
            assert answer["cot"].startswith("<event") and answer["geojson"]["type"] == "FeatureCollection"
        if path == "/v1/fixes/batch":
            assert [r["ok"] for r in answer["results"]] == [True, False] and answer["geojson"]["features"]
        if path == "/v1/crlb/grid":
            assert answer["grid"]["rows"] == 61 and not any(f["properties"].get("unobservable")
                                                            for f in answer["features"])
        if path.endswith("/measurements"):
            assert answer["applied"] == 3
