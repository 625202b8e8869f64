"""A site's devices as listed."""

from __future__ import annotations

from pydantic import BaseModel, Field

from app.positions.schemas import Position


class DeviceRead(BaseModel):
    """A device of a site with when it was last heard and its latest position."""

    site_id: str
    device_id: str
    last_seen: int = Field(description="Server clock (epoch ms) when its last batch was processed.")
    last_t: int = Field(description="Newest measurement time (device clock, epoch ms) it sent.")
    position: Position | None = Field(description="Its latest live position, if it has one.")
