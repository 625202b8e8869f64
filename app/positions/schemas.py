"""Position messages and listings."""

from __future__ import annotations

from pydantic import BaseModel, ConfigDict


class Position(BaseModel):
    """A position message (docs/api.md, Positions)."""

    model_config = ConfigDict(from_attributes=True)

    type: str = "position"
    device_id: str
    site_id: str
    floor_id: str | None
    t: int
    x: float
    y: float
    z: float
    heading: float | None
    accuracy: float
    speed: float | None
    method: str
    computed_at: int
    smoothed: bool = False


class PositionPage(BaseModel):
    """A page of a device's history; ask again with ``from=next_from`` for more."""

    items: list[Position]
    limit: int
    next_from: int | None
