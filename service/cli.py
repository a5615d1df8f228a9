"""``passive-locator serve | evaluate | reproduce``.

- ``serve [--host H] [--port P] [--workers N] [--log-level L]``: the HTTP service.
- ``evaluate SCENARIO.json [--out DIR] [--scheduler tcp://host:8786]``: a Monte Carlo evaluation with a
  progress bar, written as Markdown, JSON and a PNG of the RMSE against the bound. The file is either the
  body of ``POST /v1/evaluations`` (fix methods, ``{"network": {...}}``: the network tracker on a scene, or
  ``{"multi_emitter": {...}}``: the multi-emitter tracker on unlabelled bearings, by GOSPA) or
  ``{"tracking": {...}}``, a session-filter evaluation against the posterior CRLB (see ``evaluate --help``).
- ``reproduce [--quick] [--out DIR] [--scheduler ...]``: the five papers' scenarios, ``papers.md`` with
  each table beside the paper's claim; exit status 1 when an asserted claim fails.
"""

from __future__ import annotations

import argparse
import atexit
import os
import shutil
import tempfile


def _settings_help() -> str:
    """The environment variables the service reads, from its settings models themselves."""
    from service.settings import Settings
    from service.renderings.tak import TakSettings

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
    _add_tools(commands)
    args = parser.parse_args(argv)
    if args.command != "serve":
        sys.exit(args.run(args))

    from service.ops.logs import uvicorn_log_config
    from service.settings import Settings

    settings = Settings()
    if not settings.key_digests() and not is_loopback(args.host) and not settings.allow_anonymous:
        sys.exit(f"passive-locator: refusing to serve {args.host} without API keys: set "
                 "PASSIVE_LOCATOR_API_KEY_HASHES (or PASSIVE_LOCATOR_API_KEY_HASHES_FILE), or "
                 "PASSIVE_LOCATOR_ALLOW_ANONYMOUS=true to serve anyone who can reach it")
    level = args.log_level or settings.log_level
    os.environ["PASSIVE_LOCATOR_LOG_LEVEL"] = level  # the app's own logger too, in every worker process

    import uvicorn

    from service.ops import kernel_cache, logs

    logs.configure(level, settings.log_format)
    kernel_cache.usable_cache_dir()  # before uvicorn imports the app (and numba its kernels)
    _metrics_for_workers(args.workers)
    uvicorn.run("service.main:app", factory=False, host=args.host, port=args.port, workers=args.workers,
                log_level=level, log_config=uvicorn_log_config(level, settings.log_format), access_log=False,
                proxy_headers=False, timeout_graceful_shutdown=settings.graceful_timeout_s,
                http="service.ops.server:BoundedHttpToolsProtocol",  # read deadlines, connection bound
                ws="none")  # no WebSocket routes: an upgrade is served as the HTTP request it also is


TRACKING_HELP = """A session-filter evaluation file:
  {"tracking": {"model": "joint_ukf", "period_known": true, "runs": 20, "seed": 1000,
                "config": {"accel_sigma_mps2": 0.05}, "scenario": {"accel_sigma_mps2": 0.05}}}
config: TrackerConfig fields over paper 001's filter settings; scenario: EmitterScenario fields over paper
001's emitter (SI units, radians). The report gives the position RMSE over runs per epoch beside the
posterior CRLB of the scenario's own model.

A network-tracker evaluation file (the body of POST /v1/evaluations with "network"):
  {"network": {"scene": "df_network", "trials": 20, "seed": 0}}
scene: df_network | toa_network | airborne_df; optional process_noise and reorder_window_s over the scene's
tracker settings. The report gives the position RMSE and NEES per epoch beside the posterior CRLB.

A multi-emitter evaluation file (the body of POST /v1/evaluations with "multi_emitter"):
  {"multi_emitter": {"variant": 0, "trials": 5, "seed": 1}}
variant: 0 the base scene, others held-out variants of it; optional duration_s (10-300). The report gives
mean GOSPA and its localisation, missed and false parts beside the intersection + DBSCAN baseline's,
confirmation delays, false confirmed tracks and identity switches per run."""


