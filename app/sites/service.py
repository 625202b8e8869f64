"""Sites: create, read, list, delete, and mark their engine inputs changed."""

from __future__ import annotations

from sqlalchemy import delete, func, select
from sqlalchemy.orm import Session

from app.analytics.models import ZoneEventRecord
from app.core.errors import NotFound
from app.devices.models import Device, DeviceStateRecord
from app.outputs.models import OutboxRow
from app.positions.models import PositionRecord
from app.sites.models import Site
from app.sites.schemas import SiteUpsert


def require_site(*, db: Session, site_id: str) -> Site:
    """Return the site or raise NotFound."""
    site = db.get(Site, site_id)
    if site is None:
        raise NotFound(f"site '{site_id}' not found")
    return site


def upsert_site(*, db: Session, site_id: str, body: SiteUpsert) -> tuple[Site, bool]:
    """Create the site or update its name and engine; return it and whether it was created."""
    site = db.get(Site, site_id)
    created = site is None
    if site is None:
        site = Site(id=site_id, name=body.name, engine="hmm", map_version=0)
        db.add(site)
    site.name = body.name
    engine = body.chosen_engine()
    if engine is not None and engine != site.engine:
        site.engine = engine
        # the engine choice decides which filter new devices get: workers must reload
        site.map_version = (site.map_version or 0) + 1
    db.flush()
    return site, created


def list_sites(*, db: Session, only: str | None, limit: int, offset: int) -> tuple[list[Site], int]:
    """Return a page of sites (only one when the caller is scoped to it) and the total."""
    query = select(Site)
    if only is not None:
        query = query.where(Site.id == only)
    total = db.scalar(select(func.count()).select_from(query.subquery())) or 0
    rows = db.scalars(query.order_by(Site.id).limit(limit).offset(offset)).all()
    return list(rows), total


def delete_site(*, db: Session, site: Site) -> None:
    """Delete the site with its floors, surveys, devices, positions, device states, outputs
    and their outbox."""
    db.execute(delete(PositionRecord).where(PositionRecord.site_id == site.id))
    db.execute(delete(ZoneEventRecord).where(ZoneEventRecord.site_id == site.id))
    db.execute(delete(DeviceStateRecord).where(DeviceStateRecord.site_id == site.id))
    db.execute(delete(Device).where(Device.site_id == site.id))
    db.execute(delete(OutboxRow).where(OutboxRow.site_id == site.id))
    db.delete(site)
    db.flush()


def bump_map_version(*, db: Session, site: Site) -> None:
    """Mark the site's engine inputs as changed so workers rebuild their view."""
    site.map_version = (site.map_version or 0) + 1
    db.flush()
