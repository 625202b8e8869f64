"""Planning: expected accuracy of a floor's layout, as JSON grids or a PNG heatmap."""

from __future__ import annotations

from typing import Annotated, Any, Literal

from fastapi import APIRouter, Query, Request, Response
from starlette.concurrency import run_in_threadpool

from app.core.schemas import FloorIdPath
from app.keys.deps import SiteReaderDep
from app.planning import service
from app.sites.deps import SiteDep
from app.state import SessionDep, SettingsDep

router = APIRouter(prefix="/v1/sites/{site_id}/floors/{floor_id}", tags=["planning"])


@router.get(
    "/accuracy",
    responses={200: {"content": {"image/png": {}}, "description": "JSON grids, or a PNG heatmap"}},
)
async def accuracy(
    _: SiteReaderDep,
    site: SiteDep,
    floor_id: FloorIdPath,
    request: Request,
    db: SessionDep,
    settings: SettingsDep,
    tech: Literal["ble", "uwb"] = "ble",
    z: Annotated[float, Query(ge=-10, le=50)] = 1.0,
    cell: Annotated[float, Query(ge=0.1, le=20)] = 0.5,
    samples: Annotated[int, Query(ge=1, le=10_000)] = 50,
) -> Any:
    """Standard deviations a least-squares fix would have at each cell centre at height z."""
    result = await run_in_threadpool(
        service.accuracy_map,
        db=db,
        site=site,
        floor_id=floor_id,
        tech=tech,
        z=z,
        cell=cell,
        samples=samples,
        raster_cell=settings.raster_cell,
        max_cells=settings.planning_max_cells,
    )
    if "image/png" in request.headers.get("accept", ""):
        png = await run_in_threadpool(
            service.render_png, db=db, site=site, floor_id=floor_id, result=result, tech=tech
        )
        return Response(png, media_type="image/png")
    return result.to_json()
