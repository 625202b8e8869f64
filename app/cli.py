"""The ``locus`` command: serve, import recordings, replay, evaluate."""

from __future__ import annotations

import argparse
import os
import sys
from collections.abc import Callable, Sequence
from pathlib import Path

from pydantic import ValidationError

from app.core.config import Settings


def _settings(args: argparse.Namespace) -> Settings:
    """Return the settings of flags over ``LOCUS_*`` env; exit naming any bad one."""
    overrides = {
        key: getattr(args, key)
        for key in ("host", "port", "database_url", "workers", "broker", "home", "access_log")
        if getattr(args, key, None) is not None
    }
    try:
        return Settings(**overrides)
    except ValidationError as exc:
        raise SystemExit(f"locus: invalid settings: {exc}") from None


def _api_settings(args: argparse.Namespace) -> Settings:
    """Start the logs and return the settings of a process that serves the API, its C
    allocator limited to the arenas it may keep before any thread allocates."""
    from app.core.heap import limit_arenas
    from app.core.logging import configure_logging

    configure_logging()
    settings = _settings(args)
    limit_arenas(settings.api_malloc_arenas)
    return settings


def _port_free(settings: Settings) -> None:
    """Exit naming the port when something already listens on it (a demo left running)."""
    import socket

    with socket.socket() as probe:
        # as uvicorn binds: connections of a previous run waiting out TIME_WAIT are no obstacle
        probe.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
        try:
            probe.bind((settings.host, settings.port))
        except OSError as exc:
            raise SystemExit(
                f"locus: cannot listen on {settings.host}:{settings.port}: {exc.strerror}. "
                "Is another Locus (the demo?) running there? Stop it, or pass --port"
            ) from None


def cmd_serve(args: argparse.Namespace) -> int:
    """Upgrade the schema, make sure an admin key exists, and serve the API with workers."""
    import uvicorn

    from app.core.db import make_engine, make_sessionmaker, upgrade_database
    from app.core.logging import quiet_connections
    from app.keys.bootstrap import announce_admin_key, bootstrap_admin
    from app.main import create_app

    settings = _api_settings(args)
    _port_free(settings)
    upgrade_database(settings.resolved_database_url)
    engine = make_engine(settings.resolved_database_url)
    try:
        key = bootstrap_admin(sessions=make_sessionmaker(engine), settings=settings)
    except ValueError as exc:
        raise SystemExit(f"locus: {exc}") from None
    finally:
        engine.dispose()
    if key is not None:
        announce_admin_key(key)
    if not settings.access_log:
        quiet_connections()
    uvicorn.run(
        create_app(settings),
        host=settings.host,
        port=settings.port,
        log_level="info",
        access_log=settings.access_log,
        timeout_keep_alive=settings.keep_alive_s,
    )
    return 0


def cmd_demo(args: argparse.Namespace) -> int:
    """Serve Locus with the demo site and simulated devices walking in it."""
    import threading

    import uvicorn

    from app import demo
    from app.core.db import make_engine, make_sessionmaker, session_scope, upgrade_database
    from app.core.logging import quiet_connections
    from app.keys.bootstrap import bootstrap_admin
    from app.keys.service import create_key
    from app.main import create_app

    settings = _api_settings(args)
    if args.home is None:
        settings = settings.model_copy(update={"home": settings.home / "demo"})
    _port_free(settings)
    upgrade_database(settings.resolved_database_url)
    engine = make_engine(settings.resolved_database_url)
    sessions = make_sessionmaker(engine)
    try:
        bootstrap_admin(sessions=sessions, settings=settings)
    except ValueError as exc:
        raise SystemExit(f"locus: {exc}") from None
    admin = settings.admin_key
    if not admin:
        with session_scope(sessions) as db:
            admin = create_key(db=db, role="admin", site_id=None, label="demo")
    engine.dispose()
    if not settings.access_log:
        quiet_connections()
    server = uvicorn.Server(
        uvicorn.Config(
            create_app(settings),
            host=settings.host,
            port=settings.port,
            access_log=settings.access_log,
            timeout_keep_alive=settings.keep_alive_s,
        )
    )
    stop = threading.Event()
    base = demo.base_url(settings.host, settings.port)

    def run_devices() -> None:
        while not server.started and not stop.wait(0.2):
            pass
        demo.install(base, admin)
        # last, after the start-up lines, so it does not scroll away
        demo.simulate(
            base, admin, stop=stop, on_running=lambda: print(demo.banner(base, admin), flush=True)
        )

    threading.Thread(target=run_devices, name="demo-devices", daemon=True).start()
    try:
        server.run()
    finally:
        stop.set()
    return 0


