"""Shared schema pieces: identifiers and pages."""

from __future__ import annotations

from typing import Annotated, Generic, Literal, TypeVar

from fastapi import Path, Query
from pydantic import BaseModel, StringConstraints

ID_PATTERN = r"^[A-Za-z0-9][A-Za-z0-9_.:-]{0,63}$"
Identifier = Annotated[str, StringConstraints(pattern=ID_PATTERN)]
DEVICE_ID_PATTERN = r"^[A-Za-z0-9][A-Za-z0-9_.:@-]{0,127}$"
DeviceIdentifier = Annotated[str, StringConstraints(pattern=DEVICE_ID_PATTERN)]

SiteIdPath = Annotated[str, Path(pattern=ID_PATTERN, description="Site identifier")]
FloorIdPath = Annotated[str, Path(pattern=ID_PATTERN, description="Floor identifier")]
DeviceIdPath = Annotated[
    str, Path(pattern=DEVICE_ID_PATTERN, description="Device identifier, unique within its site")
]
LimitQuery = Annotated[int, Query(ge=1, le=1000)]
OffsetQuery = Annotated[int, Query(ge=0, le=10**9)]

T = TypeVar("T")


class Page(BaseModel, Generic[T]):
    """A page of a listing: the items, the total count and where the page starts."""

    items: list[T]
    total: int
    limit: int
    offset: int


class DroppedSample(BaseModel):
    """A sample, or only its optional field, left out for an impossible value."""

    kind: str
    index: int
    field: str
    code: str
    reason: str
    dropped: Literal["sample", "field"]
