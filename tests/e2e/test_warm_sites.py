"""Warm sites: a freshly started server has its sites' rasters built before a device comes, so
a new device's first batch on site1's five mall floors builds nothing and gets its position
at once; a site whose map changes is rebuilt before its next new device too. How long that
first position takes is measured by ``bench/first_position.py``."""

from __future__ import annotations

import time
from pathlib import Path
from typing import Any

import httpx
import numpy as np

from app.core.db import make_engine, make_sessionmaker, session_scope
from app.floors.service import put_floor
from app.geometry.extent import ExtentLimits
from app.sites.schemas import SiteUpsert
from app.sites.service import upsert_site
from bench.site1 import floor_maps, scan, walkable_point
from tests.conftest import ADMIN_KEY, LiveServer, migrated

SITE = "site1"
BUILT = f"built site {SITE} v"
"""What a worker logs when it has built the site's rasters."""


def _builds(server: LiveServer, at_least: int) -> int:
    """Return how many site builds the server has logged, waiting up to a minute for at least
    ``at_least`` (a rebuild follows the next version poll)."""
    deadline = time.monotonic() + 60
    while (count := server.log.read_text().count(BUILT)) < at_least:
        assert time.monotonic() < deadline, f"{count} builds logged, expected {at_least}"
        time.sleep(0.2)
    return count


def _first_position(http: httpx.Client, doc: dict[str, Any], device: str, seed: int) -> None:
    """Send a new device's first batch (two scans a second apart); it must get a position."""
    rng = np.random.default_rng(seed)
    xy = walkable_point(doc, rng)
    t0 = 1_700_000_000_000
    wifi = scan(doc, xy, t0, rng) + scan(doc, xy, t0 + 1000, rng)
    r = http.post("/v1/ingest?wait=true", json={"device_id": device, "site_id": SITE, "wifi": wifi})
    assert r.status_code == 200, r.text
    assert r.json()["positions"], f"{device}: no position from its first batch"


def test_a_loaded_mall_is_built_before_its_first_device_and_again_after_a_change(
    new_database: Any, tmp_path: Path
) -> None:
    maps = floor_maps()
    url = migrated(new_database())
    engine = make_engine(url)
    with session_scope(make_sessionmaker(engine)) as db:
        site, _ = upsert_site(db=db, site_id=SITE, body=SiteUpsert(name="ILC site1"))
        for floor_id, doc in maps.items():
            put_floor(
                db=db,
                site=site,
                floor_id=floor_id,
                doc=doc,
                limits=ExtentLimits(max_extent_m=3000.0, max_raster_cells=16_000_000, cell=0.25),
            )
    engine.dispose()
    server = LiveServer(
        database_url=url, home=tmp_path, workers=2, env={"LOCUS_SITE_POLL_S": "0.5"}
    )
    try:
        http = httpx.Client(
            base_url=server.url, headers={"Authorization": f"Bearer {ADMIN_KEY}"}, timeout=60
        )
        # ready means built: each worker built the site before the first device came
        assert server.log.read_text().count(BUILT) == 2
        # devices of both worker processes (the shard is a hash of the device id)
        for k in range(4):
            _first_position(http, maps["F1"], f"phone-{k}", k)
        assert _builds(server, 2) == 2, "a first batch built the site"

        assert http.put(f"/v1/sites/{SITE}/floors/F2", json=maps["F2"]).status_code == 200
        # the next version poll, then the mall's rebuild in the background, by each worker
        assert _builds(server, 4) == 4
        for k in range(4):
            _first_position(http, maps["F2"], f"after-{k}", 10 + k)
        assert _builds(server, 4) == 4, "a first batch after the change built the site"
    finally:
        server.stop()
