"""Devices of a site and their filter snapshots; a device is known by (site, device id).

The same device id in two sites is two devices: every row here is keyed by both.
"""

from __future__ import annotations

from datetime import datetime

from sqlalchemy import BigInteger, LargeBinary, String
from sqlalchemy.orm import Mapped, mapped_column

from app.core.db import Base, UtcDateTime
from app.core.time import utcnow


class Device(Base):
    """A device that has reported to a site: when it was last heard and up to which time."""

    __tablename__ = "devices"

    site_id: Mapped[str] = mapped_column(String(64), primary_key=True)
    device_id: Mapped[str] = mapped_column(String(128), primary_key=True)
    last_seen: Mapped[int] = mapped_column(BigInteger)
    """Wall clock (epoch ms) when the workers last processed a batch of it."""
    last_t: Mapped[int] = mapped_column(BigInteger)
    """Newest measurement time (device clock, epoch ms) received from it."""


class DeviceStateRecord(Base):
    """The latest serialised filter state of one device of one site."""

    __tablename__ = "device_states"

    site_id: Mapped[str] = mapped_column(String(64), primary_key=True)
    device_id: Mapped[str] = mapped_column(String(128), primary_key=True)
    t: Mapped[int] = mapped_column(BigInteger)
    snapshot: Mapped[bytes] = mapped_column(LargeBinary)
    updated_at: Mapped[datetime] = mapped_column(UtcDateTime(), default=utcnow, onupdate=utcnow)