def _add_tools(commands) -> None:
    scheduler_help = ("run the chunks on this Dask scheduler (tcp://host:8786; needs the 'distributed' extra); "
                      "default: PASSIVE_LOCATOR_DASK_SCHEDULER, else in this process. The result for a seed is "
                      "the same either way")
    evaluate = commands.add_parser("evaluate", help="Monte Carlo evaluation of a scenario file",
                                   description="Monte Carlo RMSE of methods (or of a session filter) against the "
                                               "bound; writes evaluation.md, evaluation.json and rmse.png.",
                                   epilog=TRACKING_HELP, formatter_class=argparse.RawDescriptionHelpFormatter)
    evaluate.add_argument("scenario", help="a POST /v1/evaluations body (fixes, {\"network\": ...} or "
                                           "{\"multi_emitter\": ...}), or a "
                                           "{\"tracking\": ...} file (below)")
    evaluate.add_argument("--out", default=None, help="report directory (default reports/<scenario name>)")
    evaluate.add_argument("--scheduler", default=None, help=scheduler_help)
    evaluate.set_defaults(run=_run_evaluate)
    reproduce = commands.add_parser("reproduce", help="the five papers' scenarios, checked against their claims",
                                    description="Run the five papers' scenarios (full size unless --quick) and "
                                                "write papers.md beside plots; exit 1 when an asserted claim fails.")
    reproduce.add_argument("--quick", action="store_true", help="reduced size (CI: about a minute)")
    reproduce.add_argument("--out", default=None, help="report directory (default reports, reports/quick with "
                                                       "--quick)")
    reproduce.add_argument("--paper", action="append", choices=["000", "001", "002", "003", "004"],
                           help="only these papers (repeatable)")
    reproduce.add_argument("--scheduler", default=None, help=scheduler_help)
    reproduce.set_defaults(run=_run_reproduce)
    coverage = commands.add_parser("map", help="coverage map of a geometry: GeoJSON cells and a PNG heat map",
                                   description="The CRLB over a grid of target positions (a POST /v1/crlb/grid "
                                               "body): writes coverage.geojson and coverage.png (its image size).")
    coverage.add_argument("grid", help="a POST /v1/crlb/grid body (JSON file)")
    coverage.add_argument("--out", default=None, help="output directory (default reports/<grid file name>)")
    coverage.add_argument("--scheduler", default=None, help=scheduler_help)
    coverage.set_defaults(run=_run_map)


def _scheduler(args):
    """A context giving a connected Dask client (one for the whole command), or None to run in-process."""
    import contextlib

    address = args.scheduler
    if not address:
        from service.settings import Settings

        address = Settings().dask_scheduler
    if not address:
        return contextlib.nullcontext(None)
    try:
        from distributed import Client
    except ImportError:
        raise SystemExit("passive-locator: --scheduler needs dask.distributed: pip install "
                         "'passive-locator[distributed]'") from None
    return Client(address)


def _run_evaluate(args) -> int:
    import json
    import pathlib

    from pydantic import ValidationError

    from service.renderings.reports import ProgressBar

    path = pathlib.Path(args.scenario)
    try:
        data = json.loads(path.read_text())
    except (OSError, ValueError) as error:
        print(f"passive-locator evaluate: cannot read {path}: {error}", file=sys.stderr)
        return 2
    out = pathlib.Path(args.out) if args.out else pathlib.Path("reports") / path.stem
    bar = ProgressBar(path.stem)
    try:
        with _scheduler(args) as scheduler:
            if isinstance(data, dict) and "tracking" in data:
                written = _evaluate_tracking(data["tracking"], out, path.stem, scheduler, bar)
            elif isinstance(data, dict) and "network" in data:
                written = _evaluate_network(data, out, path.stem)
            elif isinstance(data, dict) and "multi_emitter" in data:
                written = _evaluate_multi(data, out, path.stem)
            else:
                written = _evaluate_fixes(data, out, path.stem, scheduler, bar)
    except ValidationError as error:
        print(f"passive-locator evaluate: {path} is not a valid evaluation:\n{error}", file=sys.stderr)
        return 2
    except (TypeError, ValueError) as error:
        print(f"passive-locator evaluate: {path}: {error}", file=sys.stderr)
        return 2
    for p in written:
        print(p)
    return 0


def _evaluate_fixes(data, out, title, scheduler, bar):
    from core.errors import LocalizationError
    from service import schemas
    from service.renderings.reports import write_evaluation
    from service.planning import crlb_problem, evaluation_body

    request = schemas.EvaluationRequest.model_validate(data)
    try:
        problem, target = crlb_problem(request.scenario)
        methods = list(dict.fromkeys(request.methods))
        body = evaluation_body(request, problem, target, methods, None, 256, scheduler, progress=bar)
    except LocalizationError as error:
        raise ValueError(error.message) from None
    body["options"] = request.options.model_dump()
    return write_evaluation(body, out, title)


