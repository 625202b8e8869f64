"""Survey recordings: surveyed waypoints plus the sample lists of ingest."""

from __future__ import annotations

from datetime import datetime
from typing import Annotated

from pydantic import BaseModel, ConfigDict, Field, model_validator

from app.core.schemas import DeviceIdentifier, DroppedSample, Identifier
from app.ingest.schemas import (
    SAMPLE_KINDS,
    BaroSample,
    Finite,
    ImuSample,
    RadioSample,
    Time,
    UwbFix,
    UwbRange,
)


class Waypoint(BaseModel):
    """A surveyed position at time ``t``; the walker moved straight between waypoints."""

    model_config = ConfigDict(extra="forbid", frozen=True)

    t: Time
    x: Finite
    y: Finite


class SurveyCreate(BaseModel):
    """A survey walk on one floor."""

    model_config = ConfigDict(extra="forbid")

    device_id: DeviceIdentifier
    floor_id: Identifier
    site_id: Identifier | None = None
    """May repeat the path's site, as an ingest body of the same device carries it."""
    name: Annotated[str, Field(max_length=200)] | None = None
    waypoints: Annotated[list[Waypoint], Field(min_length=1)]
    wifi: list[RadioSample] = Field(default_factory=list)
    ble: list[RadioSample] = Field(default_factory=list)
    imu: list[ImuSample] = Field(default_factory=list)
    uwb: list[UwbRange] = Field(default_factory=list)
    uwb_fix: list[UwbFix] = Field(default_factory=list)
    baro: list[BaroSample] = Field(default_factory=list)

    @model_validator(mode="after")
    def _ordered_waypoints(self) -> SurveyCreate:
        ts = [w.t for w in self.waypoints]
        if any(b < a for a, b in zip(ts, ts[1:], strict=False)):
            raise ValueError("waypoints must be in time order")
        return self

    def counts(self) -> dict[str, int]:
        """Return the number of waypoints and of samples of each kind."""
        return {"waypoints": len(self.waypoints)} | {k: len(getattr(self, k)) for k in SAMPLE_KINDS}


class SurveyRead(BaseModel):
    """A stored survey, without its samples."""

    model_config = ConfigDict(from_attributes=True)

    id: int
    site_id: str
    floor_id: str
    device_id: str
    name: str | None
    counts: dict[str, int]
    created_at: datetime
    dropped: list[DroppedSample] | None = None
    dropped_total: int | None = None