def cmd_import_ilc(args: argparse.Namespace) -> int:
    """Import a Microsoft ILC site folder (floors and walks) into a Locus server."""
    import time

    from app.importers.ilc import import_site

    key = args.key or os.environ.get("LOCUS_ADMIN_KEY")
    if not key:
        print("an admin key is needed: --key or LOCUS_ADMIN_KEY", file=sys.stderr)
        return 2
    started = time.perf_counter()
    summary = import_site(
        Path(args.site_dir),
        site_id=args.site_id,
        server=args.server,
        key=key,
        rooms_walkable=args.rooms_walkable,
        limit=args.limit,
        floors=args.floors,
    )
    print(
        f"imported {summary.floors} floors and {summary.surveys} walks "
        f"({summary.samples} samples) in {time.perf_counter() - started:.1f} s"
    )
    return 0


def cmd_ilc_maps(args: argparse.Namespace) -> int:
    """Write an ILC site's floors as the API's floor-map GeoJSON files (one per floor)."""
    import json

    from app.datasets.ilc import read_floor, site_floors

    out = Path(args.out_dir)
    out.mkdir(parents=True, exist_ok=True)
    for floor_dir in site_floors(Path(args.site_dir)):
        floor = read_floor(floor_dir, rooms_walkable=args.rooms_walkable)
        path = out / f"{floor.name}.geojson"
        path.write_text(json.dumps(floor.geojson, separators=(",", ":")) + "\n", encoding="utf-8")
        print(
            f"{floor.name}: level {floor.level}, {len(floor.geojson['features'])} features → {path}"
        )
    return 0


def cmd_worker(args: argparse.Namespace) -> int:
    """Run one filter worker node on the Redis broker until SIGTERM."""
    from app.workers.redis_broker import redis_worker_main

    settings = _settings(args)
    if settings.broker == "memory":
        print("a worker node needs --broker redis://...", file=sys.stderr)
        return 2
    redis_worker_main(settings.model_dump_json())
    return 0


def cmd_replay(args: argparse.Namespace) -> int:
    """Replay a recording (or a site's held-out walks) through a server; print the positions."""
    import json

    import httpx
    import numpy as np

    from app.datasets.ilc import site_walks
    from app.evaluation.metrics import HEADER, error_stats, format_row
    from app.evaluation.split import walk_split
    from app.replay import load_recording, replay_samples, score

    key = args.key or os.environ.get("LOCUS_ADMIN_KEY")
    source = Path(args.recording)
    if source.is_dir():
        walks = site_walks(source)
        _, test = walk_split([p.name.split(".")[0] for _, p in walks], args.test_fraction)
        chosen = [p for _, p in walks if p.name.split(".")[0] in set(test)][: args.limit]
        recordings = [load_recording(p) for p in chosen]
    else:
        recordings = [load_recording(source)]

    def emit(positions: list[dict]) -> None:
        if not args.quiet:
            for position in positions:
                print(json.dumps(position), flush=True)

    errors, floor_hits = [], []
    with httpx.Client(
        base_url=args.server, headers={"Authorization": f"Bearer {key}"}, timeout=120
    ) as http:
        for rec in recordings:
            site_id = args.site_id or rec.site_id
            if site_id is None:
                print("the recording names no site: pass --site-id", file=sys.stderr)
                return 2
            device_id = args.device_id or rec.device_id or "replay"
            if rec.walk is not None and source.is_dir():
                device_id = f"{args.prefix}{rec.walk.walk_id}"
            positions = replay_samples(
                http,
                rec.samples,
                site_id=site_id,
                device_id=device_id,
                batch_ms=args.batch_ms,
                speed=args.speed,
                on_positions=emit,
            )
            if rec.walk is not None:
                scored = score(rec.walk, positions)
                errors.append(scored.errors)
                floor_hits.append(scored.floor_ok)
    if errors:
        hits = np.concatenate(floor_hits)
        print(HEADER, file=sys.stderr)
        print(
            format_row(
                f"replay of {len(errors)} walk(s)",
                error_stats(np.concatenate(errors)),
                1 - hits.mean() if hits.size else float("nan"),
            ),
            file=sys.stderr,
        )
    return 0


EVALUATIONS = {
    "pdr": "app.evaluation.pdr_eval",
    "trackfit": "app.evaluation.trackfit_eval",
    "ble-flat": "app.evaluation.ble_flat_eval",
    "ble-flat-http": "app.evaluation.ble_flat_http",
    "uwb": "app.evaluation.uwb_eval",
    "locator": "app.evaluation.locator_eval",
    "locator-http": "app.evaluation.locator_http",
    "ilc": "app.evaluation.ilc.server",
    "ilc-methods": "app.evaluation.ilc.cli",
    "ilc-floor-change": "app.evaluation.ilc.floor_change",
    "ilc-guidance": "app.evaluation.ilc.guidance",
}


