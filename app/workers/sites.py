"""The sites a worker process positions on: each site's engines, built ahead of its devices.

Assembling a site (floor rasters, transmitter tables, radio maps) and building
its shared engine takes seconds for a mall, too long for a device's first
batch to wait. With ``warm_sites`` the worker builds every site when it starts
and rebuilds a site in a background thread as soon as it sees its map version
change (it reads the versions every ``site_poll_s``), so devices find their
site ready. The shards of a process share one cache: a mall's rasters are tens
of MB.
"""

from __future__ import annotations

import logging
import time
from concurrent.futures import Future, ThreadPoolExecutor

from sqlalchemy import select
from sqlalchemy.exc import SQLAlchemyError
from sqlalchemy.orm import Session, sessionmaker

from app.core.config import Settings
from app.core.db import session_scope
from app.core.outages import is_outage
from app.sites.assembly import assemble_site
from app.sites.models import Site
from app.workers.trackers import SiteEngines

log = logging.getLogger(__name__)


def build_engines(db: Session, site: Site, settings: Settings) -> SiteEngines:
    """Assemble the site from the database and build its shared engine."""
    started = time.perf_counter()
    loaded = assemble_site(db=db, site=site, raster_cell=settings.raster_cell)
    engines = SiteEngines.for_site(loaded).warm()
    log.info("built site %s v%d in %.2f s", site.id, loaded.version, time.perf_counter() - started)
    return engines


class SiteCache:
    """Site id → the engines of its newest version this process has built."""

    def __init__(self, *, settings: Settings, sessions: sessionmaker[Session]) -> None:
        self.settings = settings
        self.sessions = sessions
        self.engines: dict[str, SiteEngines] = {}
        self._builds: dict[str, tuple[int, Future[SiteEngines | None]]] = {}
        self._failed: dict[str, int] = {}
        self._pool: ThreadPoolExecutor | None = None
        self._polled = -float("inf")

    def get(self, db: Session, site_id: str, version: int) -> SiteEngines | None:
        """Return the engines of the site at ``version`` or newer; None when it does not exist.

        A site this process has not built yet (or only an older version of) is
        taken from its background build when one is under way, else built here.
        """
        self._collect()
        cached = self.engines.get(site_id)
        if cached is not None and cached.site.version >= version:
            return cached
        build = self._builds.get(site_id)
        if build is not None:
            # waiting for the build under way costs less than building the site twice
            build[1].exception()
            self._collect()
            cached = self.engines.get(site_id)
            if cached is not None and cached.site.version >= version:
                return cached
        row = db.get(Site, site_id)
        if row is None:
            self.engines.pop(site_id, None)
            return None
        engines = build_engines(db, row, self.settings)
        self.engines[site_id] = engines
        return engines

    def poll(self, *, wait: bool = False) -> None:
        """Start building the sites whose map changed, forget deleted ones (``warm_sites``).

        Reads the versions at most every ``site_poll_s``; with ``wait`` at once,
        returning when every site is built (a worker starting up).
        """
        self._collect()
        now = time.monotonic()
        if not self.settings.warm_sites or (
            not wait and now - self._polled < self.settings.site_poll_s
        ):
            return
        self._polled = now
        try:
            with session_scope(self.sessions) as db:
                rows = db.execute(select(Site.id, Site.map_version))
                versions = {site_id: version for site_id, version in rows}
        except SQLAlchemyError as exc:
            # the database is away: devices keep the engines they have, the next poll retries
            log.warning("could not read the sites' versions: %s", exc.__class__.__name__)
            return
        for site_id in (set(self.engines) | set(self._failed)) - set(versions):
            self.engines.pop(site_id, None)
            self._failed.pop(site_id, None)
        for site_id, version in versions.items():
            cached = self.engines.get(site_id)
            built = -1 if cached is None else cached.site.version
            # a version whose build failed is not retried: its first device's batch says why
            if site_id in self._builds or max(built, self._failed.get(site_id, -1)) >= version:
                continue
            if self._pool is None:
                self._pool = ThreadPoolExecutor(1, thread_name_prefix="site-build")
            self._builds[site_id] = (version, self._pool.submit(self._build, site_id))
        if wait:
            for _, build in list(self._builds.values()):
                build.exception()
            self._collect()

    def _build(self, site_id: str) -> SiteEngines | None:
        with session_scope(self.sessions) as db:
            row = db.get(Site, site_id)
            return None if row is None else build_engines(db, row, self.settings)

    def _collect(self) -> None:
        """Install the background builds that have finished."""
        for site_id, (version, build) in list(self._builds.items()):
            if not build.done():
                continue
            del self._builds[site_id]
            error = build.exception()
            if error is not None and is_outage(error):
                log.warning("building site %s v%d waits for storage: %s", site_id, version, error)
                continue
            if error is not None:
                log.error("building site %s v%d failed", site_id, version, exc_info=error)
                self._failed[site_id] = version
                continue
            engines = build.result()
            cached = self.engines.get(site_id)
            if engines is not None and (
                cached is None or cached.site.version < engines.site.version
            ):
                self.engines[site_id] = engines

    def close(self) -> None:
        """Stop the background builds (one under way is left to finish on its own)."""
        if self._pool is not None:
            self._pool.shutdown(wait=False, cancel_futures=True)
