"""The docs without a CDN, CORS off unless configured, and `serve --help`."""

from __future__ import annotations

import re

import pytest

from service.cli import main
from service.renderings.tak import TakSettings
from service.settings import Settings


def test_docs_load_only_local_assets(client):
    for page in ("/docs", "/redoc"):
        html = client.get(page).text
        sources = re.findall(r'(?:src|href)="([^"]+)"', html) + re.findall(r"url: '([^']+)'", html)
        assert sources and all(s.startswith("/") for s in sources), sources
        for source in sources:
            assert client.get(source).status_code == 200, source
    assert "SwaggerUIBundle" in client.get("/docs/assets/swagger-ui-bundle.js").text[:2000]


def test_cors_is_off_by_default_and_configurable(make_client):
    preflight = {"Origin": "https://c2.example", "Access-Control-Request-Method": "POST",
                 "Access-Control-Request-Headers": "authorization,content-type"}
    closed = make_client()
    assert "access-control-allow-origin" not in closed.get("/healthz", headers={"Origin": "https://c2.example"}).headers
    assert "access-control-allow-origin" not in closed.options("/v1/fixes", headers=preflight).headers
    opened = make_client(cors_allow_origins=["https://c2.example"])
    response = opened.options("/v1/fixes", headers=preflight)
    assert response.status_code == 200
    assert response.headers["access-control-allow-origin"] == "https://c2.example"
    simple = opened.get("/healthz", headers={"Origin": "https://c2.example"})
    assert simple.headers["access-control-allow-origin"] == "https://c2.example"
    assert "x-request-id" in simple.headers["access-control-expose-headers"].lower()
    other = opened.options("/v1/fixes", headers={**preflight, "Origin": "https://elsewhere.example"})
    assert "access-control-allow-origin" not in other.headers


def test_serve_help_lists_every_option_and_environment_variable(capsys):
    with pytest.raises(SystemExit) as exit_info:
        main(["serve", "--help"])
    assert exit_info.value.code == 0
    text = capsys.readouterr().out
    for option in ("--host", "--port", "--workers", "--log-level"):
        assert option in text
    for model in (Settings, TakSettings):
        prefix = model.model_config["env_prefix"]
        for field in model.model_fields:
            assert f"{prefix}{field}".upper() in text, field
