"""Analytics: a zone's occupancy over time, a floor's heatmap, a site's positions exported."""

from __future__ import annotations

from typing import Annotated, Any, Literal

import numpy as np
import shapely
from fastapi import APIRouter, Path, Query, Request, Response
from fastapi.responses import StreamingResponse
from starlette.concurrency import run_in_threadpool

from app.analytics import export, service
from app.analytics.heatmap import Grid, place, to_json
from app.analytics.occupancy import bucket_edges, bucket_occupancy
from app.analytics.schemas import Heatmap, Occupancy, OccupancyBucket
from app.core.config import Settings
from app.core.errors import Invalid, NotFound
from app.core.schemas import FloorIdPath
from app.floors.render import grid_png
from app.floors.service import list_floors, require_floor
from app.geometry.floormap import parse_floor_map
from app.keys.deps import SiteReaderDep
from app.sites.deps import SiteDep
from app.state import SessionDep, SettingsDep, app_state

router = APIRouter(prefix="/v1/sites/{site_id}", tags=["analytics"])

TimeRequired = Annotated[int, Query(ge=0, le=2**53)]
DAY_MS = 86_400_000


def _check_range(t_from: int, t_to: int, settings: Settings) -> None:
    """Refuse an empty or reversed range, or one longer than the configured limit."""
    if t_to <= t_from:
        raise Invalid(f"'to' ({t_to}) must be after 'from' ({t_from})")
    days = (t_to - t_from) / DAY_MS
    if days > settings.analytics_max_range_days:
        raise Invalid(
            f"the range is {days:.2f} days; at most {settings.analytics_max_range_days:g} "
            "days (analytics_max_range_days)"
        )


@router.get("/zones/{zone}/occupancy", response_model=Occupancy)
def occupancy(
    _: SiteReaderDep,
    site: SiteDep,
    zone: Annotated[str, Path(min_length=1, max_length=200)],
    db: SessionDep,
    settings: SettingsDep,
    t_from: Annotated[TimeRequired, Query(alias="from")],
    t_to: Annotated[TimeRequired, Query(alias="to")],
    bucket_s: Annotated[int, Query(ge=60, le=86_400)] = 3600,
) -> Occupancy:
    """Per bucket of ``[from, to)``: distinct devices inside the zone, entries, dwell (s)."""
    _check_range(t_from, t_to, settings)
    bucket_ms = bucket_s * 1000
    buckets = -(-(t_to - t_from) // bucket_ms)
    if buckets > settings.analytics_max_buckets:
        raise Invalid(
            f"{buckets} buckets of {bucket_s} s; at most {settings.analytics_max_buckets} "
            "(analytics_max_buckets): use a larger bucket_s or a shorter range"
        )
    names = {
        name
        for f in list_floors(db=db, site_id=site.id)
        for name, _shape in parse_floor_map(f.geojson).zones
    }
    if zone not in names:
        raise NotFound(f"zone '{zone}' not found in site '{site.id}'")
    _devices, visits = service.zone_visits(
        db=db, site_id=site.id, zone=zone, t_from=t_from, t_to=t_to
    )
    result = bucket_occupancy(visits, bucket_edges(t_from, t_to, bucket_ms))
    return Occupancy(
        zone=zone,
        bucket_s=bucket_s,
        buckets=[
            OccupancyBucket(t=int(t), devices=int(d), entries=int(e), dwell_s=round(w / 1000, 3))
            for t, d, e, w in zip(
                result.edges[:-1], result.devices, result.entries, result.dwell_ms, strict=True
            )
        ],
    )


@router.get(
    "/floors/{floor_id}/heatmap",
    response_model=Heatmap,
    responses={200: {"content": {"image/png": {}}, "description": "JSON grid, or a PNG heatmap"}},
)
async def heatmap(
    _: SiteReaderDep,
    site: SiteDep,
    floor_id: FloorIdPath,
    request: Request,
    db: SessionDep,
    settings: SettingsDep,
    t_from: Annotated[TimeRequired, Query(alias="from")],
    t_to: Annotated[TimeRequired, Query(alias="to")],
    cell: Annotated[float, Query(ge=0.1, le=50)] = 1.0,
) -> Any:
    """Device-seconds the floor's positions spent in each cell during ``[from, to)``."""
    _check_range(t_from, t_to, settings)
    floor = require_floor(db=db, site_id=site.id, floor_id=floor_id)
    fmap = parse_floor_map(floor.geojson)
    grid = Grid.over(fmap.outline.bounds, cell)
    cells = grid.shape[0] * grid.shape[1]
    if cells > settings.heatmap_max_cells:
        raise Invalid(
            f"{cells} cells at {cell} m; at most {settings.heatmap_max_cells} "
            "(heatmap_max_cells): use a larger cell"
        )
    i, j, seconds = await run_in_threadpool(
        service.heatmap_cells,
        db=db,
        site_id=site.id,
        floor_id=floor_id,
        grid=grid,
        t_from=t_from,
        t_to=t_to,
        cap_ms=round(settings.heatmap_gap_cap_s * 1000),
    )
    values = place(grid, i, j, seconds)
    X, Y = grid.centres()
    inside = shapely.contains_xy(fmap.outline, X, Y)
    if "image/png" in request.headers.get("accept", ""):
        shown = np.where(inside, values, np.nan)
        top = float(shown[np.isfinite(shown)].max()) if np.isfinite(shown).any() else 0.0
        png = await run_in_threadpool(
            grid_png,
            fmap,
            shown,
            grid.origin,
            grid.cell,
            title=f"{site.id}/{floor_id}: device-seconds per {cell:g} m cell",
            label="device-seconds",
            cmap="inferno",
            vmax=top or 1.0,
        )
        return Response(png, media_type="image/png")
    return to_json(grid, values, inside)


@router.get(
    "/positions",
    response_class=StreamingResponse,
    responses={200: {"content": {"text/csv": {}, "application/geo+json": {}}}},
)
def site_positions(
    _: SiteReaderDep,
    site: SiteDep,
    request: Request,
    settings: SettingsDep,
    t_from: Annotated[TimeRequired, Query(alias="from")],
    t_to: Annotated[TimeRequired, Query(alias="to")],
    format: Literal["csv", "geojson"] = "csv",
) -> StreamingResponse:
    """Every live position of the site's devices in ``[from, to]`` as CSV or GeoJSON, streamed."""
    _check_range(t_from, t_to, settings)
    return export.response(
        app_state(request).sessions,
        export.site_rows(site.id),
        format,
        t_from=t_from,
        t_to=t_to,
        page_rows=settings.export_page_rows,
    )
