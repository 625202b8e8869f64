"""A short-lived cache of site versions for the ingest hot path."""

from __future__ import annotations

import time

from sqlalchemy.orm import Session, sessionmaker

from app.sites.models import Site


class SiteVersions:
    """Site id → map version, re-read from the database at most every ``ttl_s`` seconds."""

    def __init__(self, sessions: sessionmaker[Session], *, ttl_s: float) -> None:
        self.sessions = sessions
        self.ttl_s = ttl_s
        self._entries: dict[str, tuple[float, int | None]] = {}

    def get(self, site_id: str) -> int | None:
        """Return the site's map version, or None when the site does not exist."""
        now = time.monotonic()
        hit = self._entries.get(site_id)
        if hit is not None and now - hit[0] < self.ttl_s:
            return hit[1]
        with self.sessions() as db:
            site = db.get(Site, site_id)
            version = None if site is None else site.map_version
        self._entries[site_id] = (now, version)
        return version

    def invalidate(self, site_id: str) -> None:
        """Forget a site after this node changed it."""
        self._entries.pop(site_id, None)
