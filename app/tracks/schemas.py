"""Energy-saving tracks: a dead-reckoned polyline as link lengths and turns."""

from __future__ import annotations

import math
from typing import Annotated, Literal

from pydantic import BaseModel, ConfigDict, Field, model_validator

from app.core.schemas import DeviceIdentifier, Identifier
from app.ingest.schemas import Finite, Rssi, Time, TxId

Scale = Annotated[float, Field(gt=0.5, lt=2.0, allow_inf_nan=False)]
TurnChange = Annotated[float, Field(ge=-1.0, le=1.0, allow_inf_nan=False)]


TrackStatus = Literal["queued", "running", "done", "failed"]
"""Where a track fit stands: queued, running, then done or failed."""


class Point(BaseModel):
    """A point of the floor's local frame (m)."""

    model_config = ConfigDict(extra="forbid")

    x: Finite
    y: Finite


class ScanReading(BaseModel):
    """One access point of a WiFi scan: transmitter id (BSSID) and RSSI (dBm)."""

    model_config = ConfigDict(extra="forbid")

    id: TxId
    rssi: Rssi


class Segment(BaseModel):
    """One link: end time, length (m) and turn from the previous link (rad, CCW positive).

    ``wifi`` is a scan taken at the link's end, an absolute anchor the fit
    scores against the floor's radio map (ignored while the site has none).
    ``heading`` is the link's absolute direction as the phone's compass gives
    it: soft evidence whose constant bias the fit estimates.
    """

    model_config = ConfigDict(extra="forbid")

    t: Time
    length: Annotated[float, Field(ge=0, le=100, allow_inf_nan=False)]
    turn: Annotated[float, Field(ge=-2 * math.pi, le=2 * math.pi, allow_inf_nan=False)]
    wifi: Annotated[list[ScanReading], Field(min_length=1, max_length=500)] | None = None
    heading: Annotated[float, Field(ge=0, lt=360, allow_inf_nan=False)] | None = Field(
        default=None,
        description="Absolute direction of this link (a compass), degrees clockwise from +y.",
    )


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
    heading_sigma_deg: Annotated[float, Field(gt=0, le=90, allow_inf_nan=False)] | None = Field(
        default=None,
        description="Standard deviation of one link heading (degrees); 10 when not given.",
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
    radius: float | None = None
    """Radius (m) within which about 68 % of such points lie from the walker."""


class TrackCandidate(BaseModel):
    """One hypothesis the fit refined: its rotation, scale, drift and score.

    ``points`` are given for the runner-up of an ambiguous fit (the best's
    are the track's own).
    """

    rotation: float
    """Direction of the first link before fitting, degrees clockwise from +y."""
    scale: float
    """Step-length scale of the walker applied to every link."""
    drift: float
    """Heading drift removed from the turns (degrees per second, CCW positive)."""
    score: float | None
    """Lower is better; null when no track of the hypothesis survived."""
    points: list[FittedPoint] | None = None


class TrackRead(BaseModel):
    """A track's status and, when done, its fitted points and what the fit knows of itself."""

    track_id: str
    device_id: str
    site_id: str
    floor_id: str
    status: TrackStatus
    points: list[FittedPoint] = Field(default_factory=list)
    score: float | None = None
    elapsed_ms: float | None = None
    error: str | None = None
    rotation: float | None = None
    """Chosen direction of the first link before fitting, degrees clockwise from +y."""
    scale: float | None = None
    """Chosen walker step-length scale."""
    drift: float | None = None
    """Chosen heading drift (degrees per second)."""
    relaxed: list[int] | None = None
    """Per link: 0 placed normally, 1 with wider changes, 2 across a wall, 3 dead-reckoned."""
    spread: float | None = None
    """How far apart (m) the ends of fits scoring as well as the chosen one lie."""
    accuracy: float | None = None
    """Radius (m) of the last point, the device's position: half the grid, the spread, and
    when the fit is ambiguous the distance to the runner-up's end (either may be the walker)."""
    anchors: int | None = None
    """WiFi scans scored against the radio map."""
    ambiguous: bool | None = None
    """A distinct fit scored within the ambiguity margin of the chosen one."""
    candidates: list[TrackCandidate] | None = None
    """The chosen fit and the runner-up (the best distinct one), with their scores."""
    fitted: bool | None = None
    """The points are the fit; false: they are the uploaded track placed at its start."""
    reason: str | None = None
    """Why the track was not fitted."""
    margin: float | None = None
    """Runner-up's score less the chosen fit's (null: no distinct hypothesis survived)."""
    bias: float | None = None
    """Estimated bias of the per-link headings (degrees, clockwise positive)."""
