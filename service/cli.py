"""``passive-locator serve [--host H] [--port P] [--workers N] [--log-level L]``."""

from __future__ import annotations

import argparse
import atexit
import os
import shutil
import tempfile


def _settings_help() -> str:
    """The environment variables the service reads, from its settings models themselves."""
    from service.settings import Settings
    from service.tak import TakSettings

    lines = ["environment (lists as JSON, e.g. PASSIVE_LOCATOR_CORS_ALLOW_ORIGINS='[\"https://c2.example\"]'; "
             "see README.md):"]
    for model in (Settings, TakSettings):
        prefix = model.model_config.get("env_prefix", "")
        for name, field in model.model_fields.items():
            default = field.get_default(call_default_factory=True)
            shown = "" if default in (None, "", []) else f" (default {default!r})"
            about = field.description or _documented(model).get(name)
            about = f": {about}" if about else ""
            lines.append(f"  {prefix}{name.upper()}{shown}{about}")
    lines.append("  PROMETHEUS_MULTIPROC_DIR: with --workers > 1, where the workers' metrics are kept "
                 "(default: a fresh temporary directory)")
    return "\n".join(lines)


def _documented(model) -> dict[str, str]:
    """``{attribute: description}`` from a numpydoc "Attributes" section (what Settings documents)."""
    found: dict[str, str] = {}
    name = None
    for line in (model.__doc__ or "").splitlines():
        text = line.strip()
        if " : " in text and not line.startswith(" " * 8):
            name = text.split(" : ")[0]
        elif name and text:
            found[name] = f"{found.get(name, '')} {text}".strip().replace("``", "")
    return found


def _metrics_for_workers(workers: int) -> None:
    """Several processes: keep prometheus_client's values in a shared directory (summed by /metrics)."""
    if workers <= 1 or os.environ.get("PROMETHEUS_MULTIPROC_DIR"):
        return
    directory = tempfile.mkdtemp(prefix="passive-locator-metrics-")
    os.environ["PROMETHEUS_MULTIPROC_DIR"] = directory
    atexit.register(shutil.rmtree, directory, ignore_errors=True)
import ipaddress
import sys


def is_loopback(host: str) -> bool:
    if host in ("localhost", "localhost.localdomain"):
        return True
    try:
        return ipaddress.ip_address(host.strip("[]")).is_loopback
    except ValueError:
        return False


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(prog="passive-locator", description="passive emitter location service")
    commands = parser.add_subparsers(dest="command", required=True)
    serve = commands.add_parser("serve", help="run the HTTP service", epilog=_settings_help(),
                                formatter_class=argparse.RawDescriptionHelpFormatter,
                                description="Run the HTTP API with uvicorn (OpenAPI at /openapi.json, docs at /docs).")
    serve.add_argument("--host", default="127.0.0.1", help="address to bind (default %(default)s; 0.0.0.0 in "
                                                             "a container)")
    serve.add_argument("--port", type=int, default=8080, help="TCP port (default %(default)s)")
    serve.add_argument("--workers", type=int, default=1,
                       help="server processes (default %(default)s); with more than one, sessions need a shared "
                            "store (redis://) unless every worker may use the same SQLite file, and metrics are "
                            "summed over the workers")
    serve.add_argument("--log-level", default=None, choices=["critical", "error", "warning", "info", "debug"],
                       help="log level (default: PASSIVE_LOCATOR_LOG_LEVEL, else info)")
    args = parser.parse_args(argv)

    from service.logs import uvicorn_log_config
    from service.settings import Settings

    settings = Settings()
    if not settings.key_digests() and not is_loopback(args.host) and not settings.allow_anonymous:
        sys.exit(f"passive-locator: refusing to serve {args.host} without API keys: set "
                 "PASSIVE_LOCATOR_API_KEY_HASHES (or PASSIVE_LOCATOR_API_KEY_HASHES_FILE), or "
                 "PASSIVE_LOCATOR_ALLOW_ANONYMOUS=true to serve anyone who can reach it")
    level = args.log_level or settings.log_level

    import uvicorn

    _metrics_for_workers(args.workers)
    uvicorn.run("service.main:app", factory=False, host=args.host, port=args.port, workers=args.workers,
                log_level=level, log_config=uvicorn_log_config(level, settings.log_format), access_log=False,
                proxy_headers=False, timeout_graceful_shutdown=settings.graceful_timeout_s)


if __name__ == "__main__":
    main()
