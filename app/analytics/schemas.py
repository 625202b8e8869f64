"""Occupancy and heatmap documents."""

from __future__ import annotations

from pydantic import BaseModel


class OccupancyBucket(BaseModel):
    """One bucket from ``t`` (ms): distinct devices inside, entries, summed dwell (s)."""

    t: int
    devices: int
    entries: int
    dwell_s: float


class Occupancy(BaseModel):
    """A zone's occupancy over ``[from, to)`` in buckets of ``bucket_s``."""

    zone: str
    bucket_s: int
    buckets: list[OccupancyBucket]


class Heatmap(BaseModel):
    """Device-seconds per cell, (ny, nx) with row 0 at ``origin[1]``; null outside the outline."""

    origin: list[float]
    cell: float
    shape: list[int]
    seconds: list[list[float | None]]
