"""Fixtures of the worker tests: the demo office stored in a database, its engines, and a
Redis connection."""

from __future__ import annotations

import os
from collections.abc import Iterator
from typing import Any

import pytest
import redis
from sqlalchemy.orm import Session, sessionmaker

from app.core.db import make_engine, make_sessionmaker, session_scope, upgrade_database
from app.demo import load_map
from app.floors.service import put_floor
from app.geometry.extent import ExtentLimits
from app.sites.assembly import LoadedSite, assemble_site
from app.sites.models import Site
from app.sites.schemas import SiteUpsert
from app.sites.service import upsert_site
from app.workers.trackers import SiteEngines

SITE_ID = "office"
RASTER_CELL = 0.25
REDIS_URL = os.environ.get("LOCUS_TEST_REDIS_URL", "redis://127.0.0.1:6379/14")


@pytest.fixture
def redis_client() -> Iterator[redis.Redis]:
    """A connection to the test Redis database; the test is skipped without one."""
    r = redis.Redis.from_url(REDIS_URL)
    try:
        r.ping()
    except redis.RedisError:
        pytest.skip(f"no Redis at {REDIS_URL}")
    yield r
    r.close()


@pytest.fixture(scope="session")
def office_url(new_database: Any) -> str:
    """A database holding the demo office as site ``office`` (one floor, F1)."""
    url = new_database()
    upgrade_database(url)
    engine = make_engine(url)
    with session_scope(make_sessionmaker(engine)) as db:
        site, _ = upsert_site(db=db, site_id=SITE_ID, body=SiteUpsert(name="Demo office"))
        limits = ExtentLimits(max_extent_m=3000, max_raster_cells=16_000_000, cell=RASTER_CELL)
        put_floor(db=db, site=site, floor_id="F1", doc=load_map(), limits=limits)
    engine.dispose()
    return url


@pytest.fixture(scope="session")
def office_sessions(office_url: str) -> sessionmaker[Session]:
    """Sessions on the office database."""
    return make_sessionmaker(make_engine(office_url))


@pytest.fixture(scope="session")
def office(office_sessions: sessionmaker[Session]) -> LoadedSite:
    """The office as workers see it."""
    with session_scope(office_sessions) as db:
        row = db.get(Site, SITE_ID)
        assert row is not None
        return assemble_site(db=db, site=row, raster_cell=RASTER_CELL)


@pytest.fixture
def engines(office: LoadedSite) -> SiteEngines:
    """Fresh engines of the office (a particle-filter engine of its own per test)."""
    return SiteEngines.for_site(office)
