"""A site's devices: listed with their last position and when they were last heard."""

from __future__ import annotations

from fastapi import APIRouter

from app.core.schemas import LimitQuery, OffsetQuery, Page
from app.devices import service
from app.devices.schemas import DeviceRead
from app.keys.deps import SiteReaderDep
from app.positions.schemas import Position
from app.positions.service import latest_of
from app.sites.deps import SiteDep
from app.state import SessionDep

router = APIRouter(prefix="/v1/sites/{site_id}/devices", tags=["positions"])


@router.get("", response_model=Page[DeviceRead])
def list_devices(
    _: SiteReaderDep,
    site: SiteDep,
    db: SessionDep,
    limit: LimitQuery = 100,
    offset: OffsetQuery = 0,
) -> Page[DeviceRead]:
    """List the site's devices by id (admin, or the site's viewers)."""
    rows, total = service.list_devices(db=db, site_id=site.id, limit=limit, offset=offset)
    latest = latest_of(db=db, site_id=site.id, device_ids=[r.device_id for r in rows])
    items = [
        DeviceRead(
            site_id=r.site_id,
            device_id=r.device_id,
            last_seen=r.last_seen,
            last_t=r.last_t,
            position=None
            if r.device_id not in latest
            else Position.model_validate(latest[r.device_id]),
        )
        for r in rows
    ]
    return Page[DeviceRead](items=items, total=total, limit=limit, offset=offset)
