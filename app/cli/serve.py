"""`detcal serve`: run the API with uvicorn (optionally bootstrapping a first profile)."""

from __future__ import annotations

import argparse
import os
import shutil
import sys
from pathlib import Path


def register(subparsers: argparse._SubParsersAction) -> None:
    """Add the `serve` subcommand."""
    p = subparsers.add_parser(
        "serve", help="serve the calibration API and dashboard",
        description="Serve the HTTP API and dashboard with uvicorn. Options override the "
                    "DETCAL_* environment (DETCAL_HOST, DETCAL_PORT, DETCAL_WORKERS, "
                    "DETCAL_DATA_DIR, DETCAL_DATABASE_URL, DETCAL_ADMIN_TOKEN, ...).")
    p.add_argument("--host", help="bind address (default: DETCAL_HOST or 127.0.0.1)")
    p.add_argument("--port", type=int, help="port (default: DETCAL_PORT or 8000)")
    p.add_argument("--workers", type=int, help="worker processes (default: 1)")
    p.add_argument("--data-dir", help="store, uploads and token file (default: ./data)")
    p.add_argument("--bootstrap", action="store_true",
                   help="first start: generate an admin token file if none is configured and "
                        "fit a default profile from the bundled lidar detector if the store "
                        "has none")
    p.add_argument("--log-level", default="info",
                   choices=("critical", "error", "warning", "info", "debug"),
                   help="level of the server log (detcal.* and uvicorn loggers, on stderr)")
    p.add_argument("--log-format", choices=("text", "json"),
                   help="log lines as text or JSON objects (default: DETCAL_LOG_FORMAT or text)")
    p.set_defaults(func=serve)


def multiprocess_metrics(directory: Path) -> None:
    """Let the worker processes share their Prometheus counters through files in `directory`
    (emptied first: counts from an earlier run must not add up), so that /metrics from any
    worker reports the whole server (prometheus_client's multiprocess mode)."""
    if directory.exists():
        shutil.rmtree(directory)
    directory.mkdir(mode=0o700, parents=True)
    os.environ["PROMETHEUS_MULTIPROC_DIR"] = str(directory)


def serve(args: argparse.Namespace) -> int:
    """Apply the options to the environment (worker processes read it), make the data
    directory private, and run uvicorn."""
    import uvicorn

    from app.settings import Settings, get_settings

    for flag, env in (("host", "HOST"), ("port", "PORT"), ("workers", "WORKERS"),
                      ("data_dir", "DATA_DIR"), ("log_format", "LOG_FORMAT")):
        value = getattr(args, flag)
        if value is not None:
            os.environ[f"DETCAL_{env}"] = str(value)
    get_settings.cache_clear()
    settings = Settings()
    from app.cli.serve_port import bind_error

    if (busy := bind_error(settings.host, settings.port)) is not None:
        print(busy, file=sys.stderr)
        return 1
    # Everything the server writes (store, WAL, dumps, token, and their directories) is
    # private to its user; the worker processes inherit the mask.
    os.umask(0o077)
    settings.data_dir.mkdir(mode=0o700, parents=True, exist_ok=True)
    if args.bootstrap:
        from app.fitting.bootstrap import ensure_admin_token, ensure_default_profile

        ensure_admin_token(settings)
        try:
            ensure_default_profile(settings)
        except (ImportError, FileNotFoundError) as exc:
            print(f"detcal: no default profile fitted ({exc}); upload a dump to POST /v1/fit")
    if settings.workers > 1:
        multiprocess_metrics(settings.data_dir / "prometheus")
    print(f"detcal: serving on http://{settings.host}:{settings.port}/ "
          f"(data in {settings.data_dir.resolve()})", flush=True)
    from app.http.logs import log_config

    # Slow clients are cut off (app.http.connections: header and body deadlines, head size), idle
    # kept-alive connections after keep_alive_s, and beyond limit_concurrency a 503.
    uvicorn.run("app.main:create_app", factory=True, host=settings.host, port=settings.port,
                workers=settings.workers, log_level=args.log_level,
                log_config=log_config(args.log_level, settings.log_format),
                http="app.http.connections:GuardedHttpToolsProtocol",
                timeout_keep_alive=settings.keep_alive_s,
                limit_concurrency=settings.limit_concurrency)
    return 0
