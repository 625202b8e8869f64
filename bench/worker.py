"""A worker's CPU per device update, through the shard alone, without HTTP or pipes.

The load benchmark measures what a client sees with the API, the workers and
the load generator sharing two cores; this one isolates a worker's round so a
change to it can be measured in a few seconds and without that noise. The
demo office is stored in a fresh SQLite database; ``D`` devices walk it as
``bench/load.py``'s fleet does, each sending one BLE scan a second, validated
by the API's own schema and carried in the workers' msgpack messages. A
shard (``app.workers.shard.Shard``, what a worker process runs) takes them in
groups of ``G`` messages, as a worker drains its inbox, on a clock that moves
one second per second of the fleet, and positions, stores and snapshots them
as it does in a server.

Prints the process CPU per device update (µs; median over the measured
seconds, after a warm-up) for each number of devices and group size, and the
share of it inside the positioning engine.

Run: ``python bench/worker.py`` (about a minute), ``--profile`` for a
cProfile of the measured seconds of the first row.
"""

from __future__ import annotations

import argparse
import cProfile
import os
import pstats
import statistics
import sys
import tempfile
import time
from collections.abc import Mapping
from pathlib import Path

os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")
ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from app import demo  # noqa: E402
from app.core.config import Settings  # noqa: E402
from app.core.db import make_engine, make_sessionmaker, session_scope, upgrade_database  # noqa: E402
from app.core.heap import settle_heap  # noqa: E402
from app.engine.positioning import PositioningEngine  # noqa: E402
from app.engine.samples import Batch, Estimate  # noqa: E402
from app.floors.service import put_floor  # noqa: E402
from app.geometry.extent import ExtentLimits  # noqa: E402
from app.ingest.schemas import IngestBatch  # noqa: E402
from app.ingest.service import batch_samples  # noqa: E402
from app.sites.schemas import SiteUpsert  # noqa: E402
from app.sites.service import upsert_site  # noqa: E402
from app.workers.messages import Ingest, decode_ingest, encode  # noqa: E402
from app.workers.shard import Shard  # noqa: E402
from bench.load import Fleet  # noqa: E402

T0 = 1_700_000_000_000


class Clock:
    """Wall time that moves only when the benchmark says so (ms)."""

    def __init__(self) -> None:
        self.now = T0 + 500

    def __call__(self) -> int:
        return self.now


def _site(home: Path) -> tuple[Settings, int]:
    """Return settings on a fresh database holding the demo office, and its map version."""
    settings = Settings(database_url=f"sqlite:///{home / 'locus.db'}", home=home)
    upgrade_database(settings.resolved_database_url)
    engine = make_engine(settings.resolved_database_url)
    with session_scope(make_sessionmaker(engine)) as db:
        site, _ = upsert_site(db=db, site_id=demo.SITE_ID, body=SiteUpsert(name="Demo office"))
        limits = ExtentLimits(
            max_extent_m=settings.floor_max_extent_m,
            max_raster_cells=settings.floor_max_raster_cells,
            cell=settings.raster_cell,
        )
        put_floor(db=db, site=site, floor_id=demo.FLOOR_ID, doc=demo.load_map(), limits=limits)
        version = site.map_version
    engine.dispose()
    return settings, version


def _second(fleet: Fleet, k: int, version: int) -> list[bytes]:
    """Return every device's k-th batch as the API hands it to a worker."""
    out = []
    for i, name in enumerate(fleet.names):
        batch = IngestBatch.model_validate_json(fleet.body(i, k))
        message = Ingest(f"{name}-{k}", demo.SITE_ID, name, version, batch_samples(batch))
        out.append(encode(message))
    return out


def measure(
    settings: Settings,
    version: int,
    devices: int,
    group: int,
    warmup: int,
    seconds: int,
    profile: bool,
) -> tuple[float, float]:
    """Return the median CPU µs per device update and the engine's share of it."""
    sessions = make_sessionmaker(make_engine(settings.resolved_database_url))
    clock = Clock()
    shard = Shard(shard=0, settings=settings, sessions=sessions, clock=clock)
    # as a worker process does once it is ready: startup objects out of the collector's passes
    settle_heap()
    fleet = Fleet(devices, f"w{devices}g{group}", T0)
    engine_seconds = 0.0
    process = PositioningEngine.process

    def timed(self: PositioningEngine, batches: Mapping[str, Batch]) -> dict[str, list[Estimate]]:
        nonlocal engine_seconds
        started = time.process_time()
        try:
            return process(self, batches)
        finally:
            engine_seconds += time.process_time() - started

    PositioningEngine.process = timed  # type: ignore[method-assign]
    profiler = cProfile.Profile() if profile else None
    per_update: list[float] = []
    engine_share: list[float] = []
    try:
        for k in range(warmup + seconds):
            payloads = _second(fleet, k, version)
            measured = k >= warmup
            if measured and profiler is not None:
                profiler.enable()
            engine_seconds = 0.0
            started = time.process_time()
            for at in range(0, len(payloads), group):
                shard.handle([decode_ingest(p) for p in payloads[at : at + group]])
                shard.tick()
            cpu = time.process_time() - started
            if profiler is not None:
                profiler.disable()
            if measured:
                per_update.append(cpu / devices * 1e6)
                engine_share.append(engine_seconds / cpu)
            clock.now += 1000
    finally:
        PositioningEngine.process = process  # type: ignore[method-assign]
        shard.drain()
    if profiler is not None:
        for sort in ("cumulative", "tottime"):
            pstats.Stats(profiler).sort_stats(sort).print_stats(35)
    return statistics.median(per_update), statistics.median(engine_share)


def main() -> None:
    """Print the table."""
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--devices", type=int, nargs="+", default=[100, 1000, 2500])
    parser.add_argument("--groups", type=int, nargs="+", default=[10, 50])
    parser.add_argument("--warmup", type=int, default=8, help="seconds before measuring")
    parser.add_argument("--seconds", type=int, default=10, help="seconds measured")
    parser.add_argument("--profile", action="store_true")
    args = parser.parse_args()
    print("devices  group  µs/update  engine share")
    with tempfile.TemporaryDirectory() as home:
        settings, version = _site(Path(home))
        for devices in args.devices:
            for group in args.groups:
                us, share = measure(
                    settings, version, devices, group, args.warmup, args.seconds, args.profile
                )
                args.profile = False
                print(f"{devices:7d}  {group:5d}  {us:9.1f}  {share:12.2f}", flush=True)


if __name__ == "__main__":
    main()
