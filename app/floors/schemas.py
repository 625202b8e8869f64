"""Response bodies of the floors API (the request body is the GeoJSON map itself)."""

from __future__ import annotations

from datetime import datetime
from typing import Any

from pydantic import BaseModel


class FloorSummary(BaseModel):
    """What an upload answers: the map's extent, areas, counts and raster size."""

    site_id: str
    floor_id: str
    level: int
    height: float
    name: str | None
    bounds: list[float]
    outline_area: float
    walkable_area: float
    counts: dict[str, int]
    raster: dict[str, Any]
    updated_at: datetime | None = None
