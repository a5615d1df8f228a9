"""``passive-locator serve --host H --port P [--workers N]``."""

from __future__ import annotations

import argparse


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(prog="passive-locator", description="passive emitter location service")
    commands = parser.add_subparsers(dest="command", required=True)
    serve = commands.add_parser("serve", help="run the HTTP service")
    serve.add_argument("--host", default="127.0.0.1")
    serve.add_argument("--port", type=int, default=8080)
    serve.add_argument("--workers", type=int, default=1)
    serve.add_argument("--log-level", default="info")
    args = parser.parse_args(argv)

    import uvicorn

    uvicorn.run("service.main:app", factory=False, host=args.host, port=args.port, workers=args.workers,
                log_level=args.log_level, proxy_headers=False)


if __name__ == "__main__":
    main()