def cmd_eval(args: argparse.Namespace) -> int:
    """Run one accuracy evaluation on the recordings (its own options follow its name)."""
    import importlib

    module = importlib.import_module(EVALUATIONS[args.name])
    module.main(args.rest)
    return 0


def _server_args(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--host", help="bind address (default 127.0.0.1)")
    parser.add_argument("--port", type=int, help="port (default 8000)")
    parser.add_argument("--database-url", help="SQLAlchemy URL (default: embedded SQLite)")
    parser.add_argument("--workers", type=int, help="filter worker processes (default: cores)")
    parser.add_argument("--broker", help="'memory' (default) or redis://host:port/db")
    parser.add_argument("--home", help="folder for local state (default ./var)")


def _http_args(parser: argparse.ArgumentParser) -> None:
    _server_args(parser)
    parser.add_argument(
        "--access-log",
        action="store_true",
        default=None,
        help="log every HTTP request (default: off; warnings and errors always show)",
    )


def build_parser() -> argparse.ArgumentParser:
    """Return the command-line parser."""
    parser = argparse.ArgumentParser(prog="locus", description=__doc__)
    commands = parser.add_subparsers(dest="command", required=True)
    serve = commands.add_parser("serve", help="run the API and filter workers")
    _http_args(serve)
    serve.set_defaults(func=cmd_serve)
    worker = commands.add_parser("worker", help="run a filter worker node (Redis broker)")
    _server_args(worker)
    worker.set_defaults(func=cmd_worker)
    ilc = commands.add_parser("import-ilc", help="import a Microsoft ILC site folder")
    ilc.add_argument("site_dir", help="e.g. $LOCUS_DATA_DIR/ilc/site1")
    ilc.add_argument("--site-id", required=True)
    ilc.add_argument("--server", default="http://127.0.0.1:8000")
    ilc.add_argument("--key", help="admin key (default: $LOCUS_ADMIN_KEY)")
    ilc.add_argument(
        "--rooms-walkable",
        action="store_true",
        help="shops become walkable rooms instead of barriers",
    )
    ilc.add_argument("--limit", type=int, help="at most this many walks per floor")
    ilc.add_argument("--floors", nargs="+", help="only these floors (e.g. F1 F2)")
    ilc.set_defaults(func=cmd_import_ilc)
    maps = commands.add_parser("ilc-maps", help="convert an ILC site's floors to floor maps")
    maps.add_argument("site_dir", help="e.g. $LOCUS_DATA_DIR/ilc/site1")
    maps.add_argument("out_dir", help="folder for one FLOOR.geojson per floor")
    maps.add_argument("--rooms-walkable", action="store_true", help="shops become rooms")
    maps.set_defaults(func=cmd_ilc_maps)
    replay = commands.add_parser("replay", help="replay a recording through a server")
    replay.add_argument(
        "recording",
        help="an ILC walk (.txt.gz), a JSON file of ingest bodies, or an ILC site folder "
        "(its held-out test walks)",
    )
    replay.add_argument("--site-id", help="site (default: the recording's)")
    replay.add_argument("--device-id", help="device (default: the recording's or walk's id)")
    replay.add_argument(
        "--speed", type=float, default=0.0, help="1 = real time, 10 = ten times; 0 = no pacing"
    )
    replay.add_argument("--batch-ms", type=int, default=1000, help="measurement time per batch")
    replay.add_argument("--quiet", action="store_true", help="print no positions")
    replay.add_argument("--server", default="http://127.0.0.1:8000")
    replay.add_argument("--key", help="admin or device key (default: $LOCUS_ADMIN_KEY)")
    replay.add_argument("--limit", type=int, help="at most this many test walks")
    replay.add_argument("--test-fraction", type=float, default=0.2)
    replay.add_argument("--prefix", default="replay-", help="device id prefix (site folder)")
    replay.set_defaults(func=cmd_replay)
    evaluate = commands.add_parser("eval", help="accuracy on the recordings in $LOCUS_DATA_DIR")
    evaluate.add_argument("name", choices=sorted(EVALUATIONS))
    evaluate.add_argument("rest", nargs=argparse.REMAINDER, help="options of that evaluation")
    evaluate.set_defaults(func=cmd_eval)
    demo = commands.add_parser("demo", help="serve with a demo site and simulated devices")
    _http_args(demo)
    demo.set_defaults(func=cmd_demo)
    return parser


def main(argv: Sequence[str] | None = None) -> int:
    """Entry point of the ``locus`` console script."""
    args = build_parser().parse_args(argv)
    func: Callable[[argparse.Namespace], int] = args.func
    return func(args)


if __name__ == "__main__":
    sys.exit(main())
