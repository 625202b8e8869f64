"""A worker's site cache: every site built at start, a changed site rebuilt in the background
before its devices ask, a deleted one forgotten; without warming, built on first use."""

from __future__ import annotations

import time
from pathlib import Path
from typing import Any

from sqlalchemy.orm import Session, sessionmaker

from app.core.config import Settings
from app.core.db import make_engine, make_sessionmaker, session_scope, upgrade_database
from app.demo import load_map
from app.floors.service import put_floor
from app.geometry.extent import ExtentLimits
from app.sites.models import Site
from app.sites.schemas import SiteUpsert
from app.sites.service import delete_site, upsert_site
from app.workers.sites import SiteCache


def _sessions(new_database: Any, sites: list[str]) -> sessionmaker[Session]:
    url = new_database()
    upgrade_database(url)
    sessions = make_sessionmaker(make_engine(url))
    for site_id in sites:
        _put_office(sessions, site_id)
    return sessions


def _put_office(sessions: sessionmaker[Session], site_id: str) -> int:
    """Store (again) the office floor in the site; return the site's new map version."""
    with session_scope(sessions) as db:
        site, _ = upsert_site(db=db, site_id=site_id, body=SiteUpsert(name=site_id))
        put_floor(
            db=db,
            site=site,
            floor_id="F1",
            doc=load_map(),
            limits=ExtentLimits(max_extent_m=3000.0, max_raster_cells=16_000_000, cell=0.5),
        )
        return site.map_version


def _versions(cache: SiteCache) -> dict[str, int]:
    return {site_id: e.site.version for site_id, e in cache.engines.items()}


def test_poll_builds_every_site_then_rebuilds_changed_ones_and_forgets_deleted(
    new_database: Any, tmp_path: Path
) -> None:
    sessions = _sessions(new_database, ["a", "b"])
    settings = Settings(home=tmp_path, raster_cell=0.5, site_poll_s=0.01)
    cache = SiteCache(settings=settings, sessions=sessions)
    cache.poll(wait=True)
    assert _versions(cache) == {"a": 1, "b": 1}
    # the shared engine is built with the site, not by the first device, and its compiled
    # loops ran once, on a throwaway device that is gone again
    engine = cache.engines["a"]._pf
    assert engine is not None and engine.devices == {}
    assert engine.bank.x.shape[0] > 0

    version = _put_office(sessions, "b")
    with session_scope(sessions) as db:
        delete_site(db=db, site=db.get(Site, "a"))
    time.sleep(0.02)
    cache.poll()
    deadline = time.monotonic() + 30
    while _versions(cache) != {"b": version} and time.monotonic() < deadline:
        time.sleep(0.05)
        cache.poll()
    assert _versions(cache) == {"b": version}
    cache.close()


def test_without_warming_a_site_is_built_on_its_first_batch(
    new_database: Any, tmp_path: Path
) -> None:
    sessions = _sessions(new_database, ["a"])
    settings = Settings(home=tmp_path, raster_cell=0.5, warm_sites=False)
    cache = SiteCache(settings=settings, sessions=sessions)
    cache.poll(wait=True)
    assert cache.engines == {}
    with sessions() as db:
        engines = cache.get(db, "a", 1)
        assert engines is not None and engines.site.version == 1
        assert cache.get(db, "a", 1) is engines
        assert cache.get(db, "missing", 0) is None
