"""Analytics query times on PostgreSQL: a zone's occupancy over a day in hourly buckets, and
a floor's heatmap over a day and over a week.

Creates its own database on the local PostgreSQL (127.0.0.1:5432, user postgres), fills
it with ``generate_series`` (``--devices`` at ``--hz`` for ``--days`` days of positions,
each device walking a loop over a 100 × 50 m floor; each device enters the zone at the
start of every hour and leaves 10 minutes later), times the queries through the services
the routes call (median of ``--repeats``) and drops the database. Prints a Markdown table:

    python -m bench.analytics --devices 50 --hz 1 --days 7
"""

from __future__ import annotations

import argparse
import statistics
import time
import uuid
from collections.abc import Callable

from sqlalchemy import create_engine, text

from app.analytics.heatmap import Grid
from app.analytics.occupancy import bucket_edges, bucket_occupancy
from app.analytics.service import heatmap_cells, zone_visits
from app.core.db import make_engine, make_sessionmaker, upgrade_database

BASE = "postgresql+psycopg://postgres@127.0.0.1:5432/postgres"
T0 = 1_700_000_000_000 - 1_700_000_000_000 % 86_400_000
DAY = 86_400_000


def fill(url: str, devices: int, hz: float, days: float) -> int:
    """Insert the positions and zone events; return the positions' count."""
    period = round(1000 / hz)
    steps = int(days * DAY / period)
    engine = create_engine(url)
    with engine.begin() as conn:
        conn.execute(
            text(
                "INSERT INTO positions (site_id, device_id, floor_id, t, x, y, z, accuracy, "
                "method, computed_at, smoothed) "
                "SELECT 'bench', 'd' || d, 'G', :t0 + s * :period, "
                "50 + 45 * cos((s + d * 97) / 600.0), 25 + 20 * sin((s + d * 97) / 600.0), "
                "0, 1.0, 'ekf', 0, false "
                "FROM generate_series(0, :devices - 1) d, generate_series(0, :steps - 1) s"
            ),
            {"t0": T0, "period": period, "devices": devices, "steps": steps},
        )
        hours = int(days * 24)
        conn.execute(
            text(
                "INSERT INTO zone_events (site_id, zone, device_id, floor_id, event, t) "
                "SELECT 'bench', 'Food court', 'd' || d, 'G', e, "
                ":t0 + h * 3600000 + d * 1000 + CASE WHEN e = 'enter' THEN 0 ELSE 600000 END "
                "FROM generate_series(0, :devices - 1) d, generate_series(0, :hours - 1) h, "
                "unnest(ARRAY['enter', 'exit']) e"
            ),
            {"t0": T0, "devices": devices, "hours": hours},
        )
        conn.execute(text("ANALYZE"))
    engine.dispose()
    return devices * steps


def median_s(run: Callable[[], object], repeats: int) -> float:
    """Return the median wall time (s) of ``repeats`` runs."""
    times = []
    for _ in range(repeats):
        started = time.perf_counter()
        run()
        times.append(time.perf_counter() - started)
    return statistics.median(times)


def main() -> None:
    """Fill a fresh database, time the queries, print the table, drop the database."""
    parser = argparse.ArgumentParser(description=__doc__)
    parser.add_argument("--devices", type=int, default=50)
    parser.add_argument("--hz", type=float, default=1.0)
    parser.add_argument("--days", type=float, default=7.0)
    parser.add_argument("--repeats", type=int, default=3)
    args = parser.parse_args()
    name = f"locus_bench_{uuid.uuid4().hex[:8]}"
    admin = create_engine(BASE, isolation_level="AUTOCOMMIT")
    with admin.connect() as conn:
        conn.execute(text(f'CREATE DATABASE "{name}"'))
    url = BASE.rsplit("/", 1)[0] + "/" + name
    try:
        upgrade_database(url)
        started = time.perf_counter()
        rows = fill(url, args.devices, args.hz, args.days)
        filled = time.perf_counter() - started
        sessions = make_sessionmaker(make_engine(url))
        grid = Grid.over((0.0, 0.0, 100.0, 50.0), 1.0)
        last_day = T0 + int((args.days - 1) * DAY) if args.days >= 1 else T0

        def occupancy() -> object:
            with sessions() as db:
                _, visits = zone_visits(
                    db=db, site_id="bench", zone="Food court", t_from=last_day, t_to=last_day + DAY
                )
            return bucket_occupancy(visits, bucket_edges(last_day, last_day + DAY, 3_600_000))

        def heatmap(span: int) -> Callable[[], object]:
            def run() -> object:
                with sessions() as db:
                    return heatmap_cells(
                        db=db,
                        site_id="bench",
                        floor_id="G",
                        grid=grid,
                        t_from=T0,
                        t_to=T0 + span,
                        cap_ms=5000,
                    )

            return run

        print(
            f"{rows:,} positions ({args.devices} devices at {args.hz:g} Hz for {args.days:g} "
            f"days), filled in {filled:.1f} s; median of {args.repeats}\n"
        )
        print("| query | median (s) |")
        print("|---|---|")
        print(f"| occupancy, 1 day in hourly buckets | {median_s(occupancy, args.repeats):.3f} |")
        print(f"| heatmap, 1 day, 1 m cells | {median_s(heatmap(DAY), args.repeats):.3f} |")
        if args.days >= 7:
            week = median_s(heatmap(7 * DAY), args.repeats)
            print(f"| heatmap, 1 week, 1 m cells | {week:.3f} |")
    finally:
        with admin.connect() as conn:
            conn.execute(text(f'DROP DATABASE IF EXISTS "{name}" WITH (FORCE)'))
        admin.dispose()


if __name__ == "__main__":
    main()