def _evaluate_tracking(spec, out, title, scheduler, bar):
    from core.simulation.emitter import paper_001_scenario
    from core.simulation.tracking import against_bound, paper_config
    from service.renderings.reports import write_tracking_evaluation

    known = spec.get("known", spec.get("period_known", True))
    lists_as_tuples = {k: tuple(v) if isinstance(v, list) else v for k, v in spec.get("scenario", {}).items()}
    config = paper_config(spec.get("model", "joint_ukf"), bool(known),
                          **{k: tuple(v) if isinstance(v, list) else v for k, v in spec.get("config", {}).items()})
    scenario = paper_001_scenario(**lists_as_tuples)
    runs, seed = int(spec.get("runs", 20)), int(spec.get("seed", 1000))
    result = against_bound(config, scenario, runs, seed, scheduler=scheduler, progress=bar)
    return write_tracking_evaluation(result, config, runs, seed, out, title)


def _evaluate_network(data, out, title):
    from service.sessions.network import network_evaluation_body
    from service.web.problems import ApiError
    from service.renderings.reports import write_network_evaluation
    from service.schemas.sessions import NetworkEvaluationRequest

    request = NetworkEvaluationRequest.model_validate(data)
    try:
        body = network_evaluation_body(request.network)
    except ApiError as error:
        raise ValueError(error.detail) from None
    return write_network_evaluation(body, out, title)


def _evaluate_multi(data, out, title):
    from service.sessions.multi_evaluation import multi_evaluation_body
    from service.renderings.reports import write_multi_evaluation
    from service.schemas.sessions import MultiEmitterEvaluationRequest

    request = MultiEmitterEvaluationRequest.model_validate(data)
    return write_multi_evaluation(multi_evaluation_body(request.multi_emitter), out, title)


def _run_map(args) -> int:
    import json
    import pathlib

    from pydantic import ValidationError

    from core.errors import LocalizationError
    from service import schemas
    from service.web.problems import ApiError
    from service.renderings.reports import ProgressBar
    from service.planning import coverage_renderings, grid_of_request

    path = pathlib.Path(args.grid)
    try:
        request = schemas.CrlbGridRequest.model_validate(json.loads(path.read_text()))
        problem, grid = grid_of_request(request)
    except (OSError, ValueError, ValidationError, LocalizationError, ApiError) as error:
        reason = getattr(error, "message", None) or getattr(error, "detail", None) or error
        print(f"passive-locator map: {path}: {reason}", file=sys.stderr)
        return 2
    out = pathlib.Path(args.out) if args.out else pathlib.Path("reports") / path.stem
    out.mkdir(parents=True, exist_ok=True)
    with _scheduler(args) as scheduler:
        rendered = coverage_renderings(request, problem, grid, ("geojson", "png"), scheduler=scheduler,
                                       progress=ProgressBar(path.stem))
    geojson, png = out / "coverage.geojson", out / "coverage.png"
    geojson.write_text(json.dumps(rendered["geojson"]))
    png.write_bytes(rendered["png"])
    print(geojson)
    print(png)
    return 0


def _run_reproduce(args) -> int:
    import pathlib
    import time

    from core.simulation.papers import reproduce
    from service.renderings.reports import write_papers

    size = "quick" if args.quick else "full"
    out = pathlib.Path(args.out) if args.out else pathlib.Path("reports") / ("quick" if args.quick else "")
    start = time.monotonic()
    with _scheduler(args) as scheduler:
        results = reproduce(size, scheduler=scheduler, papers=args.paper,
                            progress=lambda name: print(f"paper {name} ...", file=sys.stderr, flush=True))
        where = None if scheduler is None else f"{len(scheduler.scheduler_info()['workers'])} Dask workers"
    written = write_papers(results, out, size, time.monotonic() - start, where)
    failed = [(r.paper, c) for r in results for c in r.checks if c.asserted and not c.holds]
    for paper, check in failed:
        print(f"FAILED paper {paper}: {check.claim}: {check.measured}", file=sys.stderr)
    print(written[0])
    return 1 if failed else 0


if __name__ == "__main__":
    main()
