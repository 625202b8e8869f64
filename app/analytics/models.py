"""Zone events the engine emitted, kept so occupancy can be counted after the fact."""

from __future__ import annotations

from sqlalchemy import BigInteger, Index, Integer, String
from sqlalchemy.orm import Mapped, mapped_column

from app.core.db import Base


class ZoneEventRecord(Base):
    """A device's entry into or exit from a zone at measurement time ``t`` (ms)."""

    __tablename__ = "zone_events"
    __table_args__ = (
        # an event is stored once, however often its batch was processed
        Index(
            "ix_zone_events_site_zone_device_t",
            "site_id",
            "zone",
            "device_id",
            "t",
            "event",
            unique=True,
        ),
        Index("ix_zone_events_site_zone_t", "site_id", "zone", "t"),
    )

    id: Mapped[int] = mapped_column(BigInteger().with_variant(Integer, "sqlite"), primary_key=True)
    site_id: Mapped[str] = mapped_column(String(64))
    zone: Mapped[str] = mapped_column(String(200))
    device_id: Mapped[str] = mapped_column(String(128))
    floor_id: Mapped[str | None] = mapped_column(String(64))
    event: Mapped[str] = mapped_column(String(8))
    t: Mapped[int] = mapped_column(BigInteger)
