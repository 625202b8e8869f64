"""Energy-saving tracks: a dead-reckoned polyline as link lengths and turns."""

from __future__ import annotations

import math
from typing import Annotated, Literal

from pydantic import BaseModel, ConfigDict, Field, model_validator

from app.core.schemas import DeviceIdentifier, Identifier
from app.ingest.schemas import Finite, Time

Scale = Annotated[float, Field(gt=0.5, lt=2.0, allow_inf_nan=False)]
TurnChange = Annotated[float, Field(ge=-1.0, le=1.0, allow_inf_nan=False)]


TrackStatus = Literal["queued", "running", "done", "failed"]
"""Where a track fit stands: queued, running, then done or failed."""


class Point(BaseModel):
    """A point of the floor's local frame (m)."""

    model_config = ConfigDict(extra="forbid")

    x: Finite
    y: Finite


class Segment(BaseModel):
    """One link: end time, length (m) and turn from the previous link (rad, CCW positive)."""

    model_config = ConfigDict(extra="forbid")

    t: Time
    length: Annotated[float, Field(ge=0, le=100, allow_inf_nan=False)]
    turn: Annotated[float, Field(ge=-2 * math.pi, le=2 * math.pi, allow_inf_nan=False)]


class TrackCreate(BaseModel):
    """A track to fit; ``grid``, ``scales`` and ``turns`` override the fitter's defaults."""

    model_config = ConfigDict(extra="forbid")

    device_id: DeviceIdentifier
    site_id: Identifier
    floor_id: Identifier
    start: Point
    t0: Time
    segments: Annotated[list[Segment], Field(min_length=1, max_length=20_000)]
    heading: Annotated[float, Field(ge=0, lt=360, allow_inf_nan=False)] | None = Field(
        default=None, description="Direction of the first link, degrees clockwise from +y."
    )
    grid: Annotated[float, Field(ge=0.25, le=5.0)] | None = None
    scales: Annotated[list[Scale], Field(min_length=1, max_length=9)] | None = None
    turns: Annotated[list[TurnChange], Field(min_length=1, max_length=41)] | None = None

    @model_validator(mode="after")
    def _ordered(self) -> TrackCreate:
        ts = [self.t0, *(s.t for s in self.segments)]
        if any(b < a for a, b in zip(ts, ts[1:], strict=False)):
            raise ValueError("segment times must not decrease and not precede t0")
        return self


class TrackAccepted(BaseModel):
    """The queued track's id."""

    track_id: str


class FittedPoint(BaseModel):
    """A fitted point at the time the device reached it."""

    t: int
    x: float
    y: float


class TrackRead(BaseModel):
    """A track's status and, when done, its fitted points."""

    track_id: str
    device_id: str
    site_id: str
    floor_id: str
    status: TrackStatus
    points: list[FittedPoint] = Field(default_factory=list)
    score: float | None = None
    elapsed_ms: float | None = None
    error: str | None = None
