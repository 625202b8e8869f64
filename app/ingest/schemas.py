"""Ingest bodies: a device's batch of measurements and a locator's sightings.

Validation is strict and complete: a batch with one bad sample is rejected
whole (422 naming the sample), so nothing is half-accepted.
"""

from __future__ import annotations

from typing import Annotated, Any

from pydantic import AfterValidator, BaseModel, ConfigDict, Field, StrictInt, model_validator

from app.core.sample_policy import MAX_T_MS, MIN_T_MS, check_ms
from app.core.schemas import DeviceIdentifier, DroppedSample, Identifier
from app.positions.schemas import Position

Finite = Annotated[float, Field(allow_inf_nan=False)]
Rssi = Annotated[float, Field(ge=-150, le=0, allow_inf_nan=False)]
Time = Annotated[
    StrictInt,
    AfterValidator(check_ms),
    Field(json_schema_extra={"minimum": MIN_T_MS, "exclusiveMaximum": MAX_T_MS}),
]
"""Milliseconds since the epoch; a time in seconds or microseconds is refused, naming its unit."""
TxId = Annotated[str, Field(min_length=1, max_length=100)]


class _Sample(BaseModel):
    model_config = ConfigDict(extra="ignore", frozen=True)

    t: Time


class RadioSample(_Sample):
    """One RSSI reading of a WiFi access point or BLE beacon."""

    id: TxId
    rssi: Rssi
    freq: Annotated[int, Field(ge=0, le=100_000)] | None = None
    last_seen: Time | None = None
    """When the access point was last heard (an Android ``ScanResult.timestamp``); ``t`` is
    then the time the scan completed."""
    tx_power: Annotated[float, Field(ge=-127, le=20, allow_inf_nan=False)] | None = None


class ImuSample(_Sample):
    """Inertial sample; any subset of the fields."""

    acc: Annotated[list[Finite], Field(min_length=3, max_length=3)] | None = None
    gyro: Annotated[list[Finite], Field(min_length=3, max_length=3)] | None = None
    mag: Annotated[list[Finite], Field(min_length=3, max_length=3)] | None = None
    rot: Annotated[list[Finite], Field(min_length=3, max_length=4)] | None = None

    @model_validator(mode="after")
    def _some_field(self) -> ImuSample:
        if self.acc is None and self.gyro is None and self.mag is None and self.rot is None:
            raise ValueError("an imu sample needs at least one of acc, gyro, mag, rot")
        return self


class UwbRange(_Sample):
    """A two-way range (m) to a UWB anchor."""

    anchor: TxId
    range: Annotated[float, Field(ge=0, le=1000, allow_inf_nan=False)]
    std: Annotated[float, Field(gt=0, le=100, allow_inf_nan=False)] | None = None


class UwbFix(_Sample):
    """A position fix computed elsewhere (e.g. by a UWB gateway)."""

    x: Finite
    y: Finite
    z: Finite = 0.0
    floor_id: Identifier | None = None
    std: Annotated[float, Field(gt=0, le=1000, allow_inf_nan=False)] | None = None


class BaroSample(_Sample):
    """Barometric pressure (hPa)."""

    hpa: Annotated[float, Field(gt=300, lt=1200, allow_inf_nan=False)]


class IngestBatch(BaseModel):
    """A device's batch: every list optional, at least one sample in total."""

    model_config = ConfigDict(extra="forbid")

    device_id: DeviceIdentifier
    site_id: Identifier
    wifi: list[RadioSample] = Field(default_factory=list)
    ble: list[RadioSample] = Field(default_factory=list)
    imu: list[ImuSample] = Field(default_factory=list)
    uwb: list[UwbRange] = Field(default_factory=list)
    uwb_fix: list[UwbFix] = Field(default_factory=list)
    baro: list[BaroSample] = Field(default_factory=list)

    @property
    def sample_count(self) -> int:
        """Return the number of samples of every kind."""
        return sum(len(getattr(self, k)) for k in SAMPLE_KINDS)

    @model_validator(mode="after")
    def _not_empty(self) -> IngestBatch:
        if self.sample_count == 0:
            raise ValueError("at least one sample is required")
        return self

    def max_t(self) -> int:
        """Return the latest sample time in the batch (-1 when screening left none)."""
        return max((s.t for k in SAMPLE_KINDS for s in getattr(self, k)), default=-1)


SAMPLE_KINDS = ("wifi", "ble", "imu", "uwb", "uwb_fix", "baro")
SAMPLE_MODELS: dict[str, type[BaseModel]] = {
    "wifi": RadioSample,
    "ble": RadioSample,
    "imu": ImuSample,
    "uwb": UwbRange,
    "uwb_fix": UwbFix,
    "baro": BaroSample,
}
"""The model of each sample list's items, for the per-sample validation policy."""


class Sighting(BaseModel):
    """A locator heard a tag."""

    model_config = ConfigDict(extra="ignore", frozen=True)

    t: Time
    tag_id: DeviceIdentifier
    rssi: Rssi


class LocatorBatch(BaseModel):
    """A fixed receiver's sightings of tags."""

    model_config = ConfigDict(extra="forbid")

    site_id: Identifier
    locator_id: TxId
    sightings: Annotated[list[Sighting], Field(min_length=1)]


class IngestAccepted(BaseModel):
    """Answer to an ingest: samples accepted, how many were too late to use, and what the
    per-sample policy dropped (an empty list when nothing was)."""

    accepted: int
    late: int
    dropped: list[DroppedSample] | None = None
    dropped_total: int | None = None


class IngestProcessed(IngestAccepted):
    """Answer to ``?wait=true``: every position emitted while processing the batch."""

    positions: list[Position]


class BulkIngest(BaseModel):
    """A gateway's body: many devices' batches, each validated and processed on its own."""

    model_config = ConfigDict(extra="forbid")

    batches: Annotated[list[IngestBatch], Field(min_length=1)]


class BatchError(BaseModel):
    """The contract's error object of a refused batch."""

    code: str
    message: str
    details: list[Any]


class BatchResult(BaseModel):
    """One batch's result in a bulk answer: what the single ingest would have answered."""

    status: int
    accepted: int | None = None
    late: int | None = None
    dropped: list[DroppedSample] | None = None
    dropped_total: int | None = None
    positions: list[Position] | None = None
    error: BatchError | None = None
    retry_after_s: float | None = None


class BulkAnswer(BaseModel):
    """Answer to a bulk ingest: one result per batch, in the order sent."""

    results: list[BatchResult]
