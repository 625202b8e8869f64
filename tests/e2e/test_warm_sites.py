"""Warm sites: a freshly started server has its sites' rasters built before a device comes, so
a new device's first position on site1's five mall floors arrives within a second of its
first batch; a site whose map changes is rebuilt before its next new device too."""

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
BUDGET_S = 1.0


def _first_position_s(http: httpx.Client, doc: dict[str, Any], device: str, seed: int) -> float:
    """Send a new device's first batch (two scans a second apart) and return its answer time."""
    rng = np.random.default_rng(seed)
    xy = walkable_point(doc, rng)
    t0 = 1_700_000_000_000
    wifi = scan(doc, xy, t0, rng) + scan(doc, xy, t0 + 1000, rng)
    started = time.perf_counter()
    r = http.post("/v1/ingest?wait=true", json={"device_id": device, "site_id": SITE, "wifi": wifi})
    elapsed = time.perf_counter() - started
    assert r.status_code == 200, r.text
    assert r.json()["positions"], f"{device}: no position from its first batch"
    return elapsed


def test_first_position_on_a_loaded_mall_within_a_second(new_database: Any, tmp_path: Path) -> None:
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
        # devices of both worker processes (the shard is a hash of the device id)
        fresh = [_first_position_s(http, maps["F1"], f"phone-{k}", k) for k in range(4)]
        assert max(fresh) < BUDGET_S, fresh

        assert http.put(f"/v1/sites/{SITE}/floors/F2", json=maps["F2"]).status_code == 200
        time.sleep(6)  # the next version poll, then the mall's rebuild in the background
        changed = [_first_position_s(http, maps["F2"], f"after-{k}", 10 + k) for k in range(4)]
        assert max(changed) < BUDGET_S, changed
    finally:
        server.stop()
    log = server.log.read_text()
    assert log.count(f"built site {SITE} v") >= 4, "each worker builds the site at start and again"
