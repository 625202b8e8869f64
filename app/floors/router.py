"""Floors: upload a floor map, read it back, list a site's floors."""

from __future__ import annotations

import json
from typing import Any

from fastapi import APIRouter, Request, Response
from starlette.concurrency import run_in_threadpool

from app.core.deps import AdminDep, SessionDep, SettingsDep, SiteReaderDep
from app.core.errors import ApiError
from app.core.schemas import FloorIdPath
from app.floors import service
from app.floors.models import Floor
from app.floors.schemas import FloorSummary
from app.geometry.floormap import FloorMapError
from app.sites.deps import SiteDep

router = APIRouter(prefix="/v1/sites/{site_id}/floors", tags=["floors"])


def _summary(floor: Floor) -> FloorSummary:
    return FloorSummary(
        site_id=floor.site_id, floor_id=floor.floor_id, updated_at=floor.updated_at, **floor.summary
    )


def _load(db: SessionDep, site_id: str, floor_id: str) -> Floor:
    floor = service.get_floor(db=db, site_id=site_id, floor_id=floor_id)
    if floor is None:
        raise ApiError(404, f"floor '{floor_id}' not found in site '{site_id}'")
    return floor


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
        raise ApiError(413, f"floor map larger than {settings.floor_map_max_bytes} bytes")
    try:
        doc: Any = json.loads(raw)
    except (json.JSONDecodeError, UnicodeDecodeError) as exc:
        raise ApiError(400, f"body is not JSON: {exc}") from exc
    existed = service.get_floor(db=db, site_id=site.id, floor_id=floor_id) is not None
    try:
        # Rasterising a large floor takes a fraction of a second: keep it off the loop.
        floor = await run_in_threadpool(
            service.put_floor,
            db=db,
            site=site,
            floor_id=floor_id,
            doc=doc,
            raster_cell=settings.raster_cell,
        )
    except FloorMapError as exc:
        db.rollback()
        raise ApiError(
            422,
            f"floor map rejected: {len(exc.problems)} problem(s)",
            code="invalid_floor_map",
            details=[p.as_dict() for p in exc.problems],
        ) from exc
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
    return _load(db, site.id, floor_id).geojson


@router.delete("/{floor_id}", status_code=204)
def delete_floor(_: AdminDep, site: SiteDep, floor_id: FloorIdPath, db: SessionDep) -> Response:
    """Remove a floor."""
    service.delete_floor(db=db, site=site, floor=_load(db, site.id, floor_id))
    db.commit()
    return Response(status_code=204)
