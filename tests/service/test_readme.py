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
        ("POST", "/v1/sessions"), ("POST", "/v1/sessions/$NID/reports"), ("GET", "/v1/sessions/$NID"),
        ("POST", "/v1/sessions"), ("POST", "/v1/sessions/$AID/reports"), ("GET", "/v1/sessions/$AID")]
    ids = {}
    for method, path, body in requests:
        for name, session_id in ids.items():
            path = path.replace(f"${name}", session_id)
        response = client.request(method, path, content=body, headers={"content-type": "application/json"})
        assert response.status_code in (200, 201), (path, response.text)
        answer = response.json()
        auto = answer.get("association") == "auto"
        if path == "/v1/sessions":
            ids["AID" if auto else "NID" if "stations" in answer else "ID"] = answer["id"]
        if path.endswith("/reports"):
            assert (answer["applied"], answer["duplicates"], answer["late"]) == (18 if auto else 6, 0, 0)
        if "formats=cot" in path and "tracks" in answer and auto:
            # two emitters, two confirmed tracks, one CoT uid each
            assert [t["status"] for t in answer["tracks"]] == ["confirmed", "confirmed"]
            assert sorted(t["cot"].split('uid="')[1].split('"')[0] for t in answer["tracks"]) == ["net-t1", "net-t2"]
        elif "formats=cot" in path and "tracks" in answer:
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


def _configuration_rows() -> list[tuple[list[str], list[str]]]:
    """``(names, defaults)`` of each row of the README's configuration table (``a / b`` cells split)."""
    text = (ROOT / "README.md").read_text()
    section = text.split("## Configuration (environment)", 1)[1]
    table = re.search(r"^\|.*?(?=\n\n)", section, re.S | re.M).group(0)
    rows = []
    for line in table.splitlines()[2:]:
        cells = [c.strip() for c in line.strip("|").split(" | ")]
        names = re.findall(r"`(PASSIVE_LOCATOR_[A-Z0-9_]+)`", cells[0])
        assert len(names) == cells[0].count("/") + 1, f"a variable in {cells[0]} is not written out in full"
        rows.append((names, [d.strip() for d in cells[1].split(" / ")]))
    return rows


def _settings() -> dict[str, object]:
    """Every environment variable the service's settings read, with its default."""
    from service.renderings.tak import TakSettings
    from service.settings import Settings

    found = {}
    for model in (Settings, TakSettings):
        prefix = model.model_config["env_prefix"]
        for name, field in model.model_fields.items():
            if field.description and field.description.startswith("gone:"):
                continue  # refused when set, not a setting
            found[f"{prefix}{name}".upper()] = field.get_default(call_default_factory=True)
    return found


def _same_default(text: str, default) -> bool:
    text = text.strip("`")
    if default in (None, "", []):
        return text in ("unset", "empty", "[]")
    if isinstance(default, bool):
        return text == str(default).lower()
    if isinstance(default, (int, float)):
        return float(text) == default
    return text == str(default)


def test_the_configuration_table_lists_every_setting_once_with_its_default():
    rows = _configuration_rows()
    listed = [name for names, _ in rows for name in names]
    assert len(listed) == len(set(listed)), sorted(n for n in listed if listed.count(n) > 1)
    settings = _settings()
    assert set(listed) == set(settings), (set(listed) ^ set(settings))
    for names, defaults in rows:
        assert len(defaults) == len(names), (names, defaults)
        for name, default in zip(names, defaults):
            assert _same_default(default, settings[name]), (name, default, settings[name])


def test_one_declaration_per_setting():
    """A class body keeps the last of two annotations of one name: the first is dead text with its own meaning."""
    import ast

    for path in (ROOT / "service" / "settings.py", ROOT / "service" / "renderings" / "tak.py"):
        for node in ast.walk(ast.parse(path.read_text())):
            if isinstance(node, ast.ClassDef) and node.name.endswith("Settings"):
                names = [s.target.id for s in node.body if isinstance(s, ast.AnnAssign)]
                assert len(names) == len(set(names)), (path.name, sorted(n for n in names if names.count(n) > 1))


def test_the_help_command_works_as_written(capsys):
    """``.venv/bin/passive-locator serve --help``: the venv the Makefile makes, the script pyproject.toml
    installs there, and a help that lists every setting."""
    import tomllib

    import pytest

    from service.cli import main

    text = (ROOT / "README.md").read_text()
    commands = set(re.findall(r"`(\.venv/bin/passive-locator [^`]*)`", text))
    assert commands == {".venv/bin/passive-locator serve --help"}
    assert "`passive-locator serve --help`" not in text  # not on PATH after `make serve`
    makefile = (ROOT / "Makefile").read_text()
    assert re.search(r"^VENV := \.venv$", makefile, re.M) and re.search(r"^BIN := \$\(VENV\)/bin$", makefile, re.M)
    scripts = tomllib.loads((ROOT / "pyproject.toml").read_text())["project"]["scripts"]
    assert scripts["passive-locator"] == "service.cli:main"
    with pytest.raises(SystemExit) as done:
        main(["serve", "--help"])
    assert done.value.code == 0
    shown = capsys.readouterr().out
    assert all(name in shown for name in _settings()), [n for n in _settings() if n not in shown]


def test_the_paths_the_readme_names_exist():
    text = (ROOT / "README.md").read_text()
    named = set(re.findall(r"`((?:\.ci|core|service|tests|scripts|bench|deploy|examples|openapi)/[^`\s]*)`", text))
    assert named, "no paths found: the pattern is broken"
    assert not [path for path in named if not (ROOT / path).exists()]
    assert "mirrors the tree" not in text


def test_the_cold_start_figure_is_the_one_the_service_and_the_manifests_use():
    from service.ops.kernel_cache import COLD_START_S

    text = (ROOT / "README.md").read_text()
    assert f"| empty, or from another CPU model: every kernel compiles | {COLD_START_S[0]}-{COLD_START_S[1]} s |" \
        in text
    assert "NUMBA_CACHE_DIR=/opt/numba-cache" in text and "NUMBA_CACHE_DIR=/opt/numba-cache" in \
        (ROOT / "Dockerfile").read_text()


def test_the_metrics_the_readme_names_are_served(client):
    from prometheus_client.parser import text_string_to_metric_families

    text = (ROOT / "README.md").read_text()
    named = set(re.findall(r"`((?:passive_locator|process)_[a-z0-9_]+)`", text))
    assert len(named) >= 6
    client.get("/healthz")  # the request histogram has a series once a request was answered
    families = list(text_string_to_metric_families(client.get("/metrics").text))
    served = {f.name for f in families} | {s.name for f in families for s in f.samples}
    assert named <= served, named - served
