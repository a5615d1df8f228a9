"""``passive-locator serve --host H --port P [--workers N]``."""

from __future__ import annotations

import argparse
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
    serve = commands.add_parser("serve", help="run the HTTP service")
    serve.add_argument("--host", default="127.0.0.1")
    serve.add_argument("--port", type=int, default=8080)
    serve.add_argument("--workers", type=int, default=1)
    serve.add_argument("--log-level", default=None, help="default: PASSIVE_LOCATOR_LOG_LEVEL or info")
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

    uvicorn.run("service.main:app", factory=False, host=args.host, port=args.port, workers=args.workers,
                log_level=level, log_config=uvicorn_log_config(level, settings.log_format), access_log=False,
                proxy_headers=False, timeout_graceful_shutdown=settings.graceful_timeout_s)


if __name__ == "__main__":
    main()
