"""Positions the engine emitted, kept as history."""

from __future__ import annotations

from sqlalchemy import BigInteger, Boolean, Float, Index, Integer, String, false
from sqlalchemy.orm import Mapped, mapped_column

from app.core.db import Base


class PositionRecord(Base):
    """One emitted position of a device at measurement time ``t`` (ms).

    ``smoothed`` marks a position re-emitted refined by the positions after
    it; the live one of the same time stays beside it. ``odometry_x/y`` is
    the displacement (m) the device's steps measured since its filter
    started (null for filters that count no steps): what a full smoothing
    pass over the stored track weighs the positions against.
    """

    __tablename__ = "positions"
    # a position is stored once, however often its batch was processed
    __table_args__ = (
        Index("ix_positions_site_device_t", "site_id", "device_id", "t", "smoothed", unique=True),
        # a heatmap or a site's export reads one time range of every device of the site
        Index("ix_positions_site_t", "site_id", "t"),
    )

    id: Mapped[int] = mapped_column(BigInteger().with_variant(Integer, "sqlite"), primary_key=True)
    site_id: Mapped[str] = mapped_column(String(64))
    device_id: Mapped[str] = mapped_column(String(128))
    floor_id: Mapped[str | None] = mapped_column(String(64))
    t: Mapped[int] = mapped_column(BigInteger)
    x: Mapped[float] = mapped_column(Float)
    y: Mapped[float] = mapped_column(Float)
    z: Mapped[float] = mapped_column(Float)
    heading: Mapped[float | None] = mapped_column(Float)
    accuracy: Mapped[float] = mapped_column(Float)
    speed: Mapped[float | None] = mapped_column(Float)
    method: Mapped[str] = mapped_column(String(16))
    computed_at: Mapped[int] = mapped_column(BigInteger)
    smoothed: Mapped[bool] = mapped_column(Boolean, default=False, server_default=false())
    odometry_x: Mapped[float | None] = mapped_column(Float, default=None)
    odometry_y: Mapped[float | None] = mapped_column(Float, default=None)
