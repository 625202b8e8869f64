"""Floors: upload a floor map, read it back, list a site's floors."""

from __future__ import annotations

import json
from typing import Any

from fastapi import APIRouter, Request, Response
from starlette.concurrency import run_in_threadpool

from app.core.errors import TooLarge, not_json
from app.core.schemas import FloorIdPath
from app.floors import service
from app.floors.models import FloorRecord
from app.floors.schemas import FloorSummary
from app.geometry.extent import ExtentLimits
from app.keys.deps import AdminDep, SiteReaderDep
from app.sites.deps import SiteDep
from app.state import SessionDep, SettingsDep

router = APIRouter(prefix="/v1/sites/{site_id}/floors", tags=["floors"])


def _summary(floor: FloorRecord) -> FloorSummary:
    return FloorSummary(
        site_id=floor.site_id, floor_id=floor.floor_id, updated_at=floor.updated_at, **floor.summary
    )


@router.put("/{floor_id}", response_model=FloorSummary)
async def put_floor(
    _: AdminDep,
    site: SiteDep,
    floor_id: FloorIdPath,
    request: Request,
    db: SessionDep,
    settings: SettingsDep,
    response: Response,
) -> FloorSummary:
    """Validate and store a floor map; a bad map gets 422 naming every bad feature."""
    raw = await request.body()
    if len(raw) > settings.floor_map_max_bytes:
        raise TooLarge(f"floor map larger than {settings.floor_map_max_bytes} bytes")
    try:
        doc: Any = json.loads(raw)
    except (json.JSONDecodeError, UnicodeDecodeError) as exc:
        raise not_json(str(exc)) from exc
    existed = service.get_floor(db=db, site_id=site.id, floor_id=floor_id) is not None
    # Rasterising a large floor takes a fraction of a second: keep it off the loop.
    floor = await run_in_threadpool(
        service.put_floor,
        db=db,
        site=site,
        floor_id=floor_id,
        doc=doc,
        limits=ExtentLimits(
            max_extent_m=settings.floor_max_extent_m,
            max_raster_cells=settings.floor_max_raster_cells,
            cell=settings.raster_cell,
        ),
    )
    db.commit()
    response.status_code = 200 if existed else 201
    return _summary(floor)


@router.get("", response_model=list[FloorSummary])
def list_floors(_: SiteReaderDep, site: SiteDep, db: SessionDep) -> list[FloorSummary]:
    """List the site's floors (summaries), lowest level first."""
    return [_summary(f) for f in service.list_floors(db=db, site_id=site.id)]


@router.get("/{floor_id}")
def get_floor(
    _: SiteReaderDep, site: SiteDep, floor_id: FloorIdPath, db: SessionDep
) -> dict[str, Any]:
    """Return the stored floor map exactly as uploaded."""
    return service.require_floor(db=db, site_id=site.id, floor_id=floor_id).geojson


@router.delete("/{floor_id}", status_code=204)
def delete_floor(_: AdminDep, site: SiteDep, floor_id: FloorIdPath, db: SessionDep) -> Response:
    """Remove a floor."""
    floor = service.require_floor(db=db, site_id=site.id, floor_id=floor_id)
    service.delete_floor(db=db, site=site, floor=floor)
    db.commit()
    return Response(status_code=204)
